"""Multi-experience submaps: the landmarks a leaf is localized against, from the taught vertices around the trunk and
from the few earlier repeats (experiences) a recommender picks, all in the trunk's frame (docs/map.md, "Experiences").

An experience vertex localized against taught vertex ``t`` (stored spatial edge ``T_x_t``) sits at ``T_x_trunk =
T_x_t @ inv(T_world_t) @ T_world_trunk`` relative to the trunk, so its landmarks join the submap exactly as a
taught neighbour's do: the estimate is still ``T_leaf_trunk`` against the taught trunk, and everything downstream
(poses, path errors, state.csv, landmarks.csv) stays relative to the taught path.

The recommender (:class:`Recommender`): the experiences that gave inliers to the localizations of the last
``experiences.history_keyframes`` keyframes, most inliers first, take up to ``max_per_keyframe - 1`` places (all
of them when the bound is 1); the other places go to the experiences localized near the trunk whose vertex there
looks most like the leaf to place recognition (cosine of their bag-of-words vectors), the newest first on a tie.
At most ``experiences.max_per_keyframe`` experiences, one vertex each, are matched per keyframe.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import warnings
import zipfile
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..camera import StereoCamera
from ..config import Config, ExperienceConfig
from ..errors import MapError
from ..geometry import inv_T
from ..map import Map, TaughtPath
from ..map.experiences import (
    WORDS_KEY,
    ExperienceInfo,
    ExperienceLinks,
    experience_links,
    experiences,
)
from ..map.records import RUN_SHIFT
from ..state.trajectory import adjoint
from ..types import StereoFrame
from .localization import LocalizationEstimate, Localizer, TaughtSubmap
from .place import PlaceIndex, PlaceMatch

if TYPE_CHECKING:
    from scipy.sparse import csr_matrix

FRAMES_KEPT = 96  # decoded frames held for submaps before the cache starts again (memory stays flat)


def experience_covariance(
    submap: TaughtSubmap, est: LocalizationEstimate, edge_covariance: Callable[[int], np.ndarray | None]
) -> np.ndarray:
    """What the experiences' own placement adds to the covariance of ``est`` (6x6, [rot, trans], the leaf-frame
    perturbation of ``T_leaf_trunk`` as the chain takes it): the adjustment holds each experience vertex ``x`` where
    its stored spatial edge puts it, so that edge's error ``P_x`` moves the estimate by up to ``Ad(T_leaf_x) P_x
    Ad(T_leaf_x)'``. Each experience that gave inliers adds its term whole: a leaf that looks like an experience
    is placed by that experience's landmarks almost alone (weighting the terms by the experiences' share of the
    inliers covered 93-94 % of the errors on kitti06 repeats against earlier ones, whole terms 100 %). Zero without
    experience inliers."""
    out = np.zeros((6, 6))
    if not est.ok or not est.inliers or est.T_leaf_trunk is None:
        return out
    for s in np.unique(submap.slot[est.matched[est.inlier]]):
        P = edge_covariance(int(submap.vertex_ids[s]))
        if P is not None:  # None: a taught vertex, placed by the path itself
            A = adjoint(est.T_leaf_trunk @ inv_T(submap.T_vertex_trunk[s]))
            out += A @ P @ A.T
    return out


def taught_covariance(
    submap: TaughtSubmap, est: LocalizationEstimate, edge_covariance: Callable[[int], np.ndarray | None]
) -> np.ndarray:
    """What the taught map's own placement adds to the covariance of ``est`` (6x6, [rot, trans], as
    :func:`experience_covariance`): the taught landmarks sit where odometry's window refined them, consistent with
    each other and with the window's poses, and the trunk's stored pose is off from them by the error its temporal
    edge's covariance ``P_t`` says. The estimate is relative to that stored pose, so it carries ``P_t`` moved to the
    leaf, ``Ad(T_leaf_trunk) P_t Ad(T_leaf_trunk)'``, whichever taught vertices gave the inliers. (Each vertex's
    edge added whole, as before, was about twice kitti06's errors in sigma; the adjustment with the neighbours free
    under their edges' priors moves the covariance by a few percent.) Zero without taught inliers
    (docs/localization.md, "What the covariance holds")."""
    if not est.ok or not est.inliers or est.T_leaf_trunk is None:
        return np.zeros((6, 6))
    slots = np.unique(submap.slot[est.matched[est.inlier]])
    if not any(edge_covariance(int(submap.vertex_ids[s])) is not None for s in slots):
        return np.zeros((6, 6))  # experiences' inliers only
    P = edge_covariance(int(submap.vertex_ids[submap.trunk_slot]))
    if P is None:
        return np.zeros((6, 6))
    A = adjoint(est.T_leaf_trunk)
    return A @ np.asarray(P, float) @ A.T


class ExperienceLocalizer(Localizer):
    """The :class:`~vtr.navigation.localization.Localizer` whose estimates carry the experiences' placement error
    (:func:`experience_covariance`) in their covariance, before any gate sees them. ``experiences`` is set by the
    repeat once its submaps exist (None: the estimates are the localizer's own)."""

    experiences: ExperienceSubmaps | None = None

    def localize(self, leaf: StereoFrame, submap: TaughtSubmap, *args: Any, **kwargs: Any) -> LocalizationEstimate:
        est = super().localize(leaf, submap, *args, **kwargs)
        if self.experiences is None or not est.ok:
            return est
        extra = experience_covariance(submap, est, self.experiences.edge_covariance) + taught_covariance(
            submap, est, self.experiences.taught_edge_covariance
        )
        if not extra.any():
            return est
        return dataclasses.replace(est, covariance=est.covariance + extra, frame_covariance=extra)


def single_experience(config: Config) -> Config:
    """``config`` localizing against the teach alone (``experiences.max_per_keyframe`` 0): for experiments that
    characterise localization against the taught landmarks (offsets, the perception model's data), where earlier
    repeats appended to the same map must not help."""
    return dataclasses.replace(config, experiences=dataclasses.replace(config.experiences, max_per_keyframe=0))


DIGEST_BYTES = 8  # of the vocabulary the words are of


def _encode_words(words: dict[int, np.ndarray]) -> bytes:
    vids = np.array(sorted(words), np.int64)
    top = max((int(w.max()) for w in words.values() if len(w)), default=0)
    dtype = np.uint16 if top <= np.iinfo(np.uint16).max else np.int32  # 1024 words: two bytes a feature
    parts = [np.asarray(words[int(v)], dtype) for v in vids]
    buf = io.BytesIO()
    np.savez(
        buf,
        vertex_id=vids,
        indptr=np.r_[0, np.cumsum([len(p) for p in parts])].astype(np.int64),
        words=np.concatenate(parts) if parts else np.zeros(0, dtype),
    )
    return buf.getvalue()


def _decode_words(data: bytes | None) -> dict[int, np.ndarray] | None:
    """The stored words, or None when absent or unreadable (derived data: rebuilt from the vertices)."""
    if data is None:
        return None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            vids, indptr, words = z["vertex_id"], z["indptr"], z["words"]
        if len(indptr) != len(vids) + 1 or indptr[-1] != len(words):
            return None
        words = words.astype(np.int64)
        return {int(v): words[indptr[i] : indptr[i + 1]] for i, v in enumerate(vids)}
    except (ValueError, KeyError, OSError, zipfile.BadZipFile):
        return None


class Recommender:
    """Picks the experiences a keyframe is matched against (module docstring: the rule and its bound)."""

    def __init__(self, config: ExperienceConfig):
        self.config = config
        self._history: deque[dict[int, int]] = deque(maxlen=config.history_keyframes)

    def observe(self, inliers_by_experience: dict[int, int]) -> None:
        """The inliers each experience gave the latest keyframe's localization (empty when it failed)."""
        self._history.append(dict(inliers_by_experience))

    def recent(self) -> dict[int, int]:
        """Inliers per experience over the remembered keyframes."""
        out: dict[int, int] = {}
        for h in self._history:
            for e, n in h.items():
                out[e] = out.get(e, 0) + n
        return out

    def choose(self, available: np.ndarray, similarity: Callable[[np.ndarray], np.ndarray]) -> list[int]:
        """At most ``max_per_keyframe`` of the ``available`` experience runs; ``similarity(runs)`` gives the place
        recognition score of each (asked only when places remain after the recent ones)."""
        k = self.config.max_per_keyframe
        available = np.asarray(available, np.int64)
        if k == 0 or len(available) == 0:
            return []
        recent = self.recent()
        ranked = sorted(
            (e for e in (int(a) for a in available) if recent.get(e, 0) > 0), key=lambda e: (-recent[e], -e)
        )
        chosen = ranked[: k - 1 if k > 1 else k]
        rest = available[~np.isin(available, chosen)]
        if len(chosen) < k and len(rest):
            score = np.asarray(similarity(rest), float)
            order = np.lexsort((-rest, -score))
            chosen += [int(e) for e in rest[order][: k - len(chosen)]]
        return chosen


class ExperiencePlaces:
    """Place recognition over the taught vertices and the experiences localized at them: the score of a taught
    vertex is the best of its own and of the experience vertices localized against it (so a place whose look has
    drifted from the teach is still proposed when an earlier repeat saw it so). Everything else is the taught
    :class:`~vtr.navigation.place.PlaceIndex`'s; the experience vertices' vectors are computed on first use."""

    def __init__(self, index: PlaceIndex, submaps: ExperienceSubmaps):
        self.index = index
        self.vocabulary = index.vocabulary
        self._submaps = submaps
        self._matrix = None
        self._slots = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self.index)

    def __getattr__(self, name: str) -> Any:
        if name == "index":  # not set yet (copying): no recursion
            raise AttributeError(name)
        return getattr(self.index, name)  # anything else is the taught index's

    def query(self, descriptors: np.ndarray, k: int) -> PlaceMatch:
        """The ``k`` best-scoring taught vertices (path indices) by :meth:`scores`, best first."""
        s = self.scores(descriptors)
        top = np.argsort(-s, kind="stable")[: min(int(k), len(s))]
        return PlaceMatch(top.astype(np.int64), s[top])

    def vector(self, descriptors: np.ndarray) -> np.ndarray:
        return self.index.vector(descriptors)

    def _experience_matrix(self) -> csr_matrix:
        from scipy.sparse import csr_matrix  # scipy.sparse (~0.1 s) only once experiences are scored

        if self._matrix is None:
            slots, vids = self._submaps.placed_vertices()
            vectors = [self._submaps.vector(int(v)) for v in vids]
            self._matrix = csr_matrix(np.array(vectors, np.float32).reshape(len(vids), len(self.vocabulary)))
            self._slots = slots
        return self._matrix

    def scores(self, descriptors: np.ndarray, also: np.ndarray | slice | None = None) -> np.ndarray:
        """Cosine score (V,) of the taught vertices against a query (those the taught index scores, ``also``
        included: :meth:`PlaceIndex.scores`): the best of the vertex's and its experiences'."""
        out = self.index.scores(descriptors, also=also)
        q = self.index.vector(descriptors)
        E = self._experience_matrix()
        if E.shape[0]:
            np.maximum.at(out, self._slots, np.asarray(E @ q, np.float64).ravel())
        return out


