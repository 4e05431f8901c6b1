"""vtr: visual teach-and-repeat perception from stereo vision.

Public objects are re-exported lazily (module ``__getattr__``) so ``import vtr`` — and with it the
``vtr`` command's help page — stays light: numpy, OpenCV, SciPy and GTSAM load only when a module that
needs them is used.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

if TYPE_CHECKING:
    from .camera import StereoCamera
    from .config import Config
    from .errors import VtrError

_LAZY = {"Config": "config", "StereoCamera": "camera", "VtrError": "errors"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Config", "StereoCamera", "VtrError", "__version__"]
