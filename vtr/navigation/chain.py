"""The localization chain (thesis Fig. 6.3; VT&R3's ``localization_chain.hpp``) and the decision what a leaf's
localization is worth::

    privileged (teach) path   o────o────b────o────o────t────o────o───▶
                                        ▲                ▲
                                 T_w_b  │                │  T_l_t  (estimated at each new leaf)
    current (repeat) path          o────w────o────o────l        prior T_l_t = T_l_w @ T_w_b @ T_b_t

:class:`LocalizationChain` keeps twig (w), branch (b), trunk (t) and leaf (l) in a read-only :class:`ChainState` and
composes transforms only between adjacent frames (teach and repeat worlds never mix); :class:`ChainLocalizer`
localizes each leaf by **tracking** (guided by the prior, inside the innovation gate) or **searching** (place
recognition, a candidate confirmed by the next keyframe or predicted by the last success), and refuses a pose off
the route. The modes, gates and refusals: docs/localization.md."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..config import LocalizationConfig, SmoothingConfig
from ..errors import MapError
from ..geometry import inv_T, log_se3
from ..map import TaughtPath
from ..state.smoothing import adjoint
from .localization import LocalizationEstimate
from .trunk import BACKWARD, FORWARD, UNDECIDED, select_trunk, trunk_window


@dataclass(frozen=True)
class Candidate:
    """A verified but unconfirmed localization (searching): leaf pose in the repeat world, trunk, estimate."""

    leaf_id: int
    T_world_leaf: np.ndarray
    trunk: int
    T_leaf_trunk: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class ChainState:
    """The chain between two leaves (read-only; the chain replaces it after each attempt).

    ``tracking``: localized with odometry intact since; ``trunk``/``branch`` path indices (branch -1 before
    the first success); ``T_world_twig`` the twig's repeat-world pose and ``T_twig_branch`` its localization
    with ``twig_covariance``; ``direction`` +1 along the taught path, -1 against it, 0 before the repeat's motion
    has said which (the trunk window then looks forward).
    """

    tracking: bool = False
    trunk: int = 0
    branch: int = -1
    twig_id: int = -1
    T_world_twig: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    T_twig_branch: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    twig_covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(6))
    consecutive_failures: int = 0
    distance_since_success_m: float = 0.0
    direction: int = UNDECIDED
    last_position: np.ndarray | None = None
    candidate: Candidate | None = None
    leaves_since_check: int = 0
    along_track_m: float | None = None  # of the last success
    coast_s: float = 0.0  # time odometry did not see since the last success (it broke)
    doubted: bool = False  # the periodic place check found a better place: the chain predicts nothing


@dataclass(frozen=True)
class Prior:
    """The chain's prediction for a leaf: trunk (path index), ``T_leaf_trunk`` and its 6x6 covariance."""

    trunk: int
    T_leaf_trunk: np.ndarray
    covariance: np.ndarray


def innovation_chi2(T_est: np.ndarray, P_est: np.ndarray, T_pred: np.ndarray, P_pred: np.ndarray) -> float:
    """Squared Mahalanobis length of ``log(T_est inv(T_pred))`` (left perturbations, [rot, trans]) under
    ``P_est + P_pred``; inf when it cannot be computed."""
    xi = log_se3(np.asarray(T_est) @ inv_T(np.asarray(T_pred)))
    S_ = np.asarray(P_est) + np.asarray(P_pred)
    try:
        value = float(xi @ np.linalg.solve(S_, xi))
    except np.linalg.LinAlgError:
        return float("inf")
    return value if np.isfinite(value) else float("inf")


