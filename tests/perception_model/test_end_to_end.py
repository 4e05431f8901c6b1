"""The perception model end to end on imagery.

- A short synthetic aerial teach repeated at lateral and vertical offsets (``vtr.app.offsets``) writes
  landmarks.csv; both fits (``perception_model.analysis.analyse``) find the inlier probability
  falling with parallax (c3 < 0, its interval below 0) with finite R^2 and log-loss.
- ``perception-model constraint --map`` on a small KITTI teach map: one row per position, mu > 0,
  sigma >= 0, trunks follow the localizer's rule (here each taught vertex); the yaw convention; one-line errors.
"""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
from click.testing import CliRunner

from perception_model.analysis import analyse, table
from perception_model.map_landmarks import camera_rotation_from_yaw, yaw_pitch_of_axis
from perception_model.model import PerceptionModel

LENGTH_M = 12.0
RAMP_M = 3.0
OFFSETS = [(0.0, 0.0), (4.0, 2.0)]  # (lateral left, vertical up), metres
KITTI_TEACH = "0:12:2"


def test_synthetic_repeats_fit_falls_with_parallax(tmp_path):
    from vtr.app.offsets import repeat_name, run_offset_repeats

    rows = run_offset_repeats(tmp_path, [], [], LENGTH_M, ramp_m=RAMP_M, offsets=OFFSETS)
    assert [(r["lateral_m"], r["vertical_m"]) for r in rows] == OFFSETS
    assert all(r["localized"] > 0 for r in rows), rows
    files = [tmp_path / repeat_name(dy, dz) / "landmarks.csv" for dy, dz in OFFSETS]
    summary = analyse("synthetic", files, tmp_path, seed=0)
    print(table([summary]))
    assert summary["alpha_deg_percentiles"]["95"] > 5.0  # the offsets give real parallax
    for method in ("binned", "mle"):
        fit = summary["fits"][method]
        assert "error" not in fit, fit
        c3 = fit["c"]["c3"]
        assert c3["estimate"] < 0 and c3["high"] < 0, (method, c3)
        assert fit["falls_with_parallax_significant"]
        for key in ("r2_binned", "log_loss", "holdout_log_loss"):
            assert math.isfinite(fit[key]), (method, key, fit[key])
        assert (tmp_path / f"fit_{method}.png").stat().st_size > 10_000
        assert PerceptionModel.load(tmp_path / f"model_{method}.json").constants[2] == pytest.approx(c3["estimate"])
    report = table([summary])
    assert "synthetic binned" in report and "synthetic mle" in report


# --------------------------------------------------------------------------- constraint --map
@pytest.fixture(scope="module")
def kitti_map(tmp_path_factory, kitti_clip):
    from vtr.app.pipeline import teach_command
    from vtr.config import Config

    path = tmp_path_factory.mktemp("pm_map") / "route.vtrmap"
    teach_command(kitti_clip, path, KITTI_TEACH, Config())
    return path


def _run(args):
    from vtr.cli.perception_model import main  # the console script installed with vtr (the map commands)

    return CliRunner().invoke(main, [str(a) for a in args])


def _rows(text: str) -> list[dict[str, float]]:
    return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(io.StringIO(text))]


def test_constraint_on_a_taught_map(kitti_map, tmp_path):
    from vtr.map import Map

    with Map.open(kitti_map) as m:
        taught = m.taught_path()
    ids, T = taught.ids, taught.T_world_vertex
    # half a metre right of and 0.3 m ahead of every taught vertex (map frame: x right, y down, z forward)
    pos = T[:, :3, 3] + np.array([0.5, 0.0, 0.3])
    positions = tmp_path / "pos.csv"
    np.savetxt(positions, pos, delimiter=",", header="x,y,z", comments="")
    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    out = tmp_path / "c.csv"
    r = _run(["constraint", model, "--map", kitti_map, "--positions", positions, "--out", out])
    assert r.exit_code == 0, r.output
    assert "smallest margin" in r.stdout and "trunk" in r.stdout
    rows = _rows(out.read_text())
    assert len(rows) == len(pos)
    mu = np.array([row["mu"] for row in rows])
    sigma = np.array([row["sigma"] for row in rows])
    assert np.all(mu > 0) and np.all(sigma >= 0)
    assert [int(row["trunk_id"]) for row in rows] == [int(i) for i in ids]
    assert np.all([row["n_in_view"] <= row["n_landmarks"] for row in rows])
    assert np.allclose([row["g"] for row in rows], mu - 3 * sigma - 30)
    assert all(0 <= row["p_fail_exact"] <= 1 for row in rows)

    # CSV on stdout; with a yaw column: 180 deg looks back along -z, away from every trunk landmark
    yawed = tmp_path / "pos_yaw.csv"
    np.savetxt(
        yawed, np.column_stack([pos, np.full(len(pos), 180.0)]), delimiter=",", header="x,y,z,yaw_deg", comments=""
    )
    r = _run(["constraint", model, "--map", kitti_map, "--positions", yawed, "--out", "-", "--no-exact"])
    assert r.exit_code == 0, r.output
    back = _rows(r.stdout)
    assert len(back) == len(pos) and all(row["mu"] == 0 and row["n_in_view"] == 0 for row in back)
    # every trunk landmark (no image test): the model's view cut still leaves those behind at p = 0
    r = _run(["constraint", model, "--map", kitti_map, "--positions", positions, "--out", "-", "--all-landmarks"])
    assert r.exit_code == 0, r.output
    every = _rows(r.stdout)
    assert len(every) == len(rows)
    assert all(
        e["n_in_view"] == e["n_landmarks"] and e["mu"] >= row["mu"] - 1e-9 for e, row in zip(every, rows, strict=True)
    )


