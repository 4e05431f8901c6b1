"""Summaries say what they mean: a fit the data cannot identify is refused as such (not printed as a result),
a refusal off the route is counted apart from a miss, and no figure is printed as `nan %`."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from perception_model.errors import FitError
from perception_model.fit import fit_observations
from perception_model.landmarks_file import read_landmarks
from vtr.app.evaluation import localization_integrity

HEADER = "t_ns,leaf_id,trunk_id,landmark_id,inlier,parallax_deg,view_deg,range_m,matched\n"


def write_obs(path, theta_low_deg, theta_high_deg, n=20_000, seed=0):
    rng = np.random.default_rng(seed)
    alpha = rng.uniform(0, 20, n)
    theta = rng.uniform(theta_low_deg, theta_high_deg, n)
    inlier = rng.random(n) < 0.8 * np.cos(np.radians(theta)) * np.exp(-0.05 * alpha)
    with open(path, "w") as f:
        f.write(HEADER)
        for i in range(n):
            f.write(f"{(i // 50) * 10**8},{i // 50},0,{i},{int(inlier[i])},{alpha[i]:.5f},{theta[i]:.5f},10,1\n")
    return path


@pytest.mark.parametrize(
    "low, high, what",
    [(0.3, 0.3, "singular"), (0.3, 0.6, "c2 = ")],
    ids=["one view angle", "view angles within 0.3 deg"],
)
def test_an_unidentifiable_fit_is_refused_naming_the_constant(tmp_path, low, high, what):
    obs = read_landmarks(write_obs(tmp_path / "in.csv", low, high))
    with pytest.raises(FitError, match=f"cannot identify .*c2.*{what}"):
        fit_observations(obs)
    r = subprocess.run(
        [sys.executable, "-m", "vtr.cli.perception_model", "fit", tmp_path / "in.csv", "--out", tmp_path / "O"],
        capture_output=True,
        text=True,
    )
    errors = [ln for ln in r.stderr.splitlines() if ": warning:" not in ln]
    assert r.returncode == 1 and len(errors) == 1 and "not a result" in errors[0], r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "O" / "model.json").exists()


def test_a_fit_over_a_range_of_angles_is_still_a_result(tmp_path):
    result = fit_observations(read_landmarks(write_obs(tmp_path / "in.csv", 0.0, 60.0)))
    assert result.unidentifiable == ()
    assert max(result.effect_of_one_std_err().values()) < 1.0


def test_one_view_angle_row_plots_without_contours(tmp_path):
    """MLE on data in one view-angle bin was a result, then the figure raised a matplotlib TypeError."""
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "vtr.cli.perception_model",
            "fit",
            write_obs(tmp_path / "in.csv", 0.3, 0.6),
            "--out",
            tmp_path / "O",
            "--method",
            "mle",
        ],
        capture_output=True,
        text=True,
    )
    assert "Traceback" not in r.stderr
    if r.returncode == 0:
        assert (tmp_path / "O" / "fit.png").stat().st_size > 10_000
    else:
        assert "cannot identify" in r.stderr


def test_refusals_off_the_route_are_counted_apart_from_misses():
    eye = np.eye(4)
    T = np.stack([eye] * 5)
    cov = np.stack([np.eye(6) * 1e-4] * 5)
    success = np.array([True, True, False, False, True])
    off_route = np.array([False, False, True, True, False])  # two refusals beyond the end of the route
    integ = localization_integrity(success, T, cov, T.copy(), off_route)
    assert (integ.correct, integ.refused_off_route, integ.missed) == (3, 2, 0)
    assert integ.rate_after == 1.0  # refusals are not "not correct"
    text = str(integ)
    assert "3 of 3 attempts on the route correct, 2 refused as off the route" in text and "0 missed" in text
    nothing = localization_integrity(np.zeros(3, bool), T[:3], cov[:3], T[:3].copy(), np.zeros(3, bool))
    assert "nan" not in str(nothing) and "3 missed" in str(nothing) and "not judged" in str(nothing)
