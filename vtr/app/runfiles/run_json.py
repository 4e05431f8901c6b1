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

from ...config import Config

STATUS_FINISHED = "finished"  # every output written; run.json is written last, so its presence means this
STATUS_FAILED = "failed"  # the run stopped on an error (``error`` holds it); its outputs are incomplete
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

    def write(self, summary: dict[str, Any], status: str = STATUS_FINISHED, error: str | None = None) -> None:
        """Write ``run.json`` (atomically: a temporary file renamed) and ``config.yaml``. Commands call it
        after every other output (through
        :class:`~vtr.app.outputs.OutputFolder`: never through a link), so a run killed before the end has no
        run.json."""
        from ..outputs import OutputFolder  # here: it pulls in vtr.io (numpy, OpenCV)

        self.out.mkdir(parents=True, exist_ok=True)
        folder = OutputFolder(self.out)
        folder.write_text("config.yaml", self.config.to_yaml())
        doc = {
            "command": self.command,
            "status": status,
            "argv": sys.argv,
            "python": platform.python_version(),
            "versions": package_versions(),
            "config": self.config.to_dict(),
            "inputs": describe_inputs(self.inputs),
            "start": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(self.start)),
            "end": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "summary": summary,
        }
        if error is not None:
            doc["error"] = error
        folder.write_text("run.json", json.dumps(doc, indent=2, default=_jsonable))  # a temporary file, renamed


def read_run(out: Path) -> dict[str, Any] | None:
    """The ``run.json`` in folder ``out``, or None when there is none (or it is unreadable: an interrupted write).
    Read back only when vtr made it (:meth:`vtr.app.outputs.OutputFolder.read_own`: a symbolic link there is
    an ``OutputError``, never followed)."""
    from ..outputs import OutputFolder  # here: see write()

    try:
        data = OutputFolder(Path(out)).read_own("run.json")
        if data is None:
            return None
        doc = json.loads(data)
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def run_status(out: Path) -> str | None:
    """``finished`` / ``failed`` from ``out/run.json``; None when the folder holds no complete run.json.
    (run.json files written before the status field existed are finished ones.)"""
    doc = read_run(out)
    if doc is None:
        return None
    return str(doc.get("status", STATUS_FINISHED))


def _jsonable(o: Any) -> Any:
    import numpy as np  # here: run.json readers need no numpy

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
