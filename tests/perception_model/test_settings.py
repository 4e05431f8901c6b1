"""The fit's settings record: one owner of the defaults and domains, checked when built, numpy-free."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from perception_model.errors import FitError
from perception_model.settings import THESIS_C_BAR, THESIS_L_MIN, BinSpec, FitSettings


def test_defaults_are_the_thesis_protocol_in_radians():
    s = FitSettings()
    assert (s.method, s.angle_unit, s.min_bin_count, s.holdout_fraction, s.ci) == ("binned", "deg", 10, 0.2, "sandwich")
    assert s.alpha_bin_rad == math.radians(1.0) and s.theta_bin_rad == math.radians(2.5)
    assert (s.alpha_bin_deg, s.theta_bin_deg) == (1.0, 2.5)  # the CLI's defaults round-trip exactly
    assert s.bins == BinSpec() and (THESIS_L_MIN, THESIS_C_BAR) == (30.0, 3.0)


def test_from_degrees_converts_once():
    s = FitSettings.from_degrees(alpha_bin_deg=2.0, theta_bin_deg=5.0, method="mle")
    assert s.bins == BinSpec(math.radians(2.0), math.radians(5.0), 10) and s.method == "mle"


@pytest.mark.parametrize(
    "changes, msg",
    [
        ({"method": "ols"}, "unknown method"),
        ({"angle_unit": "grad"}, "angle_unit must be one of"),
        ({"alpha_bin_rad": 0.0}, "bin widths must be > 0"),
        ({"min_bin_count": 0}, "min_count >= 1"),
        ({"holdout_fraction": 1.0}, "holdout fraction must be in [0, 1)"),
        ({"ci": "jackknife"}, "unknown ci method"),
        ({"ci": "bootstrap", "n_bootstrap": 1}, "n_bootstrap >= 2"),
        ({"confidence": 1.0}, "confidence must be in (0, 1)"),
        ({"calibration_bins": 0}, "calibration_bins must be >= 1"),
    ],
)
def test_domains_are_checked_when_the_record_is_built(changes, msg):
    with pytest.raises(FitError, match=msg.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
        FitSettings(**changes)
    with pytest.raises(FitError):
        FitSettings().replace(**changes)


def test_sandwich_intervals_do_not_need_bootstrap_replicates():
    assert FitSettings(n_bootstrap=1).n_bootstrap == 1


def test_settings_import_no_numpy():
    code = "import sys, perception_model.settings; print('numpy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"
