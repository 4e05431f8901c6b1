"""Repeat on top of odometry, the map and the localization chain (docs/localization.md).

* ``Repeat``: a program feeds frames one by one (``process_frame``) or as a stream (``steps``);
  odometry runs on the new run (stored in the same map as a repeat run), and every new keyframe
  (leaf) is localized against the taught path through the ``LocalizationChain``, then written to the map with its
  localization record in one transaction (:meth:`vtr.map.Map.add_leaf`). ``latest`` is the latest localization
  delivered.

Localizing a leaf needs its odometry and the localizations before it, never a later frame's odometry nor the map's
repeat vertices, and the odometry never needs a localization: so ``steps`` commits each leaf on a writer thread while
the next frames are processed, and localizes on a thread of its own too (``localization.thread``), in order, while
the odometry goes on with the next frames. The results are those of ``process_frame`` frame after frame, bit for bit.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Generator, Iterable
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import cast

import numpy as np

from ..config import Config
from ..geometry import usable_covariance
from ..map import Map, VertexRecord, split_vertex_id, vertex_id
from ..map.localizations import Leaf, LocalizationRecord, SpatialEdge
from ..map.writer import LeafWriter
from ..signals import held_signals
from ..types import FrameKind, Keyframe, OdometryResult, StereoFrame, StereoImages
from ..vo.odometry import OdometrySettings, StereoOdometry
from .chain import LocalizationChain
from .chain_localizer import ChainLocalizer
from .experiences import ExperienceLocalizer, ExperienceSubmaps
from .localization import Localization, LocalizationStatus, TaughtSubmap, landmark_record
from .place import PlaceIndex, route_place_index


@dataclass(frozen=True)
class RepeatStep:
    """What one repeat frame produced: its odometry result, and a localization when it became a vertex.

    ``T_teach_frame`` is the frame's camera pose in the teach run's first camera frame, as the
    chain estimates it (odometry from the last localization). ``localized`` and ``direction`` are the chain's
    verdict after the frame (:attr:`LocalizationChain.localized`, the one owner of "localized"; +1 / -1 / 0
    undecided): what every reader downstream (the state estimator, ``state.csv``, a controller) takes as given.
    """

    odometry: OdometryResult
    localization: Localization | None
    vertex_id: int
    T_teach_frame: np.ndarray
    localization_seconds: float = 0.0  # time spent localizing this frame (0 when it made no vertex)
    localized: bool = False
    direction: int = 0


LOCALIZATION_LOOKAHEAD = 2  # frames the odometry may run ahead of the steps handed out (localized and written)
PREFETCH_STEPS = (1, 2)  # taught vertices decoded ahead, counted past the submap's edge in the direction of travel

_Pending = tuple[RepeatStep, "Future[VertexRecord] | None"]  # a localized frame's step and its map write under way


def _ready(future: Future[_Pending]) -> bool:
    """Whether a frame's step can be handed out: localized (or failed) and its map write ended."""
    if not future.done():
        return False
    if future.cancelled() or future.exception() is not None:
        return True
    write = future.result()[1]
    return write is None or write.done()


def localization_record(loc: Localization) -> LocalizationRecord:
    """What the map keeps of a localization (its ``localization.csv`` row's fields, the full covariance)."""
    return LocalizationRecord(
        t_ns=loc.t_ns,
        leaf_id=loc.leaf_id,
        trunk_id=loc.trunk_id,
        twig_id=loc.twig_id,
        branch_id=loc.branch_id,
        success=loc.success,
        matches=loc.matches,
        inliers=loc.inliers,
        T_leaf_trunk=loc.T_leaf_trunk,
        covariance=loc.covariance,
        consecutive_failures=loc.consecutive_failures,
        distance_since_success_m=loc.distance_since_success_m,
        status=loc.status.value,
        direction=loc.direction,
        experiences=loc.experiences,
    )


def localization_of_record(record: LocalizationRecord) -> Localization:
    """The localization a map record stores (without its landmark record: ``landmarks.csv`` is not in the map)."""
    return Localization(
        t_ns=record.t_ns,
        leaf_id=record.leaf_id,
        trunk_id=record.trunk_id,
        twig_id=record.twig_id,
        branch_id=record.branch_id,
        success=record.success,
        matches=record.matches,
        inliers=record.inliers,
        T_leaf_trunk=np.array(record.T_leaf_trunk),
        covariance=np.array(record.covariance),
        consecutive_failures=record.consecutive_failures,
        distance_since_success_m=record.distance_since_success_m,
        status=LocalizationStatus(record.status),
        direction=record.direction,
        experiences=record.experiences,
    )


