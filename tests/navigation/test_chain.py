"""Every decision of :class:`vtr.navigation.chain_localizer.ChainLocalizer`, one row of a table each, in milliseconds.

No images: the taught route is a straight line of ``N`` vertices one metre apart (camera z along it), the repeat
runs in the teach frame, and the localizer and the place index are scripted. The scripted localizer answers with
the *true* ``T_leaf_trunk`` of the leaf (from where the row says the leaf really is) against any taught vertex
within ``VISIBLE_M`` of it and refuses the others (too few matches), unless the row scripts a vertex's reply: a
refusal with its reason, an inlier count, or an estimate that puts the leaf somewhere else. The place index scores
the vertex nearest the leaf 1 and every other 0.1, unless the row scripts the scores. What is decided from those
answers (gates, confirmation, re-entry, the periodic check, off-route, lost) is the real chain's.

A row drives leaves ``before`` through the chain (its set-up, itself one of the rows' decisions), then the leaf
under test, and checks the attempt's status, the chain's state after it and, where it matters, which taught
vertices were matched how (guided by a prior or not, the prior trusted or not).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pytest

from vtr.config import Config
from vtr.map import TaughtPath, vertex_id
from vtr.navigation.chain import LocalizationChain
from vtr.navigation.chain_localizer import CLEAR_VERIFICATION, ChainLocalizer
from vtr.navigation.localization import LocalizationEstimate
from vtr.navigation.localization import LocalizationStatus as S
from vtr.types import Features, Keyframe, StereoFrame

N = 60  # taught vertices, 1 m apart along camera z
VISIBLE_M = 4.0  # the scripted localizer verifies vertices this close to the leaf
COV = np.diag([np.radians(0.5) ** 2] * 3 + [0.05**2] * 3)
CFG = Config()
LOC = CFG.localization
CLEAR = CLEAR_VERIFICATION * LOC.min_inliers_unlocalized  # a place verified beyond doubt (120)
PLAIN = LOC.min_inliers_unlocalized + 10  # verified, not beyond doubt (70)
CHECK_DUE = LOC.place_check_every - 1  # the next success runs the periodic check


def T_at(s: float) -> np.ndarray:
    """Camera pose at ``s`` metres along the route (teach frame = repeat world)."""
    T = np.eye(4)
    T[2, 3] = s
    return T


def _path() -> TaughtPath:
    return TaughtPath(
        np.array([vertex_id(0, i) for i in range(N)]),
        np.stack([T_at(i) for i in range(N)]),
        np.arange(N, dtype=np.int64) * 10**8,
    )


@dataclass(frozen=True)
class Reply:
    """A scripted answer of the localizer against one taught vertex: refused with ``status``, or an estimate with
    ``inliers`` that puts the leaf at ``leaf_at`` metres along the route (None: where it really is)."""

    status: S = S.LOCALIZED
    inliers: int = PLAIN
    leaf_at: float | None = None


@dataclass(frozen=True)
class Leaf:
    """One leaf: really at ``s`` metres along the route, odometry says ``odo`` (default ``s``), ``dt_s`` after the
    previous leaf; ``broken``: odometry failed since the previous leaf; ``replies`` and ``scores`` script the
    localizer and the place index; ``state`` replaces fields of the chain's state before the leaf."""

    s: float
    odo: float | None = None
    broken: bool = False
    dt_s: float = 0.1
    replies: dict[int, Reply] = field(default_factory=dict)
    scores: dict[int, float] | None = None
    state: dict[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class Expect:
    status: S
    tracking: bool  # the chain tracks after the leaf (the next leaf is not a search)
    localized: bool | None = None  # the chain's verdict after the leaf (default: == tracking)
    candidate: bool = False  # a place candidate waits for the next keyframe
    trunk: int | None = None  # the attempt's trunk (path index)
    calls: list[tuple[int, bool, bool]] | None = None  # (vertex, guided, trusted prior) matched, in order
    doubted: bool = False
    failures: int | None = None  # consecutive failures after the leaf


class ScriptedLocalizer:
    """Answers as :class:`Reply` says; the submap it is handed is the trunk's path index."""

    def __init__(self) -> None:
        self.truth_m = 0.0
        self.replies: dict[int, Reply] = {}
        self.calls: list[tuple[int, bool, bool]] = []

    def localize(
        self,
        frame: StereoFrame,
        submap: int,
        T_prior: np.ndarray | None,
        seed: int = 0,
        trusted_prior: bool = True,
        consecutive_failures: int = 0,
    ) -> LocalizationEstimate:
        trunk = int(submap)
        self.calls.append((trunk, T_prior is not None, trusted_prior))
        r = self.replies.get(trunk)
        if r is None:
            r = Reply() if abs(trunk - self.truth_m) <= VISIBLE_M else Reply(S.TOO_FEW_MATCHES)
        matched = np.arange(max(r.inliers, LOC.min_matches) + 20)
        if r.status != S.LOCALIZED:
            return LocalizationEstimate.failed(matched, r.status)
        inlier = np.arange(len(matched)) < r.inliers
        at = self.truth_m if r.leaf_at is None else r.leaf_at
        T_leaf_trunk = np.linalg.inv(T_at(at)) @ T_at(trunk)
        return LocalizationEstimate(T_leaf_trunk, COV.copy(), len(matched), matched, inlier)


class ScriptedPlaces:
    def __init__(self) -> None:
        self.current = np.zeros(N)

    def scores(self, descriptors: np.ndarray, also: object = None) -> np.ndarray:
        return self.current.copy()


class Run:
    """A chain over the straight route with the scripted localizer and place index."""

    def __init__(self, start_index: int | None = None):
        self.chain = LocalizationChain(_path(), CFG.localization, CFG.smoothing, start_index)
        self.localizer = ScriptedLocalizer()
        self.places = ScriptedPlaces()
        self.chain_localizer = ChainLocalizer(
            self.chain,
            self.localizer,
            self.places,  # type: ignore[arg-type]
            lambda trunk: trunk,  # type: ignore[arg-type,return-value]
            CFG.localization,
            CFG.place,
            CFG.run.seed,
        )
        self.t_ns = 0
        self.leaves = 0

    def leaf(self, leaf: Leaf):
        self.leaves += 1
        self.t_ns += round(leaf.dt_s * 1e9)
        if leaf.state:
            self.chain.state = dataclasses.replace(self.chain.state, **leaf.state)  # type: ignore[arg-type]
        self.localizer.truth_m, self.localizer.replies, self.localizer.calls = leaf.s, leaf.replies, []
        scores = np.full(N, 0.1)
        if leaf.scores is None:
            scores[int(np.clip(round(leaf.s), 0, N - 1))] = 1.0
        else:
            for i, v in leaf.scores.items():
                scores[i] = v
        self.places.current = scores
        features = Features(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 32), np.uint8))
        frame = StereoFrame(self.t_ns, self.leaves, features, np.zeros(0), np.zeros((0, 3)))
        kf = Keyframe(self.leaves, frame, T_at(leaf.s if leaf.odo is None else leaf.odo), COV, 100)
        return self.chain_localizer.localize(vertex_id(1, self.leaves), kf, leaf.broken)


