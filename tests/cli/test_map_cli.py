"""`vtr map info` and `vtr export-map` as a user runs them: outputs, and one-line errors."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from vtr.camera import StereoCamera
from vtr.cli import main
from vtr.map import MAP_FORMAT_VERSION, Map, vertex_id
from vtr.types import Features, StereoFrame

CAMERA = StereoCamera(fx=700.0, fy=700.0, cx=600.0, cy=180.0, baseline=0.5, width=1226, height=370)
N_FEATURES = 30


def frame(rng: np.random.Generator, index: int) -> StereoFrame:
    """N_FEATURES features, the first 20 with depth."""
    uv = rng.uniform(0, 300, (N_FEATURES, 2))
    u_right = uv[:, 0] - rng.uniform(2, 40, N_FEATURES)
    points = rng.uniform(-5, 5, (N_FEATURES, 3)) + [0, 0, 10]
    u_right[20:] = np.nan
    points[20:] = np.nan
    feats = Features(
        uv, np.zeros(N_FEATURES, np.int32), np.ones(N_FEATURES), rng.integers(0, 256, (N_FEATURES, 32), dtype=np.uint8)
    )
    return StereoFrame(index * 10**8, index, feats, u_right, points)


def translation(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, 3] = x, y
    return T


@pytest.fixture(scope="module")
def route_map(tmp_path_factory):
    """Teach of 5 vertices and a repeat of 3 localized against it: 8 vertices, 160 landmarks."""
    path = tmp_path_factory.mktemp("maps") / "route.vtrmap"
    rng = np.random.default_rng(0)
    with Map.create(path, CAMERA) as m:
        teach = m.begin_run("teach", source="datasets/kitti06_clip")
        for i in range(5):
            m.add_vertex(teach, i * 10**8, translation(float(i)), frame(rng, i))
            if i:
                m.add_edge(
                    vertex_id(teach, i - 1), vertex_id(teach, i), translation(1.0), np.eye(6) * 1e-4, "temporal", 80
                )
        rep = m.begin_run("repeat", source="odd frames")
        for i in range(3):
            v = m.add_vertex(rep, i * 10**8 + 5, translation(float(i)), frame(rng, i))
            m.add_edge(v.id, vertex_id(teach, i), translation(0.0, -0.3), np.eye(6) * 1e-3, "spatial", 40)
    return path


def vtr(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vtr", *map(str, args)], capture_output=True, text=True)


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_map_info(route_map):
    r = vtr("map", "info", route_map)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert f"format version: {MAP_FORMAT_VERSION}" in out
    assert "vertices: 8  edges: 7 (temporal 4, spatial 3)  landmarks: 160  features: 240" in out
    assert "size on disk:" in out and f"({route_map.stat().st_size} bytes)" in out
    assert "camera: 1226x370 fx=700.00" in out
    runs_part, experiences_part = out.split("\nexperiences")
    rows = [line.split() for line in runs_part.splitlines() if line.startswith("  ") and "source" not in line]
    assert rows == [
        ["0", "teach", "yes", "finished", "5", "datasets/kitti06_clip"],
        ["1", "repeat", "no", "finished", "3", "odd", "frames"],
    ]
    # the repeat as an experience: its 3 vertices localized, trusted, not used yet
    assert [line.split() for line in experiences_part.splitlines()[2:]] == [["1", "3", "/", "3", "yes", "0", "0"]]
    j = json.loads(invoke("map", "info", route_map, "--json").output)
    assert (j["vertices"], j["edges"], j["landmarks"], j["format_version"]) == (8, 7, 160, MAP_FORMAT_VERSION)
    assert [r["kind"] for r in j["run_list"]] == ["teach", "repeat"] and j["camera"]["fx"] == 700.0
    assert [(e["run"], e["localized"], e["trusted"]) for e in j["experiences"]] == [(1, 3, True)]


def test_export_map_writes_a_ply(route_map, tmp_path):
    ply = tmp_path / "cloud.ply"
    r = vtr("export-map", route_map, "--ply", ply)
    assert r.returncode == 0, r.stderr
    assert "run 0 (teach): 100 landmarks" in r.stdout and "run 1 (repeat): 60 landmarks" in r.stdout
    assert "map frame" in r.stdout and f"wrote 160 points to {ply}" in r.stdout
    header = ply.read_bytes().split(b"end_header")[0].decode()
    assert "element vertex 160" in header and "property uchar red" in header


def test_export_map_never_writes_through_a_link_or_over_its_map(route_map, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("the user's file")
    (tmp_path / "p.ply").symlink_to(victim)
    r = vtr("export-map", route_map, "--ply", tmp_path / "p.ply", "--force")
    assert r.returncode == 1 and "p.ply: is a symbolic link" in r.stderr and len(r.stderr.splitlines()) == 1
    assert victim.read_text() == "the user's file"
    (tmp_path / "map.ply").symlink_to(route_map)  # the map itself, by another name
    before = route_map.read_bytes()
    r = vtr("export-map", route_map, "--ply", tmp_path / "map.ply", "--force")
    assert r.returncode == 1 and len(r.stderr.splitlines()) == 1, r.stderr
    assert route_map.read_bytes() == before


def test_errors_are_one_line(route_map, tmp_path):
    r = vtr("map", "info", tmp_path / "missing.vtrmap")
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr == f"vtr: error: no map at {tmp_path / 'missing.vtrmap'}\n"

    junk = tmp_path / "junk.vtrmap"
    junk.write_text("hello")
    r = invoke("export-map", junk, "--ply", tmp_path / "x.ply")
    assert r.exit_code == 1 and r.stderr == f"vtr: error: {junk} is not a vtr map (not an SQLite database)\n"

    r = invoke("export-map", route_map, "--ply", tmp_path / "x.txt")
    assert r.exit_code == 1 and r.stderr.count("\n") == 1 and "must end in .ply" in r.stderr

    newer = tmp_path / "newer.vtrmap"
    newer.write_bytes(route_map.read_bytes())
    con = sqlite3.connect(newer)
    con.execute("UPDATE meta SET value = ? WHERE key = 'format_version'", (str(MAP_FORMAT_VERSION + 1),))
    con.commit()
    con.close()
    r = invoke("map", "info", newer)
    assert r.exit_code == 1 and r.stderr.count("\n") == 1
    assert f"{newer}: map format version {MAP_FORMAT_VERSION + 1}" in r.stderr
    assert f"reads only format version {MAP_FORMAT_VERSION}" in r.stderr

    empty = tmp_path / "empty.vtrmap"
    Map.create(empty, CAMERA).close()
    r = invoke("map", "info", empty)
    assert r.exit_code == 0 and "vertices: 0" in r.output and "runs: 0" in r.output
    r = invoke("export-map", empty, "--ply", tmp_path / "e.ply")
    assert r.exit_code == 1 and r.stderr == f"vtr: error: {empty}: the map has no landmarks to export\n"