class Repeat:
    """Repeat pipeline: feed frames with ``process`` / ``process_frame``, or a stream to ``steps``;
    ``latest`` holds the latest localization delivered."""

    def __init__(
        self,
        map_: Map,
        config: Config,
        source: str = "",
        start_index: int | None = None,
        allow_partial: bool = False,
        warn: Callable[[str], None] | None = None,
    ):
        """Refuses (``MapError``) a map whose taught run is not finished unless ``allow_partial``. ``config``: a
        run-level root, it hands each part its sections (docs/configuration.md).

        ``start_index`` (optional) is a hint: the taught vertex (path index) the repeat starts near. Without
        it place recognition finds where on the route the repeat is; with it that vertex is tried first.
        ``warn`` is told when the map's stored place index had to be rebuilt (else a ``RuntimeWarning``).
        """
        self.map = map_
        self.camera = map_.camera
        self.config = config
        map_.check_taught_route(allow_partial)
        self.chain = LocalizationChain(map_.taught_path(), config.localization, config.smoothing, start_index)
        self.localizer = ExperienceLocalizer(
            self.camera, config.localization, config.estimation, config.stereo.pixel_sigma
        )
        self.place = route_place_index(map_, config.place, config.run.seed, warn)
        self._odometry_broken = False  # odometry failed since the previous leaf
        self.odometry = StereoOdometry(self.camera, OdometrySettings.of(config), keep_history=False)
        self.timer = self.odometry.timer  # odometry stages plus "map_write" and "localization"
        self.run = map_.begin_run("repeat", source=source, privileged=False)
        self._next_vertex = map_.next_vertex_id(self.run)  # the id the next leaf gets (leaves are written in order)
        # taught submaps plus the experiences (earlier repeats) a recommender picks (vtr.navigation.experiences)
        self.submaps = ExperienceSubmaps(
            map_,
            self.chain.path,
            config.experiences,
            config.localization.neighbour_vertices,
            self.camera,
            self.place,
            (self.run,),
            warn,
        )
        self.localizer.experiences = self.submaps  # estimates carry the experiences' placement error
        # the chain only asks place recognition for scores: the experiences' stand in for the teach's alone
        places = cast(PlaceIndex, self.submaps.places()) if self.submaps.trusted else self.place
        self.chain_localizer = ChainLocalizer(
            self.chain, self.localizer, places, self._submap, config.localization, config.place, config.run.seed
        )
        self.latest: Localization | None = None
        self._leaf: int | None = None  # map id of the newest repeat vertex
        self._kf_of_leaf: dict[int, int] = {}  # odometry keyframe id of each recent leaf
        self._undelivered: list[RepeatStep] = []

    def process(self, images: StereoImages) -> RepeatStep:
        """Stereo-process a rectified pair, then :meth:`process_frame`."""
        return self.process_frame(self.odometry.stereo.process(images))

    def process_frame(self, frame: StereoFrame) -> RepeatStep:
        """Odometry on the frame; localize it when it becomes a new vertex, and write that vertex with its
        localization to the map (one transaction) before returning."""
        result, window = self._odometry(frame)
        step, leaf = self._localize_step(result, window)
        if leaf is not None and result.new_keyframe is not None:
            with self.timer("map_write"):
                self.map.add_leaf(self.run, result.new_keyframe, leaf, self.camera.T_vehicle_sensor)
        return self._deliver(step)

    def _odometry(self, frame: StereoFrame) -> tuple[OdometryResult, dict[int, np.ndarray]]:
        """The frame's odometry and the window's keyframe poses right after it (what its localization reads)."""
        result = self.odometry.process_frame(frame)
        return result, self.odometry.window_poses() if result.new_keyframe is not None else {}

    def steps(self, frames: Iterable[StereoFrame]) -> Generator[RepeatStep, None, None]:
        """:meth:`process_frame` over ``frames``, in order: the same steps bit for bit, pipelined.

        Each new vertex's map write (:meth:`~vtr.map.Map.add_leaf`: vertex, edges and localization record in one
        transaction) is committed by a writer thread (:class:`~vtr.map.writer.LeafWriter`) while the next frames
        are processed, and the localizations run on a thread of their own too (in order; ``localization.thread``
        "own", the default, for every ``features.threads``) while the odometry goes on. A step is handed out only
        once its write committed, at most ``LOCALIZATION_LOOKAHEAD`` frames after its odometry: the map holds every
        vertex whose step was handed out.
        While the stream is open only the writer writes the map. Closing it early (an error, Ctrl-C) lets the
        localization under way finish, drops those not started and commits the ones localized; after a failed
        localization or write (a full disk...) nothing later is written: the vertices in the map are whole and in
        order, and :meth:`take_undelivered` gives the steps the map holds that the stream did not hand out.
        """
        own = self.config.localization.thread == "own"
        pool = ThreadPoolExecutor(1, thread_name_prefix="vtr-localize") if own else None
        writer = LeafWriter(self.map, self.timer)
        failed = threading.Event()

        def localize(result: OdometryResult, window: dict[int, np.ndarray]) -> _Pending:
            if failed.is_set():  # an earlier vertex failed: never localize or write a later one
                raise CancelledError()
            try:
                step, leaf = self._localize_step(result, window)
                kf = result.new_keyframe
                write = (
                    None
                    if leaf is None or kf is None
                    else writer.submit(self.run, kf, leaf, self.camera.T_vehicle_sensor)
                )
                if step.localization is not None:
                    writer.prefetch(self._next_taught(step.localization.trunk_id, step.direction))
                return step, write
            except BaseException:
                failed.set()
                raise

        pending: deque[Future[_Pending]] = deque()
        yielded: RepeatStep | None = None  # the newest step handed out (its caller may not have taken it)
        try:
            for frame in frames:
                with held_signals():  # Ctrl-C between frames, never inside a compiled kernel
                    result = self._odometry(frame)
                    if pool is None:
                        done: Future[_Pending] = Future()
                        done.set_result(localize(*result))
                    else:
                        done = pool.submit(localize, *result)
                    pending.append(done)
                while pending and (len(pending) > LOCALIZATION_LOOKAHEAD or _ready(pending[0])):
                    yielded = self._take(pending.popleft())
                    yield yielded
            while pending:
                yielded = self._take(pending.popleft())
                yield yielded
            yielded = None
        finally:
            for future in pending:
                future.cancel()
            if pool is not None:
                pool.shutdown(wait=True)
            writer.close()  # the leaves localized are committed (none after a failed one)
            # steps the map holds but the stream did not deliver (it was closed early): a caller that reports every
            # step takes them with take_undelivered, so the map and its reports agree
            out = [] if yielded is None else [yielded]
            for future in pending:
                if future.cancelled() or not _ready(future) or future.exception() is not None:
                    break
                step, write = future.result()
                if write is not None and (write.cancelled() or write.exception() is not None):
                    break
                out.append(self._deliver(step))
            self._undelivered = out

    def _next_taught(self, trunk_id: int, direction: int) -> list[int]:
        """The taught vertices the next leaves' submaps will read first after one at ``trunk_id``: those just past
        its submap (``neighbour_vertices`` each side) in the direction of travel (both ways while undecided). Reading
        them ahead changes no result (a vertex decodes the same whenever it is read)."""
        path, n = self.chain.path, self.config.localization.neighbour_vertices
        trunk = path.index(trunk_id)
        ahead = [trunk + d * (n + k) for d in ((direction,) if direction else (1, -1)) for k in PREFETCH_STEPS]
        return [int(path.ids[i]) for i in ahead if 0 <= i < len(path)]

    def _take(self, future: Future[_Pending]) -> RepeatStep:
        """The step of a localized frame once its map write committed (raising the localization's or the write's
        error)."""
        step, write = future.result()
        if write is not None:
            write.result()
        return self._deliver(step)

    def take_undelivered(self) -> list[RepeatStep]:
        """Steps written to the map (and localized) that a stream closed early may not have delivered, in order
        (once): those it never yielded, after the last one it yielded (a caller that took that one skips it)."""
        out, self._undelivered = self._undelivered, []
        return out

    def _deliver(self, step: RepeatStep) -> RepeatStep:
        if step.localization is not None:
            self.latest = step.localization
        return step

    def _localize_step(
        self, result: OdometryResult, window: dict[int, np.ndarray] | None = None
    ) -> tuple[RepeatStep, Leaf | None]:
        """The step of an odometry result, its keyframe localized (``window``: the odometry window's keyframe poses
        right after it, by odometry keyframe id), and what the map is to store with that keyframe (None: no
        keyframe). The keyframe's vertex id is the next of the run: the caller writes the leaves in order."""
        loc, seconds, leaf = None, 0.0, None
        vid = self._leaf if self._leaf is not None else -1
        if result.kind == FrameKind.FAILURE:
            self._odometry_broken = True
        if result.new_keyframe is not None:
            kf = result.new_keyframe
            vid = self._next_vertex
            self._next_vertex = vertex_id(self.run, split_vertex_id(vid)[1] + 1)
            self._leaf = vid
            self._kf_of_leaf[vid] = kf.id
            t0 = time.perf_counter()
            with self.timer("localization"):
                loc, leaf = self._localize(vid, kf, window or {})
            seconds = time.perf_counter() - t0
        return RepeatStep(
            result,
            loc,
            vid,
            self.T_teach(result.T_world_frame),
            seconds,
            localized=self.chain.localized,
            direction=self.chain.state.direction,
        ), leaf

    def T_teach(self, T_world_frame: np.ndarray) -> np.ndarray:
        """A repeat camera pose (repeat run's world) in the teach run's first camera frame, via the chain."""
        return self.chain.T_teach(T_world_frame)

    def _localize(self, leaf_id: int, kf: Keyframe, window: dict[int, np.ndarray]) -> tuple[Localization, Leaf]:
        c = self.chain
        twig, branch = c.twig_id, c.branch_id
        broken, self._odometry_broken = self._odometry_broken, False
        # the leaves still in the odometry window where its latest adjustment put them
        current = {leaf: window[k] for leaf, k in self._kf_of_leaf.items() if k in window}
        self._kf_of_leaf = {leaf: k for leaf, k in self._kf_of_leaf.items() if k in window}
        self.submaps.set_leaf(kf.frame)
        attempt = self.chain_localizer.localize(leaf_id, kf, broken, current)
        est = attempt.estimate
        trunk_id = int(c.path.ids[attempt.trunk])
        covariance = est.covariance
        spatial = None
        if attempt.success:
            assert est.T_leaf_trunk is not None
            covariance = usable_covariance(est.covariance, self.config.odometry.failure_variance)
            spatial = SpatialEdge(trunk_id, est.T_leaf_trunk, covariance, est.inliers)
        used = self.submaps.observe(self.submaps.chosen_submap(attempt.trunk), est, attempt.success)
        record = None
        if attempt.success:  # landmarks.csv (the perception model's training data) holds successes only
            sub = self._submap(attempt.trunk)
            with self.localizer.timer("landmark_record"):
                record = landmark_record(
                    self.submaps.frame(trunk_id),
                    attempt.T_report,
                    self.camera,
                    sub.trunk_features(est.matched),
                    sub.trunk_features(est.matched[est.inlier]),
                    t_ns=kf.t_ns,
                    leaf_id=leaf_id,
                    trunk_id=trunk_id,
                )
        s = c.state
        loc = Localization(
            t_ns=kf.t_ns,
            leaf_id=leaf_id,
            trunk_id=trunk_id,
            twig_id=twig,
            branch_id=branch,
            success=attempt.success,
            matches=est.matches,
            inliers=est.inliers,
            T_leaf_trunk=attempt.T_report,
            covariance=covariance,
            consecutive_failures=s.consecutive_failures,
            distance_since_success_m=s.distance_since_success_m,
            landmarks=record,
            status=attempt.status,
            direction=s.direction,
            experiences=used,
            frame_covariance=est.frame_covariance if attempt.success else None,
        )
        return loc, Leaf(localization_record(loc), spatial, used)

    def _submap(self, trunk: int) -> TaughtSubmap:
        """The trunk and its ``neighbour_vertices`` taught neighbours on each side, with the experiences the
        recommender picks, as a submap in the trunk's frame (:class:`~vtr.navigation.experiences.ExperienceSubmaps`)."""
        with self.localizer.timer("submap"):
            return self.submaps.submap(trunk)
