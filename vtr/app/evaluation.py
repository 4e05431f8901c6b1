"""Trajectory accuracy against ground truth: KITTI-style relative errors over sub-segments.

``t_err`` is the mean translation error of the relative pose over every sub-segment of the given
lengths (percent of the length), ``r_err`` the mean rotation error (degrees per metre), as the
KITTI odometry benchmark defines them; ``end_pct`` the end-point error over the travelled distance.
The shipped clips are 10-60 m long, so the segments are 10-40 m (``SEGMENT_LENGTHS_M``); KITTI's benchmark
averages 100-800 m segments, so the figures are not comparable with its table. When the ground-truth path
is shorter than the shortest segment (or the frames are not a trajectory), no segment exists: the string
says so instead of printing NaN.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..geometry import inv_T, log_se3, rotation_angle
from ..navigation.localization import LocalizationStatus

if TYPE_CHECKING:
    from ..io.base import GroundTruth
    from ..navigation.localization import Localization

SEGMENT_LENGTHS_M = (10.0, 20.0, 30.0, 40.0)
KITTI_BENCHMARK_SEGMENTS = "100-800 m"


@dataclass(frozen=True)
class DriftMetrics:
    t_err_pct: float
    r_err_deg_per_m: float
    end_pct: float
    length_ratio: float  # estimated path length / true path length
    distance_m: float
    segments: int
    segment_lengths_m: tuple[float, ...] = SEGMENT_LENGTHS_M

    def to_dict(self) -> dict:
        d = asdict(self)
        d["segment_lengths_m"] = list(self.segment_lengths_m)
        return d

    @property
    def segments_text(self) -> str:
        """``10-40 m`` (or ``10 m``): the sub-segment lengths the errors average over."""
        lo, hi = min(self.segment_lengths_m), max(self.segment_lengths_m)
        return f"{lo:g} m" if lo == hi else f"{lo:g}-{hi:g} m"

    def __str__(self) -> str:
        if self.segments:
            relative = (
                f"t_err {self.t_err_pct:.3f} %  r_err {self.r_err_deg_per_m:.4f} deg/m over "
                f"{self.segments} sub-segments of {self.segments_text} (KITTI's benchmark averages "
                f"{KITTI_BENCHMARK_SEGMENTS}: not comparable)"
            )
        else:
            relative = (
                f"t_err, r_err not measured: the ground-truth path ({self.distance_m:.1f} m) holds no "
                f"sub-segment of {self.segments_text}"
            )
        end = (
            f"end {self.end_pct:.3f} % of {self.distance_m:.1f} m  path length x{self.length_ratio:.4f}"
            if self.distance_m > 0
            else "end error and path length not measured: the ground truth does not move"
        )
        return f"{relative}; {end}"


def path_length(T: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum())


def drift_metrics(T_est: np.ndarray, T_gt: np.ndarray, lengths: tuple[float, ...] = SEGMENT_LENGTHS_M) -> DriftMetrics:
    """KITTI-style drift of an estimated trajectory against ground truth (same frames, same order).

    Both are re-expressed relative to their first pose first.
    """
    T_est = inv_T(T_est[0]) @ T_est
    T_gt = inv_T(T_gt[0]) @ T_gt
    d = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1))]
    t_err, r_err = [], []
    for L in lengths:
        i = np.arange(len(T_gt))
        j = np.searchsorted(d, d + L)
        ok = j < len(T_gt)
        i, j = i[ok], j[ok]
        if len(i) == 0:
            continue
        rel_gt = inv_T(T_gt[i]) @ T_gt[j]
        rel_est = inv_T(T_est[i]) @ T_est[j]
        E = inv_T(rel_gt) @ rel_est
        t_err.append(np.linalg.norm(E[:, :3, 3], axis=1) / L)
        r_err.append(np.degrees(rotation_angle(E[:, :3, :3])) / L)
    dist = float(d[-1])
    n = int(sum(len(e) for e in t_err))
    return DriftMetrics(
        t_err_pct=float(100 * np.mean(np.concatenate(t_err))) if n else float("nan"),
        r_err_deg_per_m=float(np.mean(np.concatenate(r_err))) if n else float("nan"),
        end_pct=float(100 * np.linalg.norm(T_est[-1, :3, 3] - T_gt[-1, :3, 3]) / dist) if dist > 0 else float("nan"),
        length_ratio=path_length(T_est) / dist if dist > 0 else float("nan"),
        distance_m=dist,
        segments=n,
        segment_lengths_m=tuple(float(v) for v in lengths),
    )


def associate(t_est: np.ndarray, t_gt: np.ndarray, tolerance_ns: int = 20_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (estimate, ground truth) whose times agree within ``tolerance_ns``."""
    j = np.clip(np.searchsorted(t_gt, t_est), 1, len(t_gt) - 1)
    j = np.where(np.abs(t_gt[j - 1] - t_est) <= np.abs(t_gt[j] - t_est), j - 1, j)
    ok = np.abs(t_gt[j] - t_est) <= tolerance_ns
    return np.flatnonzero(ok), j[ok]