#: set-ups: a place candidate at 9 verified beyond doubt, confirmed at 10 (its own rows check both)
TRACKING_AT_10 = [Leaf(9, replies={9: Reply(inliers=CLEAR)}), Leaf(10)]
#: tracking at 10, then three refusals in a row (lost by failures)
REFUSED = {i: Reply(S.TOO_FEW_INLIERS) for i in range(N)}
LOST_AFTER_10 = [*TRACKING_AT_10, *(Leaf(s, replies=REFUSED) for s in (10.4, 11.0, 11.6))]
#: a candidate pending at 10 (verified at the start, not beyond doubt)
PENDING_AT_10 = [Leaf(10)]
#: tracking at the route's last vertex
TRACKING_AT_END = [Leaf(N - 2, replies={N - 2: Reply(inliers=CLEAR)}), Leaf(N - 1)]
FAR = 50  # a vertex outside the trunk window of vertices 10-12
TRUNK_WINDOW_11 = (max(0, 11 - LOC.trunk_window_back), 11 + LOC.trunk_window_forward + 1)
assert not TRUNK_WINDOW_11[0] <= FAR < TRUNK_WINDOW_11[1] and FAR < N


# fmt: off
ROWS: list[tuple[str, list[Leaf], Leaf, Expect, int | None]] = [
    # name, leaves before, the leaf, what the chain decides, start hint
    # -- tracking: localized through the chain, prior trusted
    ("tracking: consistent estimate -> localized", TRACKING_AT_10, Leaf(11),
     Expect(S.LOCALIZED, True, trunk=11, calls=[(11, True, True)], failures=0), None),
    *((f"tracking: the localizer refuses ({status.value}) -> refused, still tracking", TRACKING_AT_10,
       Leaf(11, replies={11: Reply(status)}), Expect(status, True, trunk=11, calls=[(11, True, True)], failures=1),
       None)
      for status in (S.TOO_FEW_MATCHES, S.TOO_FEW_INLIERS, S.LOW_INLIER_RATIO, S.RESIDUALS)),
    ("tracking: estimate outside the innovation gate -> inconsistent_with_odometry, still tracking", TRACKING_AT_10,
     Leaf(11, replies={11: Reply(leaf_at=13.0)}), Expect(S.INCONSISTENT, True, trunk=11, failures=1), None),
    ("tracking: the third refusal in a row -> lost", LOST_AFTER_10[:-1], Leaf(11.6, replies=REFUSED),
     Expect(S.TOO_FEW_INLIERS, True, localized=False, failures=LOC.lost_after_failures), None),
    ("tracking: the prior is past the route's end -> off_route, lost, nothing matched", TRACKING_AT_END,
     Leaf(N - 1 + LOC.off_route_distance_m + 2), Expect(S.OFF_ROUTE, False, trunk=N - 1, calls=[]), None),
    ("tracking: the estimate is past the route's end -> off_route, lost", TRACKING_AT_END,
     Leaf(N - 1 + LOC.off_route_distance_m - 0.1,
          replies={N - 1: Reply(leaf_at=N - 1 + LOC.off_route_distance_m + 0.2)}),
     Expect(S.OFF_ROUTE, False, trunk=N - 1, calls=[(N - 1, True, True)]), None),
    # -- the periodic place check (every place_check_every successes)
    ("check due: a place outside the window verifies better elsewhere -> inconsistent, lost, chain doubted",
     TRACKING_AT_10, Leaf(11, scores={FAR: 1.0, 11: 0.5}, replies={FAR: Reply(inliers=CLEAR, leaf_at=FAR)},
                          state={"leaves_since_check": CHECK_DUE}),
     Expect(S.INCONSISTENT, False, trunk=11, calls=[(11, True, True), (FAR, False, False)], doubted=True), None),
    ("check due: the better-scoring place verifies with fewer inliers -> localized", TRACKING_AT_10,
     Leaf(11, scores={FAR: 1.0, 11: 0.5}, replies={FAR: Reply(inliers=PLAIN - 1, leaf_at=FAR)},
          state={"leaves_since_check": CHECK_DUE}),
     Expect(S.LOCALIZED, True, trunk=11, calls=[(11, True, True), (FAR, False, False)]), None),
    ("check due: the better-scoring place agrees through the taught path -> localized", TRACKING_AT_10,
     Leaf(11, scores={FAR: 1.0, 11: 0.5}, replies={FAR: Reply(inliers=CLEAR)}, state={"leaves_since_check": CHECK_DUE}),
     Expect(S.LOCALIZED, True, trunk=11, calls=[(11, True, True), (FAR, False, False)]), None),
    ("check not due: a better-scoring place is not looked at -> localized", TRACKING_AT_10,
     Leaf(11, scores={FAR: 1.0, 11: 0.5}, replies={FAR: Reply(inliers=CLEAR, leaf_at=FAR)}),
     Expect(S.LOCALIZED, True, trunk=11, calls=[(11, True, True)]), None),
    # -- searching: the start
    ("start: a place verified -> unconfirmed (candidate), every proposed place verified", [], Leaf(10),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=10, calls=[(10, False, False), (0, False, False),
                                                                  (1, False, False)]), None),
    ("start: a place verified beyond doubt -> unconfirmed, no other place looked at", [],
     Leaf(10, replies={10: Reply(inliers=CLEAR)}),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=10, calls=[(10, False, False)]), None),
    ("start: the user's hint is verified first", [], Leaf(25, scores={40: 1.0}, replies={25: Reply(inliers=CLEAR)}),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=25, calls=[(25, False, False)]), 25),
    ("start: a place verified next to the leaf's vertex -> re-localized against the nearest", [],
     Leaf(22, scores={20: 1.0}),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=22,
            calls=[(20, False, False), (0, False, False), (1, False, False), (22, True, False)]), None),
    ("start: no proposed place verifies -> the best refusal's reason, lost", [],
     Leaf(10, replies={10: Reply(S.LOW_INLIER_RATIO)}), Expect(S.LOW_INLIER_RATIO, False), None),
    ("start: the place verified lies past the route's end -> off_route", [],
     Leaf(N - 1 + LOC.off_route_distance_m + 0.5, scores={N - 1: 1.0}),
     Expect(S.OFF_ROUTE, False, trunk=N - 1), None),
    # -- searching: confirming a pending candidate with the next keyframe
    ("candidate pending: the next leaf, guided by it, agrees -> localized", PENDING_AT_10, Leaf(11),
     Expect(S.LOCALIZED, True, trunk=11, calls=[(11, True, False)], failures=0), None),
    ("candidate pending: place recognition scores its part of the route low, the places' estimate agrees -> localized",
     PENDING_AT_10, Leaf(11, scores={40: 1.0, 11: 0.5}),
     Expect(S.LOCALIZED, True, trunk=11, calls=[(10, False, False), (40, False, False), (11, False, False),
                                                (0, False, False), (11, True, False)]), None),
    ("candidate pending: the places' estimate disagrees with it -> unconfirmed, a new candidate", PENDING_AT_10,
     Leaf(11, scores={40: 1.0, 11: 0.5},
          replies={10: Reply(S.TOO_FEW_INLIERS), 11: Reply(leaf_at=14.0), 14: Reply(S.TOO_FEW_INLIERS)}),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=11), None),
    ("candidate pending: odometry broke -> the candidate is dropped, the leaf is a new one", PENDING_AT_10,
     Leaf(11, broken=True), Expect(S.UNCONFIRMED, False, candidate=True, trunk=11), None),
    # -- searching: lost, re-entry through the chain's last success
    ("lost (failures): a place verified beyond doubt that the chain predicts -> localized at once (re-entry)",
     LOST_AFTER_10, Leaf(12, replies={12: Reply(inliers=CLEAR)}),
     Expect(S.LOCALIZED, True, trunk=12, calls=[(12, False, False)], failures=0), None),
    ("lost (failures): verified, not beyond doubt -> unconfirmed", LOST_AFTER_10, Leaf(12),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=12), None),
    ("lost (failures): verified beyond doubt where the chain does not predict -> unconfirmed", LOST_AFTER_10,
     Leaf(12, replies={12: Reply(inliers=CLEAR, leaf_at=16.0), 16: Reply(S.TOO_FEW_INLIERS)}),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=12), None),
    ("lost (failures): nothing verifies and the chain is past the route's end -> off_route",
     [*TRACKING_AT_END, *(Leaf(N - 1, replies=REFUSED) for _ in range(LOC.lost_after_failures))],
     Leaf(N - 1 + LOC.off_route_distance_m + 2), Expect(S.OFF_ROUTE, False, trunk=N - 1), None),
    ("lost (distance): a leaf past lost_after_distance_m is searched for; predicted -> re-entry", TRACKING_AT_10,
     Leaf(10 + LOC.lost_after_distance_m + 1, replies={21: Reply(inliers=CLEAR)}),
     Expect(S.LOCALIZED, True, trunk=21, calls=[(21, False, False)]), None),
    ("odometry broke: the leaf is searched for; predicted across the gap -> re-entry", TRACKING_AT_10,
     Leaf(11, broken=True, replies={11: Reply(inliers=CLEAR)}),
     Expect(S.LOCALIZED, True, trunk=11, calls=[(11, False, False)]), None),
    ("odometry broke for longer than max_extrapolation_s -> no prediction, unconfirmed", TRACKING_AT_10,
     Leaf(11, broken=True, dt_s=CFG.smoothing.max_extrapolation_s + 1, replies={11: Reply(inliers=CLEAR)}),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=11), None),
    ("the periodic check doubted the chain -> no re-entry through it, unconfirmed",
     [*TRACKING_AT_10, Leaf(11, scores={FAR: 1.0, 11: 0.5}, replies={FAR: Reply(inliers=CLEAR, leaf_at=FAR)},
                            state={"leaves_since_check": CHECK_DUE})],
     Leaf(12, replies={12: Reply(inliers=CLEAR)}),
     Expect(S.UNCONFIRMED, False, candidate=True, trunk=12, doubted=True), None),
]

