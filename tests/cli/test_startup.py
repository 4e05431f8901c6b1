"""Start-up stays cheap: a help page imports no numerical library (the heavy modules load where used).

Speed itself is measured by tools/bench_startup.py (no timed assertion here); this checks the cause.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

HEAVY = (
    "numpy",
    "cv2",
    "scipy",
    "gtsam",
    "open3d",
    "numba",
    "matplotlib",
    "dask",
    "distributed",
    "pyarrow",
    "tqdm",
    "yaml",
    "rosbags",
    "osqp",
)


def imported_modules(*args: str) -> set[str]:
    """Top-level names of every module a fresh ``python -X importtime ARGS`` process imports."""
    r = subprocess.run([sys.executable, "-X", "importtime", *args], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    names = set()
    for line in r.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            names.add(line.rsplit("|", 1)[1].strip().split(".")[0])
    assert "click" in names  # the parse did read the import list
    return names


@pytest.mark.parametrize(
    "args",
    [
        ("-m", "vtr", "--help"),
        ("-m", "vtr", "odometry", "--help"),
        ("-m", "vtr", "repeat", "--help"),
        ("-m", "vtr", "--version"),
        ("-m", "vtr.cli.perception_model", "--help"),
        ("-m", "vtr.cli.perception_model", "fit", "--help"),
    ],
)
def test_help_imports_no_heavy_module(args):
    heavy = sorted(imported_modules(*args) & set(HEAVY))
    assert not heavy, f"{' '.join(args)} imports {heavy}"


def test_import_vtr_is_light_but_names_still_resolve():
    code = (
        f"import sys, vtr; heavy = [m for m in {HEAVY!r} if m in sys.modules]; "
        "from vtr import Config, VtrError; print(heavy, Config.__name__, VtrError.__name__)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    heavy, *names = r.stdout.rsplit(" ", 2)
    assert names == ["Config", "VtrError\n"] and "numpy" not in heavy and "cv2" not in heavy
