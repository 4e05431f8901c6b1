"""The perception-model command: fit / evaluate / constraint, and one-line errors with exit code 1."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from perception_model.cli import main
from perception_model.landmarks_file import write_landmarks as write_landmarks_csv
from perception_model.model import PerceptionModel
from perception_model.synthetic import ground_scene, simulate_observations


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("pm_cli")
    rng = np.random.default_rng(3)
    model = PerceptionModel.thesis()
    write_landmarks_csv(d / "run1.csv", simulate_observations(model, 30_000, rng, name="run1"))
    write_landmarks_csv(d / "run2.csv", simulate_observations(model, 8_000, rng, name="run2"))
    scene = ground_scene(300, rng)
    np.savetxt(d / "lm.csv", scene.landmarks, delimiter=",", header="x,y,z", comments="")
    np.save(d / "lm.npy", scene.landmarks)
    pos = np.column_stack([np.zeros(5), np.linspace(0, 6, 5), np.zeros(5), np.zeros(5)])
    np.savetxt(d / "pos.csv", pos, delimiter=",", header="x,y,z,yaw", comments="")
    np.savetxt(d / "pos_noyaw.csv", pos[:, :3], delimiter=",", header="x,y,z", comments="")
    return d


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _assert_one_line_error(result, match):
    assert result.exit_code == 1, result.output
    err = result.stderr.strip().splitlines()
    errors = [ln for ln in err if ln.startswith("perception-model: error:")]
    assert len(errors) == 1 and match in errors[0], result.stderr
    assert "Traceback" not in result.output


def test_fit_binned_with_plot_then_evaluate(data, tmp_path):
    out, fig = tmp_path / "model.json", tmp_path / "fit.png"
    r = _run(["fit", data / "run1.csv", "--out", out, "--plot", fig])
    assert r.exit_code == 0, r.output
    assert "c1 =" in r.stdout and "held out" in r.stdout and "calibration" in r.stdout
    d = json.loads(out.read_text())
    assert {"c1", "c2", "c3", "angle_unit", "fit", "data"} <= set(d)
    assert d["fit"]["method"] == "binned" and d["data"]["n_observations"] == 30_000
    assert fig.stat().st_size > 10_000 and fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert abs(d["c3"] / -0.145 - 1) < 0.15
    r = _run(["evaluate", out, data / "run2.csv", "--json", tmp_path / "ev.json"])
    assert r.exit_code == 0, r.output
    assert "log-loss" in r.stdout and "R^2" in r.stdout
    ev = json.loads((tmp_path / "ev.json").read_text())["evaluation"]
    assert ev["n"] == 8000 and 0.2 < ev["log_loss"] < 0.4


def test_fit_mle_in_radians(data, tmp_path):
    out = tmp_path / "m.json"
    r = _run(
        [
            "fit",
            data / "run1.csv",
            data / "run2.csv",
            "--out",
            out,
            "--method",
            "mle",
            "--unit",
            "rad",
            "--holdout",
            "0",
        ]
    )
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert d["angle_unit"] == "rad" and d["fit"]["ci_method"] == "fisher" and d["fit"]["holdout"] is None
    assert d["data"]["n_observations"] == 38_000


@pytest.mark.parametrize("lm", ["lm.csv", "lm.npy"])
def test_constraint_along_a_path(data, tmp_path, lm):
    out = tmp_path / "c.csv"
    model = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(model)
    r = _run(["constraint", model, "--landmarks", data / lm, "--positions", data / "pos.csv", "--out", out])
    assert r.exit_code == 0, r.output
    assert "smallest margin" in r.stdout
    rows = np.genfromtxt(out, delimiter=",", names=True)
    assert rows.shape == (5,) and np.all(np.diff(rows["mu"]) < 0)  # moving away from the taught camera
    assert np.allclose(rows["g"], rows["mu"] - 3 * rows["sigma"] - 30)
    assert np.all(rows["g_conservative"] <= rows["g"] + 1e-9)
    assert np.all((rows["p_fail_exact"] >= 0) & (rows["p_fail_exact"] <= 1))
    r2 = _run(
        [
            "constraint",
            model,
            "--landmarks",
            data / lm,
            "--positions",
            data / "pos_noyaw.csv",
            "--delta",
            "0.01",
            "--no-exact",
        ]
    )
    assert r2.exit_code == 0 and "c_bar = 2.326" in r2.stdout


def test_errors_are_one_line_with_exit_code_1(data, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t_ns,leaf_id,trunk_id,landmark_id,inlier,parallax_deg\n1,1,1,1,1,2.0\n")
    _assert_one_line_error(_run(["fit", bad, "--out", tmp_path / "m.json"]), "missing column")
    nan = tmp_path / "nan.csv"
    nan.write_text(
        "t_ns,leaf_id,trunk_id,landmark_id,inlier,parallax_deg,view_deg,range_m\n"
        "1,1,1,1,1,2.0,3.0,10\n1,1,1,2,0,NaN,3.0,10\n"
    )
    _assert_one_line_error(_run(["fit", nan, "--out", tmp_path / "m.json"]), "nan.csv, line 3")
    zeros = tmp_path / "zeros.csv"
    zeros.write_text(
        "t_ns,leaf_id,trunk_id,landmark_id,inlier,parallax_deg,view_deg,range_m\n"
        + "".join(f"{i},1,1,{i},0,{i * 0.1},{i * 0.3},10\n" for i in range(100))
    )
    _assert_one_line_error(_run(["fit", zeros, "--out", tmp_path / "m.json"]), "outliers")
    _assert_one_line_error(_run(["fit", tmp_path / "missing.csv", "--out", tmp_path / "m.json"]), "missing.csv")
    model = tmp_path / "nan_model.json"
    model.write_text('{"c1": NaN, "c2": 0.028, "c3": -0.145, "angle_unit": "deg"}')
    _assert_one_line_error(_run(["evaluate", model, data / "run2.csv"]), "nan_model.json")
    good = tmp_path / "thesis.json"
    PerceptionModel.thesis().save(good)
    from vtr.cli.perception_model import main as with_map  # --map lives in the script installed with vtr

    _assert_one_line_error(
        CliRunner().invoke(
            with_map, [str(a) for a in ["constraint", good, "--map", tmp_path, "--positions", data / "pos.csv"]]
        ),
        "is a directory",
    )
    _assert_one_line_error(  # the package's command knows no maps
        _run(["constraint", good, "--map", tmp_path, "--positions", data / "pos.csv"]), "No such option '--map'"
    )
    _assert_one_line_error(_run(["constraint", good, "--positions", data / "pos.csv"]), "Missing option '--landmarks'")
    _assert_one_line_error(
        CliRunner().invoke(with_map, [str(a) for a in ["constraint", good, "--positions", data / "pos.csv"]]),
        "exactly one",
    )
    _assert_one_line_error(
        _run(
            [
                "constraint",
                good,
                "--landmarks",
                data / "lm.csv",
                "--positions",
                data / "pos.csv",
                "--taught-camera",
                "1,2",
            ]
        ),
        "--taught-camera",
    )


def test_bad_model_constants_warn_with_file_name(data, tmp_path):
    big = tmp_path / "big.json"
    big.write_text('{"c1": 1.7, "c2": 0.028, "c3": -0.145, "angle_unit": "deg"}')
    r = _run(["evaluate", big, data / "run2.csv"])
    assert r.exit_code == 0
    assert "perception-model: warning: " in r.stderr and "big.json" in r.stderr and "> 1" in r.stderr


@pytest.mark.skipif(shutil.which("perception-model") is None, reason="entry point not installed")
def test_installed_entry_point_reports_errors_without_traceback(tmp_path):
    proc = subprocess.run(
        ["perception-model", "evaluate", str(tmp_path / "none.json"), str(tmp_path / "x.csv")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 1
    assert proc.stderr.startswith("perception-model: error:") and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    proc = subprocess.run(
        [sys.executable, "-m", "perception_model.cli", "--version"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 0 and "perception-model" in proc.stdout