class LocalizationChain:
    """Trunk/branch/twig/leaf bookkeeping over the taught ``path`` with a read-only :class:`ChainState`."""

    def __init__(
        self, path: TaughtPath, config: LocalizationConfig, drift: SmoothingConfig, start_index: int | None = None
    ):
        """``drift``: odometry's drift per metre (the smoother's), growing the prior between localizations."""
        if len(path) == 0:
            raise MapError("the privileged path is empty")
        if start_index is not None and not 0 <= int(start_index) < len(path):
            raise MapError(f"start vertex {start_index} is not on the taught path (0..{len(path) - 1})")
        self.path = path
        self.config = config
        self._drift = drift
        self.start_index = None if start_index is None else int(start_index)
        self.state = ChainState(trunk=self.start_index or 0)
        self._arc = path.arc_length_m()

    # -- read-only views ---------------------------------------------------------------------------

    @property
    def localized(self) -> bool:
        """The chain's verdict, the one owner of "localized": tracking (the last success holds, odometry intact
        since), with fewer than ``lost_after_failures`` failures in a row and at most ``lost_after_distance_m``
        travelled since the last success: a controller may trust the pose relative to the taught path."""
        s, c = self.state, self.config
        return bool(
            s.tracking
            and s.consecutive_failures < c.lost_after_failures
            and s.distance_since_success_m <= c.lost_after_distance_m
        )

    @property
    def trunk(self) -> int:
        return self.state.trunk

    @property
    def branch_id(self) -> int:
        """Map id of the branch (-1 before the first successful localization)."""
        return int(self.path.ids[self.state.branch]) if self.state.branch >= 0 else -1

    @property
    def twig_id(self) -> int:
        return self.state.twig_id

    def window(self, trunk: int) -> tuple[int, int]:
        """Trunk-search window (path indices, hi exclusive) around ``trunk`` in the direction of travel."""
        c = self.config
        return trunk_window(trunk, len(self.path), c.trunk_window_back, c.trunk_window_forward, self.state.direction)

    def T_teach(self, T_world_frame: np.ndarray) -> np.ndarray:
        """A repeat camera pose (repeat run's world) in the teach frame, through twig and branch (before the
        first success: as if the repeat started at the hint vertex, or the route's first)."""
        s = self.state
        T_teach_branch = self.path.T_world_vertex[s.branch if s.branch >= 0 else (self.start_index or 0)]
        return T_teach_branch @ inv_T(s.T_twig_branch) @ inv_T(s.T_world_twig) @ T_world_frame

    def T_teach_localized(self, trunk_id: int, T_leaf_trunk: np.ndarray) -> np.ndarray:
        """Teach-frame pose of a leaf localized against taught vertex ``trunk_id``:
        ``T_teach_trunk @ inv(T_leaf_trunk)`` (:meth:`TaughtPath.T_world_localized`)."""
        return self.path.T_world_localized(trunk_id, T_leaf_trunk)

    # -- geometry on the route ---------------------------------------------------------------------

    def along_track_m(self, trunk: int, T_leaf_trunk: np.ndarray) -> float:
        """Arc length along the taught path of a leaf localized against ``trunk`` (its projection on the
        tangent at the trunk)."""
        p = (self.path.T_world_vertex[trunk] @ inv_T(T_leaf_trunk))[:3, 3]
        return float(self._arc[trunk] + (p - self.path.positions[trunk]) @ self._tangent(trunk))

    def beyond_end_m(self, trunk: int, T_leaf_trunk: np.ndarray) -> float:
        """How far (m) a leaf localized against ``trunk`` lies beyond the end of the route that trunk is (the
        first or the last taught vertex; -inf for any other trunk: the trunk is the vertex nearest the leaf,
        so a leaf past an end has that end as its trunk, and a route that closes on itself has no end there)."""
        p = (self.path.T_world_vertex[trunk] @ inv_T(T_leaf_trunk))[None, :3, 3]
        return float(self._beyond(p, np.array([trunk]))[0])

    def beyond_ends_m(self, positions_teach: np.ndarray) -> np.ndarray:
        """How far (m) teach-frame camera positions (N, 3) lie beyond an end of the route whose end vertex is their
        nearest taught vertex (-inf elsewhere)."""
        p = np.atleast_2d(np.asarray(positions_teach, float))
        if len(p) == 0:
            return np.zeros(0)
        from scipy.spatial import cKDTree  # scipy.spatial (~0.2 s) only when a position is checked against the ends

        _, nearest = cKDTree(self.path.positions).query(p)
        return self._beyond(p, np.asarray(nearest, np.int64))

    def _beyond(self, p: np.ndarray, trunk: np.ndarray) -> np.ndarray:
        P = self.path.positions
        out = np.full(len(p), -np.inf)
        last = len(P) - 1
        if last == 0:
            return np.linalg.norm(p - P[0], axis=1)
        at_end, at_start = trunk == last, trunk == 0
        out[at_end] = (p[at_end] - P[-1]) @ self._tangent(last)
        out[at_start] = (p[at_start] - P[0]) @ -self._tangent(0)
        return out

    def _tangent(self, i: int) -> np.ndarray:
        """Unit direction of the path at vertex i (over the vertices within a metre or two of it)."""
        P = self.path.positions
        lo, hi = max(0, i - 2), min(len(P) - 1, i + 2)
        d = P[hi] - P[lo]
        n = float(np.linalg.norm(d))
        return d / n if n > 1e-9 else np.zeros(3)

    # -- prediction and gates ----------------------------------------------------------------------

    def rebased(self, T_leaf_vertex: np.ndarray, vertex: int, others: int | slice) -> np.ndarray:
        """A leaf pose against taught ``vertex`` re-expressed against taught vertices ``others`` (a path index, or a
        slice: a stack) along the taught path: ``T_leaf_vertex @ inv(T_world_vertex) @ T_world_others``."""
        T = self.path.T_world_vertex
        return T_leaf_vertex @ inv_T(T[vertex]) @ T[others]

    def nearest_trunk(
        self, T_leaf_vertex: np.ndarray, vertex: int, lo: int | None = None, hi: int | None = None
    ) -> tuple[int, np.ndarray]:
        """The trunk (the trunk rule) of a leaf at ``T_leaf_vertex`` from taught ``vertex``, searched in path indices
        ``lo .. hi-1`` (default: the wider side of the trunk window, on both sides of ``vertex``), with its
        ``T_leaf_trunk``."""
        if lo is None or hi is None:
            w = max(self.config.trunk_window_back, self.config.trunk_window_forward)
            lo, hi = trunk_window(vertex, len(self.path), w, w)
        T_l_v = self.rebased(T_leaf_vertex, vertex, slice(lo, hi))
        trunk = select_trunk(T_l_v, lo, self.config.rotation_weight)
        return trunk, T_l_v[trunk - lo]

    def prior(self, T_world_leaf: np.ndarray) -> Prior:
        """Trunk and ``T_leaf_trunk`` of a leaf at repeat-odometry pose ``T_world_leaf`` through the twig and the
        branch, with the covariance of the last localization moved to the leaf plus odometry's error over the motion
        (:meth:`drift_covariance`) and, across the time odometry did not see since (``state.coast_s``), the motion
        prior's (:meth:`coast_covariance`)."""
        s = self.state
        T_l_w = inv_T(T_world_leaf) @ s.T_world_twig
        trunk, T_l_t = self.nearest_trunk(T_l_w @ s.T_twig_branch, max(s.branch, 0), *self.window(s.trunk))
        return Prior(trunk, T_l_t, self._carried(T_l_w, s.twig_covariance, s.coast_s))

    def chain_prediction(self, T_world_leaf: np.ndarray, trunk: int) -> tuple[np.ndarray, np.ndarray] | None:
        """What the last localization (twig and branch) predicts for a leaf at ``T_world_leaf`` against taught
        ``trunk``, with covariance (as :meth:`prior`, against a trunk of the caller's choice, across the time odometry
        did not see since). None when the last success says nothing of where the leaf is: before the first success,
        once the periodic place check doubted it, after more than ``lost_after_distance_m`` of failed leaves, or more
        than ``smoothing.max_extrapolation_s`` that odometry did not see (the motion prior alone is not extrapolated
        further)."""
        s = self.state
        if (
            s.branch < 0
            or s.doubted
            or s.distance_since_success_m > self.config.lost_after_distance_m
            or s.coast_s > self._drift.max_extrapolation_s
        ):
            return None
        T_l_w = inv_T(T_world_leaf) @ s.T_world_twig
        T_pred = self.rebased(T_l_w @ s.T_twig_branch, s.branch, trunk)
        return T_pred, self._carried(T_l_w, s.twig_covariance, s.coast_s)

    def _carried(self, T_leaf_from: np.ndarray, P_from: np.ndarray, coast_s: float = 0.0) -> np.ndarray:
        """Covariance at the leaf of a localization made at a repeat vertex ``T_leaf_from`` away (left perturbations
        move with the adjoint) plus the error of the odometry that carried it."""
        A = adjoint(T_leaf_from)
        return A @ P_from @ A.T + self.drift_covariance(T_leaf_from[:3, 3]) + self.coast_covariance(coast_s)

    def drift_covariance(self, motion_m: np.ndarray) -> np.ndarray:
        """Odometry's error over a motion whose other end lies at ``motion_m`` (3,) in the leaf frame, plus the
        prior's floor ([rot, trans]): drift per metre in every direction (``smoothing.odometry_*_sigma_per_m``) and
        a scale error along the motion (``localization.odometry_scale_sigma`` of its length): odometry's newest
        keyframe is short or long along its motion far more than it drifts sideways (docs/localization.md)."""
        d, c = self._drift, self.config
        t = np.asarray(motion_m, float)
        distance_m = float(np.linalg.norm(t))
        rot = (d.odometry_rotation_sigma_per_m * distance_m) ** 2 + np.radians(c.prior_floor_rotation_deg) ** 2
        trans = (d.odometry_translation_sigma_per_m * distance_m) ** 2 + c.prior_floor_translation_m**2
        P = np.diag(np.r_[[rot] * 3, [trans] * 3])
        P[3:, 3:] += c.odometry_scale_sigma**2 * np.outer(t, t)
        return P

    def coast_covariance(self, coast_s: float) -> np.ndarray:
        """The motion prior's error over ``coast_s`` seconds that odometry did not see (it carried the pose at
        constant velocity across them): the smoother's white-noise-acceleration model, ``Qc t^3 / 3`` per axis."""
        d = self._drift
        tau3 = max(float(coast_s), 0.0) ** 3 / 3.0
        return np.diag(np.r_[[d.qc_rotation * tau3] * 3, [d.qc_translation * tau3] * 3])

    def consistent(self, est: LocalizationEstimate, T_pred: np.ndarray, P_pred: np.ndarray) -> bool:
        """The innovation gate."""
        assert est.T_leaf_trunk is not None
        return innovation_chi2(est.T_leaf_trunk, est.covariance, T_pred, P_pred) <= self.config.innovation_gate

    def candidate_prediction(self, T_world_leaf: np.ndarray, trunk: int) -> tuple[np.ndarray, np.ndarray] | None:
        """What the pending candidate predicts for a leaf at ``T_world_leaf`` against ``trunk``, with covariance."""
        cand = self.state.candidate
        if cand is None:
            return None
        T_l_c = inv_T(T_world_leaf) @ cand.T_world_leaf
        T_pred = self.rebased(T_l_c @ cand.T_leaf_trunk, cand.trunk, trunk)
        return T_pred, self._carried(T_l_c, cand.covariance)

    def searching(self, odometry_broken: bool, distance_m: float) -> bool:
        """Whether this leaf is localized by place recognition rather than through the chain."""
        s, c = self.state, self.config
        return (
            not s.tracking
            or odometry_broken
            or s.consecutive_failures >= c.lost_after_failures
            or s.distance_since_success_m + distance_m > c.lost_after_distance_m
        )

    # -- updates -----------------------------------------------------------------------------------

    def step_distance(self, T_world_leaf: np.ndarray) -> float:
        last = self.state.last_position
        return 0.0 if last is None else float(np.linalg.norm(T_world_leaf[:3, 3] - last))

    def succeeded(
        self,
        leaf_id: int,
        T_world_leaf: np.ndarray,
        trunk: int,
        T_leaf_trunk: np.ndarray,
        covariance: np.ndarray,
        along_prev_m: float | None = None,
    ) -> None:
        """Twig and branch move to the leaf and its trunk; the direction follows the along-track motion."""
        s, c = self.state, self.config
        along = self.along_track_m(trunk, T_leaf_trunk)
        ref = s.along_track_m if along_prev_m is None else along_prev_m
        direction = s.direction
        if ref is not None and abs(along - ref) >= c.direction_min_step_m:
            direction = FORWARD if along > ref else BACKWARD
        elif ref is None:
            direction = self.motion_direction(T_world_leaf, trunk, T_leaf_trunk) or direction
        self.state = ChainState(
            tracking=True,
            trunk=trunk,
            branch=trunk,
            twig_id=leaf_id,
            T_world_twig=np.array(T_world_leaf, float),
            T_twig_branch=np.array(T_leaf_trunk, float),
            twig_covariance=np.array(covariance, float),
            consecutive_failures=0,
            distance_since_success_m=0.0,
            direction=direction,
            last_position=np.array(T_world_leaf[:3, 3], float),
            candidate=None,
            leaves_since_check=s.leaves_since_check + 1,
            along_track_m=along,
        )

    def failed(
        self, T_world_leaf: np.ndarray, trunk: int | None, *, lost: bool, candidate: Candidate | None = None
    ) -> None:
        """A failure: odometry carries the chain; ``lost`` drops tracking (the next leaf searches). A new place
        candidate already says which way the route is travelled (:meth:`motion_direction`)."""
        s = self.state
        direction = s.direction
        if candidate is not None:
            direction = self.motion_direction(T_world_leaf, candidate.trunk, candidate.T_leaf_trunk) or direction
        self.state = dataclasses.replace(
            s,
            tracking=s.tracking and not lost,
            trunk=s.trunk if trunk is None else trunk,
            consecutive_failures=s.consecutive_failures + 1,
            distance_since_success_m=s.distance_since_success_m + self.step_distance(T_world_leaf),
            last_position=np.array(T_world_leaf[:3, 3], float),
            candidate=candidate,
            direction=direction,
        )

    def motion_direction(self, T_world_leaf: np.ndarray, trunk: int, T_leaf_trunk: np.ndarray) -> int:
        """Direction of travel (+1, -1; 0 when undecided) of a leaf placed against ``trunk`` by an estimate, from
        the odometry since the previous leaf: that motion turned into the teach frame through the estimate and
        projected on the route's tangent at the trunk, decided once it reaches ``direction_min_step_m``. So the
        first attempts of a repeat (an unconfirmed place candidate) already carry the direction of the rest."""
        last = self.state.last_position
        if last is None:
            return UNDECIDED
        T_teach_leaf = self.path.T_world_vertex[trunk] @ inv_T(T_leaf_trunk)
        C_teach_world = T_teach_leaf[:3, :3] @ np.asarray(T_world_leaf, float)[:3, :3].T
        along = float(C_teach_world @ (np.asarray(T_world_leaf, float)[:3, 3] - last) @ self._tangent(trunk))
        if abs(along) < self.config.direction_min_step_m:
            return UNDECIDED
        return FORWARD if along > 0 else BACKWARD

    def refresh(self, current: dict[int, np.ndarray]) -> None:
        """Twig and candidate poses updated from odometry's latest window adjustment (by leaf id)."""
        s = self.state
        twig = current.get(s.twig_id)
        cand = s.candidate
        if cand is not None and cand.leaf_id in current:
            cand = dataclasses.replace(cand, T_world_leaf=np.array(current[cand.leaf_id], float))
        self.state = dataclasses.replace(
            s, T_world_twig=s.T_world_twig if twig is None else np.array(twig, float), candidate=cand
        )

    def coasted(self, seconds: float) -> None:
        """Odometry broke: it carried the pose across ``seconds`` it did not see at constant velocity (the pending
        candidate is dropped; the last success is carried on, less certain by :meth:`coast_covariance`)."""
        self.state = dataclasses.replace(self.state, candidate=None, coast_s=self.state.coast_s + max(seconds, 0.0))

    def checked(self) -> None:
        self.state = dataclasses.replace(self.state, leaves_since_check=0)


__all__ = ["Candidate", "ChainState", "LocalizationChain", "Prior", "innovation_chi2"]
