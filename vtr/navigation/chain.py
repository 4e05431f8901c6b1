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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..config import LocalizationConfig, PlaceConfig, SmoothingConfig
from ..conventions import NS_PER_S
from ..errors import MapError
from ..geometry import inv_T, log_se3
from ..map import TaughtPath
from ..state.smoothing import adjoint
from ..types import Keyframe
from .localization import LocalizationEstimate, LocalizationStatus, Localizer, TaughtSubmap
from .place import PlaceIndex
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
    along_track_m: float | None = None       # of the last success
    coast_s: float = 0.0                     # time odometry did not see since the last success (it broke)
    doubted: bool = False                    # the periodic place check found a better place: the chain predicts nothing


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

    def __init__(self, path: TaughtPath, config: LocalizationConfig, drift: SmoothingConfig,
                 start_index: int | None = None):
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
        return bool(s.tracking and s.consecutive_failures < c.lost_after_failures
                    and s.distance_since_success_m <= c.lost_after_distance_m)

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

    def nearest_trunk(self, T_leaf_vertex: np.ndarray, vertex: int, lo: int | None = None,
                      hi: int | None = None) -> tuple[int, np.ndarray]:
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
        if (s.branch < 0 or s.doubted or s.distance_since_success_m > self.config.lost_after_distance_m
                or s.coast_s > self._drift.max_extrapolation_s):
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
        return (not s.tracking or odometry_broken or s.consecutive_failures >= c.lost_after_failures
                or s.distance_since_success_m + distance_m > c.lost_after_distance_m)

    # -- updates -----------------------------------------------------------------------------------

    def step_distance(self, T_world_leaf: np.ndarray) -> float:
        last = self.state.last_position
        return 0.0 if last is None else float(np.linalg.norm(T_world_leaf[:3, 3] - last))

    def succeeded(self, leaf_id: int, T_world_leaf: np.ndarray, trunk: int, T_leaf_trunk: np.ndarray,
                  covariance: np.ndarray, along_prev_m: float | None = None) -> None:
        """Twig and branch move to the leaf and its trunk; the direction follows the along-track motion."""
        s, c = self.state, self.config
        along = self.along_track_m(trunk, T_leaf_trunk)
        ref = s.along_track_m if along_prev_m is None else along_prev_m
        direction = s.direction
        if ref is not None and abs(along - ref) >= c.direction_min_step_m:
            direction = FORWARD if along > ref else BACKWARD
        elif ref is None:
            direction = self.motion_direction(T_world_leaf, trunk, T_leaf_trunk) or direction
        self.state = ChainState(tracking=True, trunk=trunk, branch=trunk, twig_id=leaf_id,
                                T_world_twig=np.array(T_world_leaf, float), T_twig_branch=np.array(T_leaf_trunk, float),
                                twig_covariance=np.array(covariance, float), consecutive_failures=0,
                                distance_since_success_m=0.0, direction=direction,
                                last_position=np.array(T_world_leaf[:3, 3], float), candidate=None,
                                leaves_since_check=s.leaves_since_check + 1, along_track_m=along)

    def failed(self, T_world_leaf: np.ndarray, trunk: int | None, *, lost: bool,
               candidate: Candidate | None = None) -> None:
        """A failure: odometry carries the chain; ``lost`` drops tracking (the next leaf searches). A new place
        candidate already says which way the route is travelled (:meth:`motion_direction`)."""
        s = self.state
        direction = s.direction
        if candidate is not None:
            direction = self.motion_direction(T_world_leaf, candidate.trunk, candidate.T_leaf_trunk) or direction
        self.state = dataclasses.replace(
            s, tracking=s.tracking and not lost, trunk=s.trunk if trunk is None else trunk,
            consecutive_failures=s.consecutive_failures + 1,
            distance_since_success_m=s.distance_since_success_m + self.step_distance(T_world_leaf),
            last_position=np.array(T_world_leaf[:3, 3], float), candidate=candidate, direction=direction)

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
        self.state = dataclasses.replace(s, T_world_twig=s.T_world_twig if twig is None else np.array(twig, float),
                                         candidate=cand)

    def coasted(self, seconds: float) -> None:
        """Odometry broke: it carried the pose across ``seconds`` it did not see at constant velocity (the pending
        candidate is dropped; the last success is carried on, less certain by :meth:`coast_covariance`)."""
        self.state = dataclasses.replace(self.state, candidate=None, coast_s=self.state.coast_s + max(seconds, 0.0))

    def checked(self) -> None:
        self.state = dataclasses.replace(self.state, leaves_since_check=0)


SubmapFn = Callable[[int], TaughtSubmap]

