"""vtr: visual teach-and-repeat perception from stereo vision.

Public objects are re-exported lazily so ``import vtr`` stays light; heavy optional modules
(open3d, matplotlib) are imported only where used.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .camera import StereoCamera
from .config import Config
from .errors import VtrError

__all__ = ["Config", "StereoCamera", "VtrError", "__version__"]
