"""Both fits keep c1 <= 1 (the model is a probability) and say when that bound is active."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import optimize

from perception_model.cli import main
from perception_model.fit import (
    C1_MAX,
    BinSpec,
    FitSettings,
    Samples,
    bin_observations,
    fit_binned,
    fit_mle,
    fit_observations,
    simulate_labels,
)
from perception_model.landmarks_file import write_landmarks
from perception_model.model import PerceptionModel
from perception_model.synthetic import sample_angles, simulate_observations

N_OBS = 60_000
C2, C3 = 0.028, -0.1  # per degree


def _data(c1: float, seed: int, n: int = N_OBS):
    """Labels from p = min(1, c1 cos(c2 theta) exp(c3 alpha)) at uniform angles (radians)."""
    rng = np.random.default_rng(seed)
    a, t = sample_angles(n, rng)
    y = simulate_labels(PerceptionModel(c1, C2, C3), a, t, rng)
    return a, t, y


@pytest.mark.parametrize("fitter", [fit_binned, fit_mle], ids=["binned", "mle"])
def test_c1_below_one_is_recovered_and_the_bound_is_inactive(fitter):
    r = fitter(Samples(*_data(0.9, seed=11)))
    c1 = r.intervals[0]
    assert not r.c1_at_bound and r.to_dict()["c1_at_bound"] is False
    assert abs(c1.estimate - 0.9) < 0.02 and c1.contains(0.9)
    assert r.model.c2 == pytest.approx(C2, rel=0.1) and r.model.c3 == pytest.approx(C3, rel=0.1)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(c1_true=st.floats(1.15, 1.6), seed=st.integers(0, 2**16))
def test_labels_that_push_c1_above_one_stop_at_the_bound(c1_true, seed):
    """Labels from a clipped model with c1 > 1: the p = 1 plateau makes an unconstrained fit exceed 1."""
    a, t, y = _data(c1_true, seed, n=30_000)
    assert _unconstrained_binned_c1(a, t, y) > 1.0  # the data do push c1 above 1
    for fitter in (fit_binned, fit_mle):
        r = fitter(Samples(a, t, y))
        assert r.model.c1 == C1_MAX and r.c1_at_bound, (fitter.__name__, r.model)
        assert r.intervals[0].estimate == 1.0 and r.intervals[0].high <= 1.0
        assert r.model.probability(a, t).max() <= 1.0
        assert r.to_dict()["c1_at_bound"] is True


def _unconstrained_binned_c1(a, t, y) -> float:
    """c1 of a weighted least-squares fit of c1 cos(c2 theta) exp(c3 alpha) to bin frequencies, no bounds."""
    b = bin_observations(Samples(a, t, y), BinSpec())
    a_deg, t_deg, w = np.degrees(b.alpha), np.degrees(b.theta), np.sqrt(b.count)

    def resid(c):
        return w * (c[0] * np.cos(c[1] * t_deg) * np.exp(c[2] * a_deg) - b.frequency)

    return float(optimize.least_squares(resid, [0.9, C2, C3]).x[0])


def test_bound_reported_in_fit_observations_cli_summary_and_model_file(tmp_path):
    obs = simulate_observations(PerceptionModel(1.4, C2, C3), 40_000, np.random.default_rng(2), name="hi")
    r = fit_observations(obs, FitSettings(method="mle"))
    assert r.c1_at_bound and r.model.c1 == 1.0
    write_landmarks(tmp_path / "hi.parquet", obs)
    out = tmp_path / "model.json"
    res = CliRunner().invoke(main, ["fit", str(tmp_path / "hi.parquet"), "--out", str(out), "--method", "mle"])
    assert res.exit_code == 0, res.output
    assert "c1 is at its bound 1" in res.output
    saved = json.loads(out.read_text())
    assert saved["c1"] == 1.0 and saved["fit"]["c1_at_bound"] is True and saved["fit"]["c1_max"] == 1.0
    # an inner model: no bound line, flag false
    write_landmarks(tmp_path / "lo.csv", simulate_observations(PerceptionModel(0.7, C2, C3), 40_000,
                                                               np.random.default_rng(3), name="lo"))  # fmt: skip
    # the same model file again: fit refuses to replace it without --force (the output rule)
    res = CliRunner().invoke(main, ["fit", str(tmp_path / "lo.csv"), "--out", str(out), "--force"])
    assert res.exit_code == 0 and "at its bound" not in res.output
    assert json.loads(out.read_text())["fit"]["c1_at_bound"] is False
