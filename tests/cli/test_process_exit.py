"""How a ``vtr`` process ends: a command leaves the objects alive at exit out of the interpreter's last garbage
collections (``vtr.cli.skip_final_collection``: about a second of a short run, ``tools/bench_processes.py``), and
what the process wrote is exactly what the library writes in a process that ends the ordinary way.

Speed is measured by tools/bench_processes.py (no timed assertion here); this checks the cause and the outputs.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vtr.app.pipeline import odometry_command, repeat_command, teach_command
from vtr.config import Config

ROOT = Path(__file__).resolve().parents[2]
SUBPROCESS_TIMEOUT_S = 300

FREEZE_COUNT_AT_EXIT = (
    "import atexit, gc, sys\n"
    "from vtr.cli import main\n"
    "before = gc.get_freeze_count()\n"
    "if sys.argv[1:]:\n"
    "    main.main(sys.argv[1:], standalone_mode=False)\n"
    "atexit._run_exitfuncs()\n"  # the exit handlers, as the interpreter runs them at exit
    "print(before, gc.get_freeze_count() > 0)\n"
)


def _freeze_at_exit(*args: str) -> str:
    r = subprocess.run(
        [sys.executable, "-c", FREEZE_COUNT_AT_EXIT, *args],
        capture_output=True,
        text=True,
        timeout=SUBPROCESS_TIMEOUT_S,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert r.returncode == 0, r.stderr
    return r.stdout.splitlines()[-1]


def test_a_command_skips_the_final_collection_and_an_import_does_not():
    assert _freeze_at_exit() == "0 False"  # `import vtr.cli` alone leaves the interpreter's exit as it is
    assert _freeze_at_exit("config") == "0 True"  # a command run: the heap is frozen by its exit handler


def _compare_outputs():
    spec = importlib.util.spec_from_file_location("compare_outputs", ROOT / "tools" / "compare_outputs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def taught(kitti_clip, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("taught") / "route.vtrmap"
    teach_command(kitti_clip, path, "0:16:2", Config())
    return path


@pytest.mark.parametrize("command", ["odometry", "repeat"])
def test_a_whole_process_writes_what_the_library_writes(kitti_clip, taught, tmp_path, command):
    """``python -m vtr CMD`` (which ends with the final collection skipped) and the library in this process give
    the same files: CSVs, trajectory, report, map rows, ``run.json`` without its clock."""
    frames, config = "1:16:2", Config().replace("features", threads=1)
    runs = {}
    for how in ("process", "library"):
        folder = tmp_path / how
        folder.mkdir()
        route = folder / "maps" / "route.vtrmap"
        route.parent.mkdir()
        shutil.copyfile(taught, route)
        out = folder / "out"
        if how == "library":
            if command == "odometry":
                odometry_command(kitti_clip, out, frames, config)
            else:
                repeat_command(kitti_clip, route, out, frames, config)
        else:
            args = [command, str(kitti_clip), "--frames", frames, "--out", str(out), "--threads", "1"]
            if command == "repeat":
                args += ["--map", str(route)]
            r = subprocess.run(
                [sys.executable, "-m", "vtr", *args],
                capture_output=True,
                text=True,
                timeout=SUBPROCESS_TIMEOUT_S,
                env={**os.environ, "PYTHONPATH": str(ROOT)},
            )
            assert r.returncode == 0, r.stderr
        runs[how] = folder
    compare = _compare_outputs()
    for part in ("out", "maps"):
        a, b = runs["process"] / part, runs["library"] / part
        files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
        assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
        assert files
        for rel in files:
            assert compare.differs(rel, a / rel, b / rel, runs["process"], runs["library"]) is None, rel