class ExperienceSubmaps:
    """Builds the submap of a trunk (the ``submap`` of :class:`~vtr.navigation.chain_localizer.ChainLocalizer`) with the
    experiences the recommender picks, and learns from each localization which ones matched.

    ``exclude``: runs never used (the repeat under way). Trusted experiences are read once, when the repeat starts.
    """

    def __init__(
        self,
        map_: Map,
        path: TaughtPath,
        config: ExperienceConfig,
        neighbours: int,
        camera: StereoCamera,
        place: PlaceIndex,
        exclude: tuple[int, ...] = (),
        warn: Callable[[str], None] | None = None,
    ):
        """``config``: the experiences section; ``neighbours``: taught vertices on each side of a trunk in its
        submap (``localization.neighbour_vertices``)."""
        self.map = map_
        self.path = path
        self.camera = camera
        self.place = place
        self.neighbours = neighbours
        self.recommender = Recommender(config)
        self._warn = warn
        self.infos: list[ExperienceInfo] = []
        trusted: list[int] = []
        if config.max_per_keyframe > 0:
            self.infos = experiences(map_, config.min_localized_share, exclude)
            trusted = [e.run for e in self.infos if e.trusted]
        self.links: ExperienceLinks = experience_links(map_, trusted)
        taught_slot = np.searchsorted(path.ids, self.links.taught_id)
        ok = (taught_slot < len(path.ids)) & (
            path.ids[np.minimum(taught_slot, len(path.ids) - 1)] == self.links.taught_id
        )
        self._link_slot = np.where(ok, taught_slot, -1)  # path index of each link's taught vertex
        self._rows_of: dict[int, list[int]] = {}
        for row, vid in enumerate(self.links.vertex_id.tolist()):
            self._rows_of.setdefault(int(vid), []).append(row)
        self._taught_runs = frozenset(int(r) for r in np.unique(path.ids >> RUN_SHIFT))
        self._frames: dict[int, StereoFrame] = {}
        self._taught_edges: dict[int, np.ndarray | None] = {}
        self._submaps: dict[tuple[int, tuple[int, ...]], TaughtSubmap] = {}
        self._vectors: dict[int, np.ndarray] = {}
        self._words: dict[int, dict[int, np.ndarray]] = {}
        self._damaged: set[int] = set()
        self._leaf: StereoFrame | None = None
        self._leaf_vector: np.ndarray | None = None
        self._chosen: dict[int, tuple[int, ...]] = {}  # this leaf's choice per trunk
        self._leaf_submaps: dict[int, TaughtSubmap] = {}  # this leaf's submap per trunk
        self._used: dict[int, int] = {}  # keyframes each experience gave inliers to

    @property
    def trusted(self) -> list[int]:
        """The experience runs this repeat may use."""
        return sorted(int(r) for r in np.unique(self.links.run) if int(r) not in self._damaged)

    @property
    def used(self) -> dict[int, int]:
        """Keyframes of this repeat each experience gave localization inliers to."""
        return dict(self._used)

    def frame(self, vid: int) -> StereoFrame:
        """The stored frame of a vertex (kept while recent submaps use it)."""
        f = self._frames.get(vid)
        if f is None:
            if len(self._frames) > FRAMES_KEPT:
                self._frames, self._submaps = {}, {}
            f = self._frames[vid] = self.map.vertex(vid).frame
        return f

    def set_leaf(self, leaf: StereoFrame) -> None:
        """The keyframe about to be localized (its submaps may choose other experiences than the last one's)."""
        self._leaf, self._leaf_vector, self._chosen, self._leaf_submaps = leaf, None, {}, {}

    # -- the recommender's inputs ------------------------------------------------------------------

    def _near(self, trunk: int) -> tuple[np.ndarray, np.ndarray]:
        """(runs, link rows): per trusted experience localized within the submap's taught vertices, the link
        nearest the trunk (most inliers on a tie)."""
        rows = np.flatnonzero((self._link_slot >= 0) & (np.abs(self._link_slot - trunk) <= self.neighbours))
        if self._damaged:
            rows = rows[~np.isin(self.links.run[rows], list(self._damaged))]
        if len(rows) == 0:
            return np.zeros(0, np.int64), rows
        order = np.lexsort((-self.links.inliers[rows], np.abs(self._link_slot[rows] - trunk), self.links.run[rows]))
        rows = rows[order]
        runs, first = np.unique(self.links.run[rows], return_index=True)
        return runs, rows[first]

    def _similarity(self, rows: np.ndarray) -> np.ndarray:
        """Place-recognition cosine between the leaf and each link's experience vertex."""
        if self._leaf is None:
            return np.zeros(len(rows))
        if self._leaf_vector is None:
            self._leaf_vector = self.place.vector(self._leaf.features.descriptors)
        return np.array([float(self.vector(int(vid)) @ self._leaf_vector) for vid in self.links.vertex_id[rows]])

    def taught_edge_covariance(self, vid: int) -> np.ndarray | None:
        """The stored covariance of the temporal edge that placed taught vertex ``vid`` after its predecessor (the
        first vertex of a run: the edge to its successor); None for a vertex not of the taught runs or without
        temporal edges."""
        if int(vid) >> RUN_SHIFT not in self._taught_runs:
            return None
        if vid not in self._taught_edges:
            P = None
            for a, b in ((vid - 1, vid), (vid, vid + 1)):
                try:
                    P = np.asarray(self.map.edge(a, b, "temporal").covariance, float)
                    break
                except MapError:
                    continue
            self._taught_edges[vid] = P
        return self._taught_edges[vid]

    def edge_covariance(self, vid: int) -> np.ndarray | None:
        """The stored covariance of the spatial edge that places experience vertex ``vid`` (None: not an experience
        vertex of this repeat). The vertex nearest the trunk is used when several edges place it."""
        rows = self._rows_of.get(vid)
        return None if rows is None else self.links.covariance[rows[0]]

    def placed_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """(taught path index, experience vertex id) of every trusted experience vertex localized on the path."""
        rows = np.flatnonzero(self._link_slot >= 0)
        return self._link_slot[rows], self.links.vertex_id[rows]

    def vector(self, vid: int) -> np.ndarray:
        """Place-recognition vector of an experience vertex: its words (:meth:`run_words`) weighted by the taught
        index's inverse document frequencies, unit length (what ``PlaceIndex.vector`` gives its descriptors)."""
        v = self._vectors.get(vid)
        if v is None:
            words = self.run_words(vid >> RUN_SHIFT).get(vid)
            v = np.zeros(len(self.place.vocabulary))
            if words is not None and len(words):
                v = np.bincount(words, minlength=len(self.place.vocabulary)) * np.asarray(self.place.idf, float)
                v = v / max(float(np.linalg.norm(v)), np.finfo(float).tiny)
            self._vectors[vid] = v
        return v

    def run_words(self, run: int) -> dict[int, np.ndarray]:
        """The vocabulary words of every placed vertex of an experience (vertex id -> word per feature): stored in the
        map's derived data (``experience_words/<run>/<vocabulary digest>``) the first time a repeat needs them, so a
        later repeat reads them instead of reading and describing every experience vertex again. {} for a damaged
        experience."""
        words = self._words.get(run)
        if words is not None:
            return words
        key = f"{WORDS_KEY}/{run}/{self._vocabulary_digest()}"
        words = _decode_words(self.map.derived(key)) if run not in self._damaged else {}
        if words is None:
            vids = np.unique(self.links.vertex_id[self.links.run == run])
            try:
                words = {
                    int(v): self.place.vocabulary.words_of(self.map.vertex(int(v)).frame.features.descriptors)
                    for v in vids
                }
            except MapError as err:  # a vertex that does not read back whole: its experience is never used
                self._drop({run}, err)
                words = {}
            else:
                if self.map.mode == "a":
                    self.map.put_derived(key, _encode_words(words))
        self._words[run] = words
        return words

    def _vocabulary_digest(self) -> str:
        voc = self.place.vocabulary
        return hashlib.blake2b(
            np.ascontiguousarray(voc.top).tobytes() + np.ascontiguousarray(voc.leaves).tobytes(),
            digest_size=DIGEST_BYTES,
        ).hexdigest()

    def _drop(self, runs: set[int], err: MapError) -> None:
        runs = runs - self._damaged  # said once per experience
        if not runs:
            return
        self._damaged |= runs
        message = f"experience run(s) {sorted(runs)} not used: {err}"
        if self._warn is not None:
            self._warn(message)
        else:
            warnings.warn(message, RuntimeWarning, stacklevel=3)

    def places(self) -> ExperiencePlaces:
        """Place recognition over the taught vertices and the experiences localized at them."""
        return ExperiencePlaces(self.place, self)

    # -- submaps -----------------------------------------------------------------------------------

    def submap(self, trunk: int) -> TaughtSubmap:
        """The trunk, its ``neighbour_vertices`` taught neighbours on each side, and one vertex of each chosen
        experience, in the trunk's frame."""
        sub = self._leaf_submaps.get(trunk)
        if sub is not None:
            return sub
        chosen = self._chosen.get(trunk)
        runs, rows = self._near(trunk)
        if chosen is None:
            by_run = dict(zip(runs.tolist(), rows.tolist(), strict=True))
            picked = self.recommender.choose(runs, lambda rs: self._similarity(np.array([by_run[int(r)] for r in rs])))
            chosen = self._chosen[trunk] = tuple(sorted(picked))
        key = (trunk, chosen)
        sub = self._submaps.get(key)
        if sub is not None:
            self._leaf_submaps[trunk] = sub
            return sub
        try:
            sub = self._build(trunk, [int(rows[np.flatnonzero(runs == e)[0]]) for e in chosen])
        except MapError as err:  # an experience vertex that does not read back whole: never used again
            bad = {e for e in chosen if not self._readable(int(rows[np.flatnonzero(runs == e)[0]]))}
            if not bad:
                raise
            self._drop(bad, err)
            self._chosen.pop(trunk, None)
            return self.submap(trunk)
        self._submaps[key] = self._leaf_submaps[trunk] = sub
        return sub

    def _readable(self, row: int) -> bool:
        try:
            self.frame(int(self.links.vertex_id[row]))
        except MapError:
            return False
        return True

    def _build(self, trunk: int, rows: list[int]) -> TaughtSubmap:
        path, n = self.path, self.neighbours
        slots = np.arange(max(trunk - n, 0), min(trunk + n + 1, len(path.ids)))
        T_world = path.T_world_vertex
        ids = [int(i) for i in path.ids[slots]]
        T_vertex_trunk = list(inv_T(T_world[slots]) @ T_world[trunk])
        for r in rows:
            ids.append(int(self.links.vertex_id[r]))
            s = int(self._link_slot[r])
            T_vertex_trunk.append(self.links.T_vertex_taught[r] @ inv_T(T_world[s]) @ T_world[trunk])
        frames = [self.frame(i) for i in ids]
        return TaughtSubmap.build(
            frames,
            np.array(ids, np.int64),
            np.array(T_vertex_trunk),
            int(np.flatnonzero(slots == trunk)[0]),
            self.camera,
        )

    # -- learning from the localizations -----------------------------------------------------------

    def observe(self, sub: TaughtSubmap | None, est: LocalizationEstimate | None, success: bool) -> tuple[int, ...]:
        """Tell the recommender which experiences gave inliers to the leaf's localization (none when it failed);
        returns them (the experience runs a success used, the teach's not included)."""
        used: dict[int, int] = {}
        if success and sub is not None and est is not None and est.inliers:
            runs, counts = np.unique(sub.experience[est.matched[est.inlier]], return_counts=True)
            used = {int(r): int(c) for r, c in zip(runs, counts, strict=True) if int(r) not in self._taught_runs}
        self.recommender.observe(used)
        for e in used:
            self._used[e] = self._used.get(e, 0) + 1
        return tuple(sorted(used))

    def chosen_submap(self, trunk: int) -> TaughtSubmap | None:
        """The submap this leaf was localized against at ``trunk`` (None when none was built)."""
        return self._leaf_submaps.get(trunk)


__all__ = [
    "ExperienceLocalizer",
    "ExperiencePlaces",
    "ExperienceSubmaps",
    "Recommender",
    "experience_covariance",
    "single_experience",
]
