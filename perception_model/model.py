"""The geometric perception model ``p = c1 cos(c2 theta) exp(c3 alpha)`` (thesis eq. 7.5): the probability that a trunk
landmark becomes a localization inlier given its parallax ``alpha`` and view angle ``theta``, clipped to [0, 1] and cut
at the cosine's first zero, constants tied to a stored angle unit, every public method in radians; ``save``/``load``
as JSON (``ModelFileError`` naming the file). The definition, its documented range and the file:
docs/perception_model.md, "Model and fit" and "In code" (Model)."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import ModelFileError, PerceptionModelError, PerceptionModelWarning
from .inputs import MAX_MODEL_FILE_BYTES, read_small_text
from .outputs import replace_text
from .settings import UNIT_SCALE  # the units the constants may be expressed in (radians -> unit)

#: Thesis constants (c1, c2, c3) for angles in degrees (thesis §7.3.1, fit over 12 km, R^2 = 0.92).
THESIS_CONSTANTS_DEG = (0.424, 0.028, -0.145)
THESIS_R2 = 0.92

#: Documented angle range of the thesis data (radians): parallax 0-20 deg, view 0-50 deg.
DEFAULT_ALPHA_MAX_RAD = math.radians(20.0)
DEFAULT_THETA_MAX_RAD = math.radians(50.0)

#: JSON identification.
FILE_FORMAT = "perception-model"
FILE_VERSION = 1
REQUIRED_KEYS = ("c1", "c2", "c3", "angle_unit")

#: Grid resolution for checking the model over its documented range.
RANGE_CHECK_POINTS = 81
#: Tolerance on "probability outside [0, 1]" in that check.
RANGE_CHECK_TOL = 1e-9

FORMULA = "p = clip(c1*cos(c2*theta)*exp(c3*alpha), 0, 1); p = 0 where |c2*theta| > pi/2; angles in angle_unit"


def _finite_float(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PerceptionModelError(f"{name} must be a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise PerceptionModelError(f"{name} must be finite, got {out}")
    return out


@dataclass(frozen=True)
class PerceptionModel:
    """``p = clip(c1 cos(c2 theta) exp(c3 alpha), 0, 1)`` with constants in ``angle_unit``.

    ``alpha_max``/``theta_max`` (radians) document the angle range the constants are valid for.
    Public methods take angles in radians.
    """

    c1: float
    c2: float
    c3: float
    angle_unit: str = "deg"
    alpha_max: float = field(default=DEFAULT_ALPHA_MAX_RAD)
    theta_max: float = field(default=DEFAULT_THETA_MAX_RAD)

    def __post_init__(self) -> None:
        for name in ("c1", "c2", "c3", "alpha_max", "theta_max"):
            object.__setattr__(self, name, _finite_float(getattr(self, name), name))
        if self.angle_unit not in UNIT_SCALE:
            raise PerceptionModelError(f"angle_unit must be one of {sorted(UNIT_SCALE)}, got {self.angle_unit!r}")
        if self.c1 <= 0.0:
            raise PerceptionModelError(f"c1 must be > 0 (got {self.c1}): the model would predict no inliers")
        if not (0.0 < self.alpha_max <= math.pi and 0.0 < self.theta_max <= math.pi):
            raise PerceptionModelError("alpha_max and theta_max must be in (0, pi] radians")

    # ----------------------------------------------------------------- construction
    @classmethod
    def thesis(cls) -> PerceptionModel:
        """The thesis model c = (0.424, 0.028, -0.145), angles in degrees."""
        return cls(*THESIS_CONSTANTS_DEG, angle_unit="deg")

    @property
    def constants(self) -> NDArray[np.float64]:
        """``[c1, c2, c3]`` in the model's angle unit."""
        return np.array([self.c1, self.c2, self.c3])

    @property
    def unit_scale(self) -> float:
        """Factor converting radians to the model's angle unit."""
        return UNIT_SCALE[self.angle_unit]

    @property
    def constants_per_radian(self) -> tuple[float, float, float]:
        """``(c1, c2, c3)`` converted so that angles can be given in radians."""
        k = self.unit_scale
        return self.c1, self.c2 * k, self.c3 * k

    @property
    def theta_cutoff(self) -> float:
        """View angle (radians) beyond which ``p = 0``: the first zero of ``cos(c2 theta)``."""
        c2r = abs(self.constants_per_radian[1])
        return math.inf if c2r == 0.0 else 0.5 * math.pi / c2r

    def in_unit(self, angle_unit: str) -> PerceptionModel:
        """The same model with constants expressed for ``angle_unit``."""
        if angle_unit not in UNIT_SCALE:
            raise PerceptionModelError(f"angle_unit must be one of {sorted(UNIT_SCALE)}, got {angle_unit!r}")
        f = self.unit_scale / UNIT_SCALE[angle_unit]
        return PerceptionModel(self.c1, self.c2 * f, self.c3 * f, angle_unit, self.alpha_max, self.theta_max)

    # ----------------------------------------------------------------- evaluation
    def raw(self, alpha: ArrayLike, theta: ArrayLike) -> NDArray[np.float64]:
        """Unclipped, uncut ``c1 cos(c2 theta) exp(c3 alpha)`` for angles in radians."""
        c1, c2r, c3r = self.constants_per_radian
        a = np.asarray(alpha, dtype=np.float64)
        t = np.asarray(theta, dtype=np.float64)
        return c1 * np.cos(c2r * t) * np.exp(c3r * a)

    def probability(self, alpha: ArrayLike, theta: ArrayLike) -> NDArray[np.float64]:
        """Inlier probability in [0, 1] for parallax ``alpha`` and view ``theta`` in radians.

        Broadcasts ``alpha`` and ``theta``; NaN angles give NaN.
        """
        t = np.asarray(theta, dtype=np.float64)
        p = np.clip(self.raw(alpha, t), 0.0, 1.0)
        return np.where(np.abs(t) > self.theta_cutoff, 0.0, p)

    def probability_and_partials(
        self, alpha: ArrayLike, theta: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(p, dp/dalpha, dp/dtheta)`` with derivatives per radian, zero where clipped or cut."""
        c1, c2r, c3r = self.constants_per_radian
        a = np.asarray(alpha, dtype=np.float64)
        t = np.asarray(theta, dtype=np.float64)
        e = np.exp(c3r * a)
        raw = c1 * np.cos(c2r * t) * e
        inside = (np.abs(t) <= self.theta_cutoff) & (raw > 0.0) & (raw < 1.0)
        p = np.where(np.abs(t) > self.theta_cutoff, 0.0, np.clip(raw, 0.0, 1.0))
        dp_da = np.where(inside, c3r * raw, 0.0)
        dp_dt = np.where(inside, -c1 * c2r * np.sin(c2r * t) * e, 0.0)
        return p, dp_da, dp_dt

    # ----------------------------------------------------------------- checks
    def range_problems(self) -> list[str]:
        """Reasons the constants are unsuitable over the documented range (empty if fine).

        Checks the unclipped surface on a grid over ``[0, alpha_max] x [0, theta_max]``: values
        above 1 (clipped), and a sign change of ``cos(c2 theta)`` inside the range (p cut to 0).
        """
        problems = []
        a = np.linspace(0.0, self.alpha_max, RANGE_CHECK_POINTS)
        t = np.linspace(0.0, self.theta_max, RANGE_CHECK_POINTS)
        raw = self.raw(a[:, None], t[None, :])
        k = self.unit_scale
        if raw.max() > 1.0 + RANGE_CHECK_TOL:
            problems.append(
                f"the constants give probabilities up to {raw.max():.3g} > 1 inside the documented range "
                f"(alpha <= {self.alpha_max * k:.4g} {self.angle_unit}, theta <= {self.theta_max * k:.4g} "
                f"{self.angle_unit}); they are clipped to 1"
            )
        if self.theta_cutoff < self.theta_max:
            problems.append(
                f"cos(c2*theta) reaches 0 at theta = {self.theta_cutoff * k:.4g} {self.angle_unit}, "
                f"inside the documented range (theta <= {self.theta_max * k:.4g} {self.angle_unit}); "
                "probabilities there would be negative and are set to 0"
            )
        return problems

    # ----------------------------------------------------------------- files
    def to_dict(self, *, fit: dict[str, Any] | None = None, data: dict[str, Any] | None = None) -> dict[str, Any]:
        """JSON-ready dict: constants at top level, range in the model unit, optional sections."""
        k = self.unit_scale
        out: dict[str, Any] = {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "c1": self.c1,
            "c2": self.c2,
            "c3": self.c3,
            "angle_unit": self.angle_unit,
            "formula": FORMULA,
            "valid_range": {"alpha": [0.0, self.alpha_max * k], "theta": [0.0, self.theta_max * k]},
        }
        if fit is not None:
            out["fit"] = fit
        if data is not None:
            out["data"] = data
        return out

    @classmethod
    def from_dict(cls, d: Any, *, source: str = "<dict>") -> PerceptionModel:
        """Build a model from a ``to_dict``-style mapping; errors name ``source``."""
        if not isinstance(d, dict):
            raise ModelFileError(f"{source}: expected a JSON object at top level, got {type(d).__name__}")
        if "format" in d and d["format"] != FILE_FORMAT:
            raise ModelFileError(f"{source}: format {d['format']!r} is not {FILE_FORMAT!r}")
        version = d.get("version", FILE_VERSION)
        if isinstance(version, bool) or version != FILE_VERSION:
            raise ModelFileError(
                f"{source}: model file version {version!r} is not supported (this perception_model reads "
                f"version {FILE_VERSION}; refit or upgrade perception_model)"
            )
        missing = [key for key in REQUIRED_KEYS if key not in d]
        if missing:
            raise ModelFileError(f"{source}: missing key(s) {', '.join(missing)} (need {', '.join(REQUIRED_KEYS)})")
        unit = d["angle_unit"]
        if unit not in UNIT_SCALE:
            raise ModelFileError(f"{source}: angle_unit must be one of {sorted(UNIT_SCALE)}, got {unit!r}")
        kwargs: dict[str, Any] = {}
        rng = d.get("valid_range")
        if rng is not None:
            try:
                k = UNIT_SCALE[unit]
                kwargs["alpha_max"] = float(rng["alpha"][1]) / k
                kwargs["theta_max"] = float(rng["theta"][1]) / k
            except (KeyError, TypeError, IndexError, ValueError) as err:
                raise ModelFileError(
                    f"{source}: valid_range must be {{'alpha': [lo, hi], 'theta': [lo, hi]}} ({err})"
                ) from None
        try:
            return cls(d["c1"], d["c2"], d["c3"], unit, **kwargs)
        except PerceptionModelError as err:
            raise ModelFileError(f"{source}: {err}") from None

    def save(self, path: str | Path, *, fit: dict[str, Any] | None = None, data: dict[str, Any] | None = None) -> None:
        """Write the model as JSON (see ``to_dict``), whole and never through a link at ``path``
        (:func:`perception_model.outputs.replace_file`)."""
        text = json.dumps(self.to_dict(fit=fit, data=data), indent=2, allow_nan=False)
        replace_text(path, text + "\n")

    @classmethod
    def load(cls, path: str | Path, *, check_range: bool = True) -> PerceptionModel:
        """Read a model JSON file; ``ModelFileError`` on bad content, warnings on suspicious constants."""
        p = Path(path)
        try:
            text = read_small_text(p, MAX_MODEL_FILE_BYTES)
        except OSError as err:
            raise ModelFileError(f"{p}: cannot read model file ({err.strerror or err})") from None
        except UnicodeDecodeError:
            raise ModelFileError(f"{p}: not a model file (not UTF-8 text)") from None
        except ValueError as err:
            raise ModelFileError(f"{p}: {err}") from None
        try:
            d = json.loads(text)
        except json.JSONDecodeError as err:
            raise ModelFileError(f"{p}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
        except RecursionError:
            raise ModelFileError(f"{p}: nested too deeply to read (a model file is an object of constants)") from None
        model = cls.from_dict(d, source=str(p))
        if check_range:
            for problem in model.range_problems():
                warnings.warn(f"{p}: {problem}", PerceptionModelWarning, stacklevel=2)
        return model


def read_model_sections(path: str | Path) -> dict[str, Any]:
    """The whole JSON object of a model file (for its ``fit``/``data`` sections)."""
    try:
        out = json.loads(read_small_text(path, MAX_MODEL_FILE_BYTES))
    except (OSError, ValueError) as err:
        raise ModelFileError(f"{path}: cannot read model file ({err})") from None
    except RecursionError:
        raise ModelFileError(f"{path}: nested too deeply to read (a model file is an object of constants)") from None
    if not isinstance(out, dict):
        raise ModelFileError(f"{path}: expected a JSON object at top level")
    return out
