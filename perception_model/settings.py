"""The package's settings, each written once: the fit's record and the thesis values of the chance constraint.

- :class:`FitSettings`: how a model is fitted and judged (estimator, unit of the constants, (alpha, theta)
  bins, hold-out split, intervals, calibration table). One unit: every angle is in radians (``*_rad``);
  the command line, which speaks degrees, converts once with :meth:`FitSettings.from_degrees`. Every field
  declares its domain beside its default; the record checks them all when it is built
  (``FitError``, the messages the fit has always used), so the fit receives settings already checked.
- :class:`BinSpec`: the (alpha, theta) grid of the binned fit and of binned R^2 (part of the record,
  :attr:`FitSettings.bins`).
- ``THESIS_L_MIN``, ``THESIS_C_BAR``: the default minimum inlier count and normal quantile of the chance
  constraint ``mu - c_bar sigma >= L_min`` (thesis §7.4); ``THESIS_PITCH_DOWN_RAD``: the camera pitch of the
  thesis simulations; ``UNIT_SCALE``: the units the model's constants may be expressed in.

Standard library only: a help page shows these defaults and must start without numpy.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

from .errors import FitError

#: Units the constants may be expressed in, and the factor from radians to that unit.
UNIT_SCALE = {"deg": 180.0 / math.pi, "rad": 1.0}

#: Thesis simulation settings (§7.4): minimum inliers and the c_bar multiplier (3 sigma).
THESIS_L_MIN = 30.0
THESIS_C_BAR = 3.0
#: Pitch of the camera below the horizon in the thesis simulations (§7.4), radians.
THESIS_PITCH_DOWN_RAD = math.radians(50.0)

Method = Literal["binned", "mle"]
CiMethod = Literal["sandwich", "bootstrap"]
#: The estimators (``binned``: the thesis protocol, weighted least squares on bin frequencies; ``mle``:
#: Bernoulli maximum likelihood) and the interval methods of the binned fit.
METHODS: tuple[Method, ...] = ("binned", "mle")
CI_METHODS: tuple[CiMethod, ...] = ("sandwich", "bootstrap")
#: A bootstrap needs at least this many replicates.
MIN_BOOTSTRAP = 2


# --------------------------------------------------------------------------- the rules, one each
def check_bins(alpha_width_rad: float, theta_width_rad: float, min_count: int) -> None:
    """Bin widths > 0 (radians) and a minimum count >= 1."""
    if not (alpha_width_rad > 0 and theta_width_rad > 0 and min_count >= 1):
        raise FitError("bin widths must be > 0 and min_count >= 1")


def check_angle_unit(angle_unit: str) -> None:
    """A key of ``UNIT_SCALE``."""
    if angle_unit not in UNIT_SCALE:
        raise FitError(f"angle_unit must be one of {sorted(UNIT_SCALE)}")


def check_method(method: str) -> None:
    """One of ``METHODS``."""
    if method not in METHODS:
        raise FitError(f"unknown method {method!r} (use 'binned' or 'mle')")


def check_ci(ci: str) -> None:
    """One of ``CI_METHODS``."""
    if ci not in CI_METHODS:
        raise FitError(f"unknown ci method {ci!r} (use 'sandwich' or 'bootstrap')")


def check_bootstrap(n_bootstrap: int) -> None:
    """At least ``MIN_BOOTSTRAP`` replicates (checked where a bootstrap runs)."""
    if n_bootstrap < MIN_BOOTSTRAP:
        raise FitError(f"bootstrap needs n_bootstrap >= {MIN_BOOTSTRAP}")


def check_holdout_fraction(fraction: float) -> None:
    """In [0, 1): some localizations stay to fit on."""
    if not 0.0 <= fraction < 1.0:
        raise FitError(f"holdout fraction must be in [0, 1), got {fraction}")


def check_confidence(confidence: float) -> None:
    """In (0, 1)."""
    if not 0.0 < confidence < 1.0:
        raise FitError(f"confidence must be in (0, 1), got {confidence}")


def check_calibration_bins(calibration_bins: int) -> None:
    """At least one predicted-probability bin."""
    if calibration_bins < 1:
        raise FitError(f"calibration_bins must be >= 1, got {calibration_bins}")


# --------------------------------------------------------------------------- records
@dataclass(frozen=True)
class FitSettings:
    """How a model is fitted and judged; angles in radians. Defaults: the thesis protocol (§7.3.1).

    Built once (by the command line from its options, by a caller in code), checked when built.
    """

    #: Estimator: one of ``METHODS``.
    method: Method = "binned"
    #: Unit of the fitted constants: a key of ``UNIT_SCALE``.
    angle_unit: str = "deg"
    #: Bin widths of the binned fit and of binned R^2 (> 0, radians): 1 deg parallax x 2.5 deg view.
    alpha_bin_rad: float = math.radians(1.0)
    theta_bin_rad: float = math.radians(2.5)
    #: Bins with fewer observations than this (>= 1) are left out of binned fits and R^2.
    min_bin_count: int = 10
    #: Fraction of the localizations held out for evaluation, in [0, 1).
    holdout_fraction: float = 0.2
    #: Seed of the hold-out split and of the bootstrap (any integer).
    seed: int = 0
    #: Intervals of the binned fit: one of ``CI_METHODS`` (MLE always uses the Fisher information).
    ci: CiMethod = "sandwich"
    #: Bootstrap replicates when ``ci="bootstrap"`` (>= ``MIN_BOOTSTRAP`` there).
    n_bootstrap: int = 200
    #: Confidence level of the intervals, in (0, 1).
    confidence: float = 0.95
    #: Equal-width predicted-probability bins of the calibration table (>= 1).
    calibration_bins: int = 10

    def __post_init__(self) -> None:
        check_method(self.method)
        check_angle_unit(self.angle_unit)
        check_bins(self.alpha_bin_rad, self.theta_bin_rad, self.min_bin_count)
        check_holdout_fraction(self.holdout_fraction)
        check_ci(self.ci)
        if self.ci == "bootstrap":
            check_bootstrap(self.n_bootstrap)
        check_confidence(self.confidence)
        check_calibration_bins(self.calibration_bins)

    @classmethod
    def from_degrees(cls, *, alpha_bin_deg: float, theta_bin_deg: float, **fields: Any) -> FitSettings:
        """The record from bin widths in degrees (the command line's unit), converted here once."""
        return cls(alpha_bin_rad=math.radians(alpha_bin_deg), theta_bin_rad=math.radians(theta_bin_deg), **fields)

    def replace(self, **changes: Any) -> FitSettings:
        """A copy with some fields changed (checked again)."""
        return dataclasses.replace(self, **changes)

    @property
    def alpha_bin_deg(self) -> float:
        return math.degrees(self.alpha_bin_rad)

    @property
    def theta_bin_deg(self) -> float:
        return math.degrees(self.theta_bin_rad)

    @property
    def bins(self) -> BinSpec:
        return BinSpec(self.alpha_bin_rad, self.theta_bin_rad, self.min_bin_count)


@dataclass(frozen=True)
class BinSpec:
    """Regular (alpha, theta) grid for binning (radians) and the minimum count of a used bin."""

    alpha_width: float = FitSettings.alpha_bin_rad
    theta_width: float = FitSettings.theta_bin_rad
    min_count: int = FitSettings.min_bin_count

    def __post_init__(self) -> None:
        check_bins(self.alpha_width, self.theta_width, self.min_count)


#: The thesis protocol: the settings of a fit or an evaluation when the caller gives none.
DEFAULT_SETTINGS = FitSettings()


__all__ = [
    "CI_METHODS",
    "DEFAULT_SETTINGS",
    "METHODS",
    "THESIS_C_BAR",
    "THESIS_L_MIN",
    "THESIS_PITCH_DOWN_RAD",
    "UNIT_SCALE",
    "BinSpec",
    "CiMethod",
    "FitSettings",
    "Method",
]
