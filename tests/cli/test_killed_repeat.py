"""A real `vtr repeat` process SIGKILLed at several points: the map holds exactly the repeat vertices whose localization
records it holds (one transaction each), `localization.csv` holds the first of them (a row is written once its vertex
committed, so never one the map lacks), and `vtr map localizations` writes the run's whole `localization.csv` back,
row for row as the repeat wrote it. Before the records existed a kill between the map's commit and the row left the
map one vertex ahead of the CSV with no way to get that row back (issue 35)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from vtr.app.pipeline import teach_command
from vtr.cli import main
from vtr.config import Config
from vtr.map import Map

SUBPROCESS_TIMEOUT_S = 180
FRAMES = "1:40:2"  # 20 repeat frames against the teach of the even ones (every frame a keyframe)


@pytest.fixture(scope="module")
def taught(kitti_clip, tmp_path_factory):
    path = tmp_path_factory.mktemp("killed") / "route.vtrmap"
    teach_command(kitti_clip, path, "0:40:2", Config())
    return path


def _csv_lines(path: Path) -> list[str]:
    """The complete data rows of a CSV (a row cut by the kill, without its newline, is not one)."""
    text = path.read_text() if path.exists() else ""
    lines = text.split("\n")[:-1]  # the part after the last newline is unfinished (or empty)
    return lines[1:]  # the header


def _kill_after_rows(cmd: list[str], csv: Path, rows: int) -> None:
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
    )
    deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
    try:
        while len(_csv_lines(csv)) < rows:
            assert proc.poll() is None, f"the repeat ended before {rows} rows: {proc.stderr.read()}"
            assert time.monotonic() < deadline
            time.sleep(0.005)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
        assert proc.stderr is not None
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL


@pytest.mark.parametrize(("threads", "rows"), [(1, 1), (1, 4), (1, 9), (2, 3), (2, 7)])
def test_a_killed_repeat_leaves_one_record_per_vertex_and_its_rows_can_be_written_back(
    kitti_clip, taught, tmp_path, threads, rows
):
    path = tmp_path / "route.vtrmap"
    shutil.copyfile(taught, path)
    out = tmp_path / "out"
    csv = out / "localization.csv"
    _kill_after_rows(
        [
            sys.executable,
            "-m",
            "vtr",
            "repeat",
            str(kitti_clip),
            "--map",
            str(path),
            "--out",
            str(out),
            "--frames",
            FRAMES,
            "--threads",
            str(threads),
        ],
        csv,
        rows,
    )
    written = _csv_lines(csv)
    with Map.open(path) as m:
        [run] = [r for r in m.runs() if r.kind == "repeat"]
        assert run.state == "interrupted"
        vertices = [int(v) for v in m.vertex_ids(run.id)]
        records = m.localization_records(run.id)
        spatial = [e.from_id for e in m.edges(run.id, "spatial")]
    assert [r.leaf_id for r in records] == vertices  # exactly the vertices' records, in order
    assert spatial == [r.leaf_id for r in records if r.success]  # and the spatial edge of each success
    assert rows <= len(written) <= len(vertices)
    assert [int(line.split(",")[1]) for line in written] == vertices[: len(written)]  # the CSV: the first of them

    r = CliRunner().invoke(main, ["map", "info", str(path)])
    assert r.exit_code == 0, r.output
    assert f"`vtr map localizations {path} {run.id} --out DIR`" in r.output

    r = CliRunner().invoke(main, ["map", "localizations", str(path), str(run.id), "--out", str(out)])
    assert r.exit_code == 1 and "--force" in r.output  # the folder holds the killed run's files
    r = CliRunner().invoke(main, ["map", "localizations", str(path), str(run.id), "--out", str(out), "--force"])
    assert r.exit_code == 0, r.output
    assert f"{len(vertices)} rows" in r.output
    whole = _csv_lines(csv)
    assert [int(line.split(",")[1]) for line in whole] == vertices  # now one row per vertex
    assert whole[: len(written)] == written  # the rows the repeat wrote, as it wrote them


def test_a_finished_repeats_rows_are_the_ones_the_map_gives_back(kitti_clip, taught, tmp_path):
    path = tmp_path / "route.vtrmap"
    shutil.copyfile(taught, path)
    r = CliRunner().invoke(
        main,
        [
            "repeat",
            str(kitti_clip),
            "--map",
            str(path),
            "--out",
            str(tmp_path / "rep"),
            "--frames",
            "1:16:2",
            "--threads",
            "1",
        ],
    )
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["map", "localizations", str(path), "1", "--out", str(tmp_path / "back")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "back" / "localization.csv").read_text() == (tmp_path / "rep" / "localization.csv").read_text()
    r = CliRunner().invoke(main, ["map", "localizations", str(path), "0", "--out", str(tmp_path / "teach")])
    assert r.exit_code == 1 and "only repeats have localizations" in r.output