@dataclass(frozen=True)
class LocalizationErrors:
    """Errors of estimated ``T_leaf_trunk`` against ground truth (successful localizations only)."""

    translation_m: np.ndarray
    rotation_deg: np.ndarray

    @property
    def median_translation_m(self) -> float:
        return float(np.median(self.translation_m)) if len(self.translation_m) else float("nan")

    @property
    def median_rotation_deg(self) -> float:
        return float(np.median(self.rotation_deg)) if len(self.rotation_deg) else float("nan")

    def __str__(self) -> str:
        return (
            f"T_leaf_trunk error vs ground truth: median {1000 * self.median_translation_m:.1f} mm, "
            f"{self.median_rotation_deg:.3f} deg (max {1000 * np.max(self.translation_m, initial=0):.1f} mm, "
            f"{np.max(self.rotation_deg, initial=0):.3f} deg; {len(self.translation_m)} localizations)"
        )


def localization_errors(
    T_leaf_trunk: np.ndarray,
    leaf_t_ns: np.ndarray,
    trunk_t_ns: np.ndarray,
    gt_t_ns: np.ndarray,
    gt_T_world_cam: np.ndarray,
    tolerance_ns: int = 20_000_000,
) -> LocalizationErrors:
    """Compare estimates with ground truth ``inv(G_leaf) @ G_trunk`` (teach and repeat sharing one world,
    as when both come from one source). Leaves or trunks without ground truth within tolerance are skipped."""
    il, gl = associate(np.asarray(leaf_t_ns), gt_t_ns, tolerance_ns)
    it, gtr = associate(np.asarray(trunk_t_ns), gt_t_ns, tolerance_ns)
    both = np.intersect1d(il, it)
    gl = gl[np.searchsorted(il, both)]
    gtr = gtr[np.searchsorted(it, both)]
    G = inv_T(gt_T_world_cam[gl]) @ gt_T_world_cam[gtr]
    E = inv_T(G) @ np.asarray(T_leaf_trunk)[both]
    return LocalizationErrors(np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(rotation_angle(E[:, :3, :3])))


#: a reported success further than this from ground truth is a *wrong success*
WRONG_SUCCESS_M = 0.30
WRONG_SUCCESS_DEG = 2.0
#: chi-square quantile (3 dof, 99.73 %: "3 sigma") a success's translation error must stay inside to be covered
COVERAGE_CHI2_3DOF = 14.16


@dataclass(frozen=True)
class Integrity:
    """What a repeat's localization attempts were worth against ground truth (every attempt, in order).

    A success is *correct* within ``WRONG_SUCCESS_M`` and ``WRONG_SUCCESS_DEG`` of the truth, else *wrong*.
    ``first_correct`` is the attempt index of the first correct one (None: none), ``rate_after`` the share of
    attempts from there on that are correct, ``covered`` the share of correct successes whose translation
    error lies inside the 3-sigma ellipsoid of the reported covariance, ``median_nees`` their median
    normalized squared translation error (2.37 for an honest covariance).
    """

    attempts: int
    successes: int
    correct: int
    wrong: int
    first_correct: int | None
    rate_after: float
    median_error_m: float
    covered: float
    median_nees: float
    refused_off_route: int = 0  # attempts refused as off the route (beyond an end): counted apart from misses

    @property
    def missed(self) -> int:
        """Attempts that did not localize, other than the refusals off the route."""
        return self.attempts - self.successes - self.refused_off_route

    def to_dict(self) -> dict:
        return {**asdict(self), "missed": self.missed}

    def __str__(self) -> str:
        first = "none" if self.first_correct is None else f"attempt {self.first_correct}"
        judged = self.attempts - self.refused_off_route
        refused = (
            f", {self.refused_off_route} refused as off the route (counted apart, not as misses)"
            if self.refused_off_route
            else ""
        )
        after = f", {100 * self.rate_after:.0f} % correct after it" if self.first_correct is not None else ""
        cover = (
            f"reported sigma covers {100 * self.covered:.0f} % of errors (3 sigma)"
            if math.isfinite(self.covered)
            else "reported sigma not judged (no correct success)"
        )
        return (
            f"against ground truth: {self.correct} of {judged} attempts on the route correct{refused}, "
            f"{self.missed} missed, {self.wrong} wrong successes (> {100 * WRONG_SUCCESS_M:.0f} cm or "
            f"{WRONG_SUCCESS_DEG:g} deg); first correct {first}{after}; {cover}"
        )


