"""``run.json`` and ``config.yaml`` beside every command's outputs (docs/architecture.md)."""

from __future__ import annotations

import json
import platform
import sys
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from ..config import Config

KEY_PACKAGES = ("vtr", "numpy", "scipy", "opencv-python-headless", "gtsam", "open3d", "rosbags")


def package_versions() -> dict[str, str]:
    out = {}
    for name in KEY_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def describe_inputs(paths: list[Path]) -> list[dict[str, Any]]:
    """Each input's path and size (bytes, summed over a folder's files)."""
    out = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            size = sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
        elif p.exists():
            size = p.stat().st_size
        else:
            size = None
        out.append({"path": str(p.resolve()), "bytes": size})
    return out


@dataclass
class RunLog:
    """Collects what a command did and writes ``run.json`` + ``config.yaml`` into ``out``."""

    out: Path
    command: str
    config: Config
    inputs: list[Path]
    start: float = field(default_factory=time.time)

    def write(self, summary: dict[str, Any]) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.yaml").write_text(self.config.to_yaml())
        doc = {
            "command": self.command,
            "argv": sys.argv,
            "python": platform.python_version(),
            "versions": package_versions(),
            "config": self.config.to_dict(),
            "inputs": describe_inputs(self.inputs),
            "start": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(self.start)),
            "end": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "summary": summary,
        }
        tmp = self.out / "run.json.tmp"
        tmp.write_text(json.dumps(doc, indent=2, default=_jsonable))
        tmp.replace(self.out / "run.json")


def _jsonable(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