# fmt: on


@pytest.mark.parametrize("before, leaf, expect, start", [r[1:] for r in ROWS], ids=[r[0] for r in ROWS])
def test_chain_decision(before: list[Leaf], leaf: Leaf, expect: Expect, start: int | None) -> None:
    run = Run(start)
    for earlier in before:
        run.leaf(earlier)
    attempt = run.leaf(leaf)
    chain, state = run.chain, run.chain.state
    assert attempt.status == expect.status
    assert attempt.success == (expect.status == S.LOCALIZED)
    assert state.tracking == expect.tracking
    assert chain.localized == (expect.tracking if expect.localized is None else expect.localized)
    assert (state.candidate is not None) == expect.candidate
    if expect.candidate:
        assert state.candidate is not None and state.candidate.leaf_id == vertex_id(1, run.leaves)
        assert state.candidate.trunk == attempt.trunk
    assert state.doubted == expect.doubted
    if expect.trunk is not None:
        assert attempt.trunk == expect.trunk
    if expect.calls is not None:
        assert run.localizer.calls == expect.calls
    if expect.failures is not None:
        assert state.consecutive_failures == expect.failures
    if attempt.success:
        assert state.branch == attempt.trunk and chain.twig_id == vertex_id(1, run.leaves)
        np.testing.assert_allclose(attempt.T_report, attempt.estimate.T_leaf_trunk)
        # the estimate is the truth here: the leaf's teach-frame pose is where it really is
        np.testing.assert_allclose(
            chain.T_teach_localized(int(chain.path.ids[attempt.trunk]), attempt.T_report), T_at(leaf.s), atol=1e-9
        )


def test_the_table_covers_every_status() -> None:
    """Each reason a leaf's localization can come to is some row's outcome, except ``no_candidates`` (the place
    index scores every taught vertex, so a non-empty route always proposes one)."""
    assert {r[3].status for r in ROWS} == set(S) - {S.NO_CANDIDATES}
