"""The chain's decisions (thesis Fig. 6.3): :class:`ChainLocalizer` localizes each leaf of a repeat against the taught
path held by a :class:`~vtr.navigation.chain.LocalizationChain`, by **tracking** (guided by the chain's prior, inside
the innovation gate) or **searching** (place recognition, a candidate confirmed by the next keyframe or predicted by
the last success), and refuses a pose off the route. The modes, gates and refusals: docs/localization.md."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..config import LocalizationConfig, PlaceConfig
from ..conventions import NS_PER_S
from ..geometry import inv_T
from ..types import Keyframe
from .chain import Candidate, LocalizationChain
from .localization import LocalizationEstimate, LocalizationStatus, Localizer, TaughtSubmap
from .place import PlaceIndex

#: builds the submap of a trunk (the trunk's and its neighbours' landmarks, experiences included)
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

    def __init__(
        self,
        chain: LocalizationChain,
        localizer: Localizer,
        place: PlaceIndex,
        submap: SubmapFn,
        config: LocalizationConfig,
        place_config: PlaceConfig,
        seed: int = 0,
    ):
        """``place_config``: how many place candidates to verify; ``seed``: ``run.seed`` (+1 per attempt)."""
        self.chain = chain
        self.localizer = localizer
        self.place = place
        self.submap = submap
        self.config = config
        self.place_config = place_config
        self._seed = seed
        self._attempts = 0
        self._last_t_ns: int | None = None  # the previous leaf's time

    def _localize(
        self, kf: Keyframe, trunk: int, T_prior: np.ndarray | None, trusted: bool, failures: int = 0
    ) -> LocalizationEstimate:
        self._attempts += 1
        return self.localizer.localize(
            kf.frame,
            self.submap(trunk),
            T_prior,
            seed=self._seed + self._attempts,
            trusted_prior=trusted,
            consecutive_failures=failures,
        )

    def localize(
        self, leaf_id: int, kf: Keyframe, odometry_broken: bool, current: dict[int, np.ndarray] | None = None
    ) -> Attempt:
        """Localize leaf ``leaf_id`` (``odometry_broken``: odometry failed since the previous leaf) and update
        the chain. ``current`` holds repeat-world poses of earlier leaves as odometry's window now has them:
        the twig's and the pending candidate's are read from there when present, so the odometry between
        them and the leaf is one adjustment's."""
        ch = self.chain
        ch.refresh(current or {})
        last_t_ns, self._last_t_ns = self._last_t_ns, kf.t_ns
        if odometry_broken:  # carried at constant velocity since (at most) the previous leaf
            ch.coasted(0.0 if last_t_ns is None else (kf.t_ns - last_t_ns) / NS_PER_S)
        if ch.searching(odometry_broken, ch.step_distance(kf.T_world_kf)):
            return self._search(leaf_id, kf)
        return self._track(leaf_id, kf)

    def _fail(
        self,
        kf: Keyframe,
        trunk: int,
        est: LocalizationEstimate,
        status: LocalizationStatus,
        T_report: np.ndarray,
        *,
        lost: bool,
        candidate: Candidate | None = None,
    ) -> Attempt:
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
        scores = self.place.scores(kf.frame.features.descriptors, also=slice(lo, hi))  # the window scored exactly
        inside = float(scores[lo:hi].max())
        outside = np.r_[np.arange(0, lo), np.arange(hi, len(scores))]
        rivals = outside[scores[outside] > inside]
        for cand in rivals[np.argsort(-scores[rivals], kind="stable")][: self.place_config.candidates]:
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
            extra.append(ch.start_index)  # the user's hint, tried first
        if ch.state.candidate is not None:
            extra.append(ch.state.candidate.trunk)  # where the pending candidate was
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
        if near.max() < CONFIRM_SCORE_RATIO * scores.max():  # place recognition sees that part of the route too
            return None
        pred = ch.candidate_prediction(kf.T_world_kf, trunk)
        assert pred is not None
        est = self._localize(kf, trunk, pred[0], False)
        if (
            est.T_leaf_trunk is None
            or ch.beyond_end_m(trunk, est.T_leaf_trunk) > c.off_route_distance_m
            or not ch.consistent(est, *pred)
        ):
            return None
        ch.succeeded(
            leaf_id,
            kf.T_world_kf,
            trunk,
            est.T_leaf_trunk,
            est.covariance,
            along_prev_m=ch.along_track_m(pending.trunk, pending.T_leaf_trunk),
        )
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
        carried = self._pending_trunk(kf)  # its part of the route scored exactly (a long route's shortlist)
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
                break  # verified beyond doubt: the other places need no look
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
            if pr is not None:  # the reported T_leaf_trunk is the chain's prior: against its trunk
                trunk = pr.trunk
            return self._fail(kf, trunk, est, LocalizationStatus.OFF_ROUTE if off else est.status, T_chain, lost=True)
        trunk, est = self._nearest_trunk(kf, *best)
        assert est.T_leaf_trunk is not None
        if ch.beyond_end_m(trunk, est.T_leaf_trunk) > c.off_route_distance_m:
            return self._fail(kf, trunk, est, LocalizationStatus.OFF_ROUTE, est.T_leaf_trunk, lost=True)
        pred = ch.candidate_prediction(kf.T_world_kf, trunk)
        pending = ch.state.candidate
        if pred is not None and pending is not None and ch.consistent(est, *pred):
            ch.succeeded(
                leaf_id,
                kf.T_world_kf,
                trunk,
                est.T_leaf_trunk,
                est.covariance,
                along_prev_m=ch.along_track_m(pending.trunk, pending.T_leaf_trunk),
            )
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


__all__ = ["CLEAR_VERIFICATION", "CONFIRM_SCORE_RATIO", "Attempt", "ChainLocalizer", "SubmapFn"]