def localization_integrity(
    success: np.ndarray,
    T_leaf_trunk: np.ndarray,
    covariance: np.ndarray,
    T_true: np.ndarray,
    off_route: np.ndarray | None = None,
) -> Integrity:
    """Judge attempts (``success`` (N,), estimates and covariances (N, 4, 4), (N, 6, 6) [rot, trans] left
    perturbation) against the true ``T_leaf_trunk`` (N, 4, 4; NaN where unknown: such a success is wrong).
    ``off_route`` (N,) marks the attempts refused as off the route: counted apart, neither correct nor missed,
    and left out of ``rate_after``."""
    success = np.asarray(success, bool)
    n = len(success)
    refused = np.zeros(n, bool) if off_route is None else (np.asarray(off_route, bool) & ~success)
    correct = np.zeros(n, bool)
    errors, nees = [], []
    for k in np.flatnonzero(success):
        if not np.all(np.isfinite(T_true[k])):
            continue
        E = T_leaf_trunk[k] @ inv_T(T_true[k])
        xi = log_se3(E)
        e_t, e_r = (
            float(np.linalg.norm((inv_T(T_true[k]) @ T_leaf_trunk[k])[:3, 3])),
            float(np.degrees(np.linalg.norm(xi[:3]))),
        )
        if e_t <= WRONG_SUCCESS_M and e_r <= WRONG_SUCCESS_DEG:
            correct[k] = True
            errors.append(e_t)
            P = np.asarray(covariance[k], float)[3:, 3:]
            try:
                nees.append(float(xi[3:] @ np.linalg.solve(P, xi[3:])))
            except np.linalg.LinAlgError:
                nees.append(float("inf"))
    first = int(np.argmax(correct)) if correct.any() else None
    judged_after = ~refused[first:] if first is not None else np.zeros(0, bool)
    after = float(correct[first:][judged_after].mean()) if judged_after.any() else 0.0
    nees_a = np.array(nees)
    return Integrity(
        attempts=n,
        successes=int(success.sum()),
        correct=int(correct.sum()),
        wrong=int(success.sum() - correct.sum()),
        first_correct=first,
        rate_after=after,
        refused_off_route=int(refused.sum()),
        median_error_m=float(np.median(errors)) if errors else float("nan"),
        covered=float(np.mean(nees_a <= COVERAGE_CHI2_3DOF)) if len(nees_a) else float("nan"),
        median_nees=float(np.median(nees_a)) if len(nees_a) else float("nan"),
    )


def true_leaf_trunk(
    leaf_t_ns: np.ndarray,
    trunk_t_ns: np.ndarray,
    gt_repeat_t_ns: np.ndarray,
    gt_repeat_T: np.ndarray,
    gt_teach_t_ns: np.ndarray,
    gt_teach_T: np.ndarray,
    tolerance_ns: int = 20_000_000,
) -> np.ndarray:
    """True ``T_leaf_trunk`` (N, 4, 4) = ``inv(G_leaf) @ G_trunk`` from the repeat's and the teach's ground truth
    (one world); NaN where either time has no ground truth within tolerance."""
    out = np.full((len(leaf_t_ns), 4, 4), np.nan)
    il, gl = associate(np.asarray(leaf_t_ns, np.int64), np.asarray(gt_repeat_t_ns), tolerance_ns)
    it, gt = associate(np.asarray(trunk_t_ns, np.int64), np.asarray(gt_teach_t_ns), tolerance_ns)
    both = np.intersect1d(il, it)
    G_l = gt_repeat_T[gl[np.searchsorted(il, both)]]
    G_t = gt_teach_T[gt[np.searchsorted(it, both)]]
    out[both] = inv_T(G_l) @ G_t
    return out


def integrity_of(
    locs: Sequence[Localization], trunk_t_ns: np.ndarray, gt_repeat: GroundTruth, gt_teach: GroundTruth
) -> Integrity:
    """:func:`localization_integrity` of ``Localization`` records whose trunks were taught at ``trunk_t_ns``, with
    the repeat's and the teach's ground truth (``GroundTruth``: ``t_ns``, ``T_world_cam``, one world)."""
    T_true = true_leaf_trunk(
        np.array([loc.t_ns for loc in locs], np.int64),
        trunk_t_ns,
        gt_repeat.t_ns,
        gt_repeat.T_world_cam,
        gt_teach.t_ns,
        gt_teach.T_world_cam,
    )
    return localization_integrity(
        np.array([loc.success for loc in locs], bool),
        np.array([loc.T_leaf_trunk for loc in locs]).reshape(-1, 4, 4),
        np.array([loc.covariance for loc in locs]).reshape(-1, 6, 6),
        T_true,
        np.array([loc.status == LocalizationStatus.OFF_ROUTE for loc in locs], bool),
    )