#: a place candidate verified with this many times ``min_inliers_unlocalized`` inliers ends the search
CLEAR_VERIFICATION = 2
#: a candidate is confirmed only where place recognition scores the leaf at least this share of its best score
#: (a route that passes a place several times scores every pass alike: the best is any of them)
CONFIRM_SCORE_RATIO = 0.8


@dataclass(frozen=True)
class Attempt:
    """What one leaf's localization came to: its trunk (path index), the estimate (``T_leaf_trunk`` set
    even when refused: an unconfirmed or inconsistent estimate is still reported), the status, and the
    ``T_leaf_trunk`` to report (the estimate, else the chain's prior)."""

    trunk: int
    estimate: LocalizationEstimate
    status: LocalizationStatus
    T_report: np.ndarray

    @property
    def success(self) -> bool:
        return self.status == LocalizationStatus.LOCALIZED


class ChainLocalizer:
    """Localizes each new leaf: through the chain when tracking, by place recognition when searching.

    ``submap(trunk)`` returns the taught submap around a path index; ``place`` proposes taught vertices.
    """

    def __init__(self, chain: LocalizationChain, localizer: Localizer, place: PlaceIndex, submap: SubmapFn,
                 config: LocalizationConfig, place_config: PlaceConfig, seed: int = 0):
        """``place_config``: how many place candidates to verify; ``seed``: ``run.seed`` (+1 per attempt)."""
        self.chain = chain
        self.localizer = localizer
        self.place = place
        self.submap = submap
        self.config = config
        self.place_config = place_config
        self._seed = seed
        self._attempts = 0
        self._last_t_ns: int | None = None       # the previous leaf's time

    def _localize(self, kf: Keyframe, trunk: int, T_prior: np.ndarray | None, trusted: bool,
                  failures: int = 0) -> LocalizationEstimate:
        self._attempts += 1
        return self.localizer.localize(kf.frame, self.submap(trunk), T_prior, seed=self._seed + self._attempts,
                                       trusted_prior=trusted, consecutive_failures=failures)

    def localize(self, leaf_id: int, kf: Keyframe, odometry_broken: bool,
                 current: dict[int, np.ndarray] | None = None) -> Attempt:
        """Localize leaf ``leaf_id`` (``odometry_broken``: odometry failed since the previous leaf) and update
        the chain. ``current`` holds repeat-world poses of earlier leaves as odometry's window now has them:
        the twig's and the pending candidate's are read from there when present, so the odometry between
        them and the leaf is one adjustment's."""
        ch = self.chain
        ch.refresh(current or {})
        last_t_ns, self._last_t_ns = self._last_t_ns, kf.t_ns
        if odometry_broken:                 # carried at constant velocity since (at most) the previous leaf
            ch.coasted(0.0 if last_t_ns is None else (kf.t_ns - last_t_ns) / NS_PER_S)
        if ch.searching(odometry_broken, ch.step_distance(kf.T_world_kf)):
            return self._search(leaf_id, kf)
        return self._track(leaf_id, kf)

    def _fail(self, kf: Keyframe, trunk: int, est: LocalizationEstimate, status: LocalizationStatus,
              T_report: np.ndarray, *, lost: bool, candidate: Candidate | None = None) -> Attempt:
        self.chain.failed(kf.T_world_kf, trunk, lost=lost, candidate=candidate)
        return Attempt(trunk, est, status, T_report)

    # -- tracking ----------------------------------------------------------------------------------

    def _track(self, leaf_id: int, kf: Keyframe) -> Attempt:
        ch, c = self.chain, self.config
        pr = ch.prior(kf.T_world_kf)
        if ch.beyond_end_m(pr.trunk, pr.T_leaf_trunk) > c.off_route_distance_m:
            none = LocalizationEstimate.failed(np.zeros(0, np.int64), LocalizationStatus.OFF_ROUTE)
            return self._fail(kf, pr.trunk, none, LocalizationStatus.OFF_ROUTE, pr.T_leaf_trunk, lost=True)
        est = self._localize(kf, pr.trunk, pr.T_leaf_trunk, True, ch.state.consecutive_failures)
        if est.T_leaf_trunk is None:
            return self._fail(kf, pr.trunk, est, est.status, pr.T_leaf_trunk, lost=False)
        if not ch.consistent(est, pr.T_leaf_trunk, pr.covariance):
            return self._fail(kf, pr.trunk, est, LocalizationStatus.INCONSISTENT, est.T_leaf_trunk, lost=False)
        if ch.beyond_end_m(pr.trunk, est.T_leaf_trunk) > c.off_route_distance_m:
            return self._fail(kf, pr.trunk, est, LocalizationStatus.OFF_ROUTE, est.T_leaf_trunk, lost=True)
        if ch.state.leaves_since_check + 1 >= c.place_check_every and self._elsewhere(kf, pr.trunk, est):
            ch.state = dataclasses.replace(ch.state, doubted=True)
            return self._fail(kf, pr.trunk, est, LocalizationStatus.INCONSISTENT, est.T_leaf_trunk, lost=True)
        ch.succeeded(leaf_id, kf.T_world_kf, pr.trunk, est.T_leaf_trunk, est.covariance)
        return Attempt(pr.trunk, est, LocalizationStatus.LOCALIZED, est.T_leaf_trunk)

    def _elsewhere(self, kf: Keyframe, trunk: int, est: LocalizationEstimate) -> bool:
        """Periodic check: does a place outside the trunk's window look more like the leaf than every vertex in it,
        and then verify with more inliers than the tracked estimate? (Only such places are verified.)"""
        ch = self.chain
        ch.checked()
        lo, hi = ch.window(trunk)
        scores = self.place.scores(kf.frame.features.descriptors, also=slice(lo, hi))   # the window scored exactly
        inside = float(scores[lo:hi].max())
        outside = np.r_[np.arange(0, lo), np.arange(hi, len(scores))]
        rivals = outside[scores[outside] > inside]
        for cand in rivals[np.argsort(-scores[rivals], kind="stable")][:self.place_config.candidates]:
            other = self._localize(kf, int(cand), None, False)
            if not other.ok or other.inliers <= est.inliers:
                continue
            assert other.T_leaf_trunk is not None
            # the rival as a pose against the tracked trunk: the same place (a route that passes it again) is no
            # conflict, only another one is
            T_as_trunk = ch.rebased(other.T_leaf_trunk, int(cand), trunk)
            if not ch.consistent(est, T_as_trunk, other.covariance):
                return True
        return False

    # -- searching ---------------------------------------------------------------------------------

    def _candidates(self, found: list[int]) -> list[int]:
        """Taught vertices to verify: the user's hint (before the first success), the pending candidate's, then
        place recognition's ``found``."""
        ch = self.chain
        extra = []
        if ch.start_index is not None and ch.state.branch < 0:
            extra.append(ch.start_index)                       # the user's hint, tried first
        if ch.state.candidate is not None:
            extra.append(ch.state.candidate.trunk)            # where the pending candidate was
        out: list[int] = []
        for i in extra + found:
            if i not in out:
                out.append(i)
        return out

    def _confirm(self, leaf_id: int, kf: Keyframe, scores: np.ndarray, trunk: int | None) -> Attempt | None:
        """The pending candidate carried to this leaf by odometry, the leaf localized guided by it against the
        nearest taught vertex: a success when place recognition also scores that part of the route close to its
        best for this leaf and the estimate passes the gate of the prediction; None otherwise (search the places).
        ``trunk``: the taught vertex nearest the carried candidate (:meth:`_pending_trunk`; None: none pending)."""
        ch, c = self.chain, self.config
        if trunk is None:
            return None
        pending = ch.state.candidate
        assert pending is not None
        near = scores[self._near(trunk)]
        if near.max() < CONFIRM_SCORE_RATIO * scores.max():     # place recognition sees that part of the route too
            return None
        pred = ch.candidate_prediction(kf.T_world_kf, trunk)
        assert pred is not None
        est = self._localize(kf, trunk, pred[0], False)
        if (est.T_leaf_trunk is None or ch.beyond_end_m(trunk, est.T_leaf_trunk) > c.off_route_distance_m
                or not ch.consistent(est, *pred)):
            return None
        ch.succeeded(leaf_id, kf.T_world_kf, trunk, est.T_leaf_trunk, est.covariance,
                     along_prev_m=ch.along_track_m(pending.trunk, pending.T_leaf_trunk))
        return Attempt(trunk, est, LocalizationStatus.LOCALIZED, est.T_leaf_trunk)

    def _pending_trunk(self, kf: Keyframe) -> int | None:
        """The taught vertex nearest to the pending candidate carried to this leaf by odometry (None: none pending)."""
        ch = self.chain
        pending = ch.state.candidate
        if pending is None:
            return None
        return ch.nearest_trunk(inv_T(kf.T_world_kf) @ pending.T_world_leaf @ pending.T_leaf_trunk, pending.trunk)[0]

    def _near(self, trunk: int) -> slice:
        n = self.config.neighbour_vertices
        return slice(max(0, trunk - n - 1), trunk + n + 2)

    def _search(self, leaf_id: int, kf: Keyframe) -> Attempt:
        ch, c = self.chain, self.config
        carried = self._pending_trunk(kf)      # its part of the route scored exactly (a long route's shortlist)
        scores = self.place.scores(kf.frame.features.descriptors, also=None if carried is None else self._near(carried))
        k = min(self.place_config.candidates, len(scores))
        places = [int(i) for i in np.argsort(-scores, kind="stable")[:k]]
        confirmed = self._confirm(leaf_id, kf, scores, carried)
        if confirmed is not None:
            return confirmed
        best: tuple[int, LocalizationEstimate] | None = None
        tried: list[tuple[int, LocalizationEstimate]] = []
        for cand in self._candidates(places):
            est = self._localize(kf, cand, None, False)
            tried.append((cand, est))
            if est.ok and (best is None or est.inliers > best[1].inliers):
                best = (cand, est)
            if est.ok and est.inliers >= CLEAR_VERIFICATION * c.min_inliers_unlocalized:
                break                       # verified beyond doubt: the other places need no look
        if best is None:
            pr = ch.prior(kf.T_world_kf) if ch.state.branch >= 0 else None
            T_chain = pr.T_leaf_trunk if pr is not None else np.eye(4)
            # nothing verified; past an end of the route by odometry since the last localization: off the route
            off = pr is not None and ch.beyond_end_m(pr.trunk, pr.T_leaf_trunk) > c.off_route_distance_m
            if not tried:
                none = LocalizationEstimate.failed(np.zeros(0, np.int64), LocalizationStatus.NO_CANDIDATES)
                status = LocalizationStatus.OFF_ROUTE if off else LocalizationStatus.NO_CANDIDATES
                return self._fail(kf, ch.state.trunk, none, status, T_chain, lost=True)
            trunk, est = max(tried, key=lambda x: x[1].inliers)
            if pr is not None:              # the reported T_leaf_trunk is the chain's prior: against its trunk
                trunk = pr.trunk
            return self._fail(kf, trunk, est, LocalizationStatus.OFF_ROUTE if off else est.status, T_chain, lost=True)
        trunk, est = self._nearest_trunk(kf, *best)
        assert est.T_leaf_trunk is not None
        if ch.beyond_end_m(trunk, est.T_leaf_trunk) > c.off_route_distance_m:
            return self._fail(kf, trunk, est, LocalizationStatus.OFF_ROUTE, est.T_leaf_trunk, lost=True)
        pred = ch.candidate_prediction(kf.T_world_kf, trunk)
        pending = ch.state.candidate
        if pred is not None and pending is not None and ch.consistent(est, *pred):
            ch.succeeded(leaf_id, kf.T_world_kf, trunk, est.T_leaf_trunk, est.covariance,
                         along_prev_m=ch.along_track_m(pending.trunk, pending.T_leaf_trunk))
            return Attempt(trunk, est, LocalizationStatus.LOCALIZED, est.T_leaf_trunk)
        if self._chain_confirms(kf, trunk, est):
            ch.succeeded(leaf_id, kf.T_world_kf, trunk, est.T_leaf_trunk, est.covariance)
            return Attempt(trunk, est, LocalizationStatus.LOCALIZED, est.T_leaf_trunk)
        new = Candidate(leaf_id, np.array(kf.T_world_kf, float), trunk, est.T_leaf_trunk, est.covariance)
        return self._fail(kf, trunk, est, LocalizationStatus.UNCONFIRMED, est.T_leaf_trunk, lost=True, candidate=new)

    def _chain_confirms(self, kf: Keyframe, trunk: int, est: LocalizationEstimate) -> bool:
        """A place candidate verified beyond doubt (``CLEAR_VERIFICATION`` times ``min_inliers_unlocalized`` inliers,
        found without the chain's prior) that the last success, carried here by odometry (and across a break by the
        motion prior), predicts inside the innovation gate: two independent witnesses agree, so the leaf needs no
        second keyframe (re-entry after a gap, a long step, failures in a row)."""
        ch = self.chain
        if est.inliers < CLEAR_VERIFICATION * self.config.min_inliers_unlocalized:
            return False
        pred = ch.chain_prediction(kf.T_world_kf, trunk)
        return pred is not None and ch.consistent(est, *pred)

    def _nearest_trunk(self, kf: Keyframe, cand: int, est: LocalizationEstimate) -> tuple[int, LocalizationEstimate]:
        """Re-localize against the taught vertex nearest to a verified candidate's estimate, guided by it."""
        assert est.T_leaf_trunk is not None
        trunk, T_prior = self.chain.nearest_trunk(est.T_leaf_trunk, cand)
        if trunk == cand:
            return cand, est
        again = self._localize(kf, trunk, T_prior, False)
        if again.ok and again.inliers >= est.inliers // 2:
            return trunk, again
        return cand, est


__all__ = ["Attempt", "Candidate", "ChainLocalizer", "ChainState", "LocalizationChain", "Prior", "innovation_chi2"]