def test_constraint_map_errors_are_one_line(kitti_map, tmp_path):
    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    positions = tmp_path / "pos.csv"
    positions.write_text("x,y,z\n0,0,1\n")
    for args, match in (
        (["--map", tmp_path / "missing.vtrmap"], "no map at"),
        (["--map", model], "not a vtr map"),
        (["--map", kitti_map, "--taught-camera", "0,0,0"], "--taught-camera"),
    ):
        r = _run(["constraint", model, *args, "--positions", positions])
        assert r.exit_code == 1, r.output
        errors = [ln for ln in r.stderr.splitlines() if ln.startswith("perception-model: error:")]
        assert len(errors) == 1 and match in errors[0], r.stderr
        assert "Traceback" not in r.output


def test_yaw_convention_in_the_map_frame():
    R = camera_rotation_from_yaw(np.radians([0.0, 90.0, -30.0]), np.radians([0.0, 0.0, 50.0]))
    assert np.allclose(R[0], np.eye(3))
    assert np.allclose(R[1][:, 2], [-1.0, 0.0, 0.0])  # +90 deg looks left (-x) in x right, y down, z forward
    for Ri in R:
        assert np.allclose(Ri.T @ Ri, np.eye(3)) and np.isclose(np.linalg.det(Ri), 1.0)
        assert abs(Ri[1, 0]) < 1e-12  # no roll: image x stays horizontal
    yaw, pitch = yaw_pitch_of_axis(R[2][:, 2])
    assert np.isclose(yaw, np.radians(-30.0)) and np.isclose(pitch, np.radians(50.0))


def test_map_commands_live_on_the_vtr_side(kitti_map, tmp_path):
    """The package's command knows no maps (``--map`` never worked without vtr); vtr's declares and serves it."""
    from perception_model.cli import main as package_main

    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    positions = tmp_path / "pos.csv"
    positions.write_text("x,y,z\n0,0,1\n")
    args = ["constraint", str(model), "--map", str(kitti_map), "--positions", str(positions)]
    r = CliRunner().invoke(package_main, args)
    assert r.exit_code == 1 and "No such option '--map'" in r.stderr and "Traceback" not in r.output
    assert not [o for p in package_main.commands["constraint"].params for o in p.opts if "map" in o]
    assert "envelope" not in package_main.commands
    r = _run([*args, "--out", "-"])
    assert r.exit_code == 0, r.output
    assert r.stdout.splitlines()[0].startswith("index,x,y,z,yaw_deg,pitch_deg,trunk_id")


@pytest.mark.parametrize(
    "args, msg",
    [
        (["--step", "1e-4"], "grid cells a side"),  # was: grew to 24 GB, killed by the kernel
        (["--step", "1e-6"], "grid cells a side"),  # was: an allocation traceback
        (["--max", "1e9"], "--max 1e+09 m: at most"),  # was: an allocation traceback
        (["--max", "inf"], "--max"),
        (["--step", "5", "--max", "1"], "at most --max"),
        (["--l-min", "-5"], "l_min must be"),
    ],
)
def test_envelope_grid_and_bounds_have_a_domain(kitti_map, tmp_path, args, msg):
    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    r = _run(["envelope", model, "--map", kitti_map, "--out", tmp_path / "env", *args])
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and msg in lines[0], r.stderr
    assert not (tmp_path / "env" / "envelope.csv").exists()


