"""Outputs are never replaced silently (`export-trajectory`, `export-map` need --force, `convert`
refuses), and a closed map is inspected read-only: `map info`, `export-map` and the perception
constraint read it without writing anything beside it."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner
from test_map_cli import CAMERA, frame, translation

from vtr.cli import main
from vtr.map import Map, vertex_id
from vtr.types import Keyframe


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line(r, *needles):
    assert r.exit_code == 1 and r.stderr.count("\n") == 1 and r.stderr.startswith("vtr: error:"), r.stderr
    for n in needles:
        assert n in r.stderr, r.stderr


@pytest.fixture
def small_map(tmp_path):
    path = tmp_path / "maps" / "route.vtrmap"
    rng = np.random.default_rng(0)
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach", source="synthetic")
        for i in range(4):
            f = frame(rng, i)  # t_ns = i * 10**8
            m.add_keyframe(run, Keyframe(i, f, translation(float(i)), np.eye(6) * 1e-4, 50))
    return path


def test_export_trajectory_refuses_to_overwrite_without_force(tmp_path):
    tum = tmp_path / "traj_tum.txt"
    tum.write_text("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n")
    out = tmp_path / "traj.kitti"
    out.write_text("precious\n")
    one_line(invoke("export-trajectory", tum, out, "--to", "kitti"), f"{out}: already exists", "--force")
    assert out.read_text() == "precious\n"
    r = invoke("export-trajectory", tum, out, "--to", "kitti", "--force")
    assert r.exit_code == 0, r.output
    assert len(out.read_text().splitlines()) == 2
    folder = tmp_path / "folder"
    folder.mkdir()
    one_line(invoke("export-trajectory", tum, folder, "--to", "kitti", "--force"), "is a folder")


def test_export_map_refuses_to_overwrite_without_force(small_map, tmp_path):
    ply = tmp_path / "cloud.ply"
    ply.write_bytes(b"precious")
    one_line(invoke("export-map", small_map, "--ply", ply), f"{ply}: already exists", "--force")
    assert ply.read_bytes() == b"precious"
    r = invoke("export-map", small_map, "--ply", ply, "--force")
    assert r.exit_code == 0, r.output
    assert b"element vertex 80" in ply.read_bytes()[:400]


def test_convert_refuses_with_the_same_rule(kitti_clip, tmp_path):
    out = tmp_path / "clip.bag"
    out.write_bytes(b"precious")
    r = invoke("convert", kitti_clip, out, "--frames", "0:2", "--no-progress")
    one_line(r, f"{out}: already exists (not overwriting)")
    assert "--force" not in r.stderr and out.read_bytes() == b"precious"


def test_readers_write_nothing_beside_a_read_only_map(small_map, tmp_path):
    """(As root the permissions do not bind; that nothing is written beside or into the map is still
    checked. test_lifecycle opens through the immutable URI directly.)"""
    from vtr.app.perception import open_map

    folder = small_map.parent
    shutil.copyfile(small_map, tmp_path / "pristine.vtrmap")
    folder.chmod(0o555)
    small_map.chmod(0o444)
    try:
        r = invoke("map", "info", small_map)
        assert r.exit_code == 0, r.output
        assert ["0", "teach", "yes", "finished", "4", "synthetic"] in [line.split() for line in r.output.splitlines()]
        r = invoke("export-map", small_map, "--ply", tmp_path / "cloud.ply")
        assert r.exit_code == 0, r.output
        m = open_map(small_map)
        try:
            assert m.mode == "r" and len(m.taught_path().nearest(np.zeros(3), 2)) == 2
        finally:
            m.close()
        assert sorted(p.name for p in folder.iterdir()) == ["route.vtrmap"]
        assert small_map.read_bytes() == (tmp_path / "pristine.vtrmap").read_bytes()
        with Map.open(small_map) as m:
            assert vertex_id(0, 3) in m.vertex_ids(0)
    finally:
        folder.chmod(0o755)
        small_map.chmod(0o644)


def test_a_writer_on_a_read_only_folder_is_told_the_map_is_readable_and_how_to_use_it(
    small_map, tmp_path, permissions_bind
):
    """Appending to a map whose folder is read-only: one line saying it cannot write there and naming
    --read-only-map (it said "not a readable vtr map"); the map is untouched and still opens read-only."""
    folder = small_map.parent
    pristine = small_map.read_bytes()
    code = (
        "import sys\nfrom vtr.errors import MapError\nfrom vtr.map import Map\ntry:\n"
        "    Map.open(sys.argv[1], 'a').close()\nexcept MapError as err:\n    sys.exit(str(err))"
    )
    folder.chmod(0o555)
    try:
        for args in (
            [sys.executable, "-c", code, str(small_map)],
            [sys.executable, "-m", "vtr", "map", "prune", str(small_map)],
        ):
            r = subprocess.run(permissions_bind(args), capture_output=True, text=True, timeout=120)
            assert r.returncode != 0 and r.stderr.count("\n") == 1, r.stderr
            assert "cannot write it or create files beside it" in r.stderr and "--read-only-map" in r.stderr, r.stderr
        r = subprocess.run(
            permissions_bind([sys.executable, "-m", "vtr", "map", "info", str(small_map)]),
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 0, r.stderr
        assert sorted(p.name for p in folder.iterdir()) == ["route.vtrmap"]
        assert small_map.read_bytes() == pristine
    finally:
        folder.chmod(0o755)
