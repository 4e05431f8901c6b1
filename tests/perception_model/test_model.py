"""PerceptionModel: formula, units, clipping/cut, partial derivatives, JSON files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from perception_model.errors import ModelFileError, PerceptionModelError, PerceptionModelWarning
from perception_model.model import THESIS_CONSTANTS_DEG, PerceptionModel

D = math.radians


def test_thesis_formula_in_degrees_with_radian_api():
    m = PerceptionModel.thesis()
    assert m.constants.tolist() == list(THESIS_CONSTANTS_DEG)
    assert m.probability(0.0, 0.0) == pytest.approx(0.424)
    expected = 0.424 * math.cos(0.028 * 20.0) * math.exp(-0.145 * 10.0)
    assert m.probability(D(10.0), D(20.0)) == pytest.approx(expected, rel=1e-14)


def test_unit_conversion_keeps_probabilities():
    m = PerceptionModel.thesis()
    r = m.in_unit("rad")
    assert r.angle_unit == "rad" and r.c2 == pytest.approx(0.028 * 180 / math.pi)
    a, t = np.meshgrid(np.linspace(0, D(20), 9), np.linspace(0, D(50), 11))
    assert np.allclose(r.probability(a, t), m.probability(a, t), rtol=1e-13)
    assert r.in_unit("deg").constants == pytest.approx(m.constants)


def test_clip_and_view_cut():
    big = PerceptionModel(2.0, 0.028, -0.145)
    assert big.probability(0.0, 0.0) == 1.0
    m = PerceptionModel.thesis()
    cut = m.theta_cutoff
    assert math.degrees(cut) == pytest.approx(0.5 * math.pi / 0.028)  # 56.1 deg
    assert m.probability(0.0, cut * 0.999) > 0.0
    assert m.probability(0.0, cut * 1.001) == 0.0
    # without the cut cos(c2 theta) would be positive again for landmarks behind the camera
    assert m.raw(0.0, D(175.0)) > 0.0 and m.probability(0.0, D(175.0)) == 0.0
    assert np.isnan(m.probability(np.nan, 0.1))


def test_partials_match_finite_differences_and_vanish_when_clipped():
    m = PerceptionModel.thesis()
    a = np.array([0.01, 0.1, 0.3])
    t = np.array([0.05, 0.4, 0.8])
    p, da, dt = m.probability_and_partials(a, t)
    h = 1e-7
    assert np.allclose(da, (m.probability(a + h, t) - m.probability(a - h, t)) / (2 * h), rtol=1e-6)
    assert np.allclose(dt, (m.probability(a, t + h) - m.probability(a, t - h)) / (2 * h), rtol=1e-6)
    big = PerceptionModel(2.0, 0.028, -0.145)
    p, da, dt = big.probability_and_partials(0.01, 0.05)
    assert p == 1.0 and da == 0.0 and dt == 0.0
    p, da, dt = m.probability_and_partials(0.01, m.theta_cutoff + 0.1)
    assert p == 0.0 and da == 0.0 and dt == 0.0


@pytest.mark.parametrize(
    "bad", [dict(c1=0.0), dict(c1=-0.1), dict(c2=math.nan), dict(c3=math.inf), dict(angle_unit="grad")]
)
def test_constructor_rejects_bad_constants(bad):
    kwargs = dict(c1=0.4, c2=0.028, c3=-0.145, angle_unit="deg") | bad
    with pytest.raises(PerceptionModelError):
        PerceptionModel(**kwargs)


def test_save_load_roundtrip(tmp_path):
    m = PerceptionModel(0.41, 0.027, -0.15, "deg", alpha_max=D(25), theta_max=D(45))
    path = tmp_path / "model.json"
    m.save(path, fit={"method": "binned", "r2": 0.9}, data={"n_observations": 10})
    d = json.loads(path.read_text())
    assert {k: d[k] for k in ("c1", "c2", "c3", "angle_unit")} == {
        "c1": 0.41,
        "c2": 0.027,
        "c3": -0.15,
        "angle_unit": "deg",
    }
    assert d["valid_range"]["alpha"][1] == pytest.approx(25.0) and d["fit"]["r2"] == 0.9
    back = PerceptionModel.load(path)
    assert back == m


@pytest.mark.parametrize(
    "text, match",
    [
        ('{"c2": 0.028, "c3": -0.145, "angle_unit": "deg"}', "missing key"),
        ('{"c1": NaN, "c2": 0.028, "c3": -0.145, "angle_unit": "deg"}', "finite"),
        ('{"c1": "0.4", "c2": 0.028, "c3": -0.145, "angle_unit": "deg"}', "number"),
        ('{"c1": 0.4, "c2": 0.028, "c3": -0.145, "angle_unit": "gon"}', "angle_unit"),
        ('{"c1": 0.4, "c2": 0.028, ', "not valid JSON"),
        ("[0.4, 0.028, -0.145]", "JSON object"),
        (
            '{"c1": 0.4, "c2": 0.028, "c3": -0.145, "angle_unit": "deg", "valid_range": {"alpha": 3}}',
            "valid_range",
        ),
    ],
)
def test_load_errors_name_the_file(tmp_path, text, match):
    path = tmp_path / "bad_model.json"
    path.write_text(text)
    with pytest.raises(ModelFileError, match=match) as info:
        PerceptionModel.load(path)
    assert "bad_model.json" in str(info.value)
    with pytest.raises(ModelFileError, match="cannot read"):
        PerceptionModel.load(tmp_path / "missing.json")


def test_load_warns_when_probabilities_leave_unit_interval(tmp_path):
    path = tmp_path / "big.json"
    path.write_text('{"c1": 1.5, "c2": 0.028, "c3": -0.145, "angle_unit": "deg"}')
    with pytest.warns(PerceptionModelWarning, match=r"big\.json.*> 1"):
        PerceptionModel.load(path)
    path.write_text('{"c1": 0.4, "c2": 0.05, "c3": -0.145, "angle_unit": "deg"}')
    with pytest.warns(PerceptionModelWarning, match=r"big\.json.*reaches 0"):
        PerceptionModel.load(path)
    assert PerceptionModel.thesis().range_problems() == []