def test_envelope_never_writes_through_a_planted_link(kitti_map, tmp_path):
    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    out = tmp_path / "env"
    out.mkdir()
    (out / "envelope.csv").symlink_to(victim)
    r = _run(["envelope", model, "--map", kitti_map, "--out", out, "--step", "0.5", "--max", "2", "--force"])
    assert r.exit_code == 1 and "symbolic link" in r.stderr and victim.read_text() == "keep", r.output


def test_envelope_on_a_taught_map(kitti_map, tmp_path):
    from vtr.app.perception import ENVELOPE_BISECTIONS, _bound, _read
    from vtr.map import Map

    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    out = tmp_path / "env"
    r = _run(["envelope", model, "--map", kitti_map, "--out", out, "--step", "0.5", "--max", "10"])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((out / "envelope.csv").open()))
    with Map.open(kitti_map) as m:
        ids = m.taught_path().ids
    assert [int(row["vertex_id"]) for row in rows] == [int(i) for i in ids]
    assert (out / "envelope.png").stat().st_size > 10_000
    # the reported distance is the last offset that keeps mu - 3 sigma >= L_min before the first crossing
    vertices, camera, _ = _read(kitti_map)
    m = PerceptionModel.thesis()
    checked = 0
    for v, row in zip(vertices, rows, strict=True):
        d = float(row["left_m"])
        if int(row["left_capped"]) or d == 0.0:
            continue
        R = v.T_map_camera[:3, :3]
        left_map = -R[:, 0]  # level KITTI camera: the vehicle's left is the camera's -x
        c = v.T_map_camera[:3, 3]
        inside = _bound(m, v, camera, (c + d * left_map)[None], 30.0, 3.0)[0]
        beyond = _bound(m, v, camera, (c + (d + 0.5 / 2**ENVELOPE_BISECTIONS + 1e-9) * left_map)[None], 30.0, 3.0)[0]
        assert inside >= 30.0 > beyond
        checked += 1
    assert checked > 0


def test_envelope_marks_where_the_model_extrapolates(kitti_map, tmp_path):
    """A bound resting on landmarks seen beyond the model's valid angle range is marked extrapolated (CSV column and
    a warning); a model valid for every angle marks nothing."""
    import math

    narrow, wide = tmp_path / "narrow.json", tmp_path / "wide.json"
    base = PerceptionModel.thesis()
    PerceptionModel(base.c1, base.c2, base.c3, base.angle_unit, math.radians(0.5), math.radians(5.0)).save(narrow)
    PerceptionModel(base.c1, base.c2, base.c3, base.angle_unit, math.pi, math.pi).save(wide)
    counts = {}
    for name, model in (("narrow", narrow), ("wide", wide)):
        out = tmp_path / name
        r = _run(["envelope", model, "--map", kitti_map, "--out", out, "--step", "0.5", "--max", "20"])
        assert r.exit_code == 0, r.output
        rows = list(csv.DictReader((out / "envelope.csv").open()))
        counts[name] = sum(int(row[f"{d}_extrapolated"]) for row in rows for d in ("left", "right", "up", "down"))
        assert ("valid range" in r.stderr) == (counts[name] > 0)
    assert counts["wide"] == 0 and counts["narrow"] > 0


def test_envelope_work_is_bounded_before_it_starts_and_reports_progress(kitti_map, tmp_path, monkeypatch):
    """`envelope --step 0.001` on a 51-vertex map ran for many minutes without a word: the worst-case work
    (vertices x 4 x max/step) is refused before any is done, naming a step that passes; a run reports progress."""
    import vtr.app.perception as perception

    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    n = len(perception._read(kitti_map)[0])
    monkeypatch.setattr(perception, "ENVELOPE_MAX_EVALUATIONS", n * 4 * 100)  # 100 cells per direction
    r = _run(["envelope", model, "--map", kitti_map, "--out", tmp_path / "env", "--step", "0.01", "--max", "2"])
    assert r.exit_code == 1, r.output
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "--step 0.01 m" in line and f"on {n} vertices" in line, line
    suggested = float(line.split("use --step ")[1].split(" m")[0])
    perception.check_envelope_work(n, suggested, 2.0)  # the advice passes
    assert not (tmp_path / "env" / "envelope.csv").exists()
    r = _run(["envelope", model, "--map", kitti_map, "--out", tmp_path / "env", "--step", str(suggested), "--max", "2"])
    assert r.exit_code == 0, r.output
    assert f"envelope: {n}/{n} vertices" in r.stderr
