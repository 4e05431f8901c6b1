"""Repeat on top of odometry, the map and the localization chain.

* ``Repeat``: a program feeds frames one by one (``process_frame``) or as a stream (``steps``);
  odometry runs on the new run (stored in the same map as a repeat run), and every new keyframe
  (leaf) is localized against the taught path through the ``LocalizationChain``. ``latest`` is the
  latest localization delivered.

Localizing a leaf needs its odometry and the localizations before it, never a later frame's
odometry, and the odometry never needs a localization: so ``steps`` with 2 or more threads runs each
new vertex's map write and localization on a thread of their own, in order, while the odometry goes
on with the next frames. The results are those of ``process_frame`` frame after frame, bit for bit.
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
from ..map import Map
from ..signals import held_signals
from ..types import FrameKind, Keyframe, OdometryResult, StereoFrame, StereoImages
from ..vo.odometry import OdometrySettings, StereoOdometry
from .chain import ChainLocalizer, LocalizationChain
from .experiences import ExperienceLocalizer, ExperienceSubmaps
from .localization import Localization, TaughtSubmap, landmark_record
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
    localization_seconds: float = 0.0     # time spent localizing this frame (0 when it made no vertex)
    localized: bool = False
    direction: int = 0


LOCALIZATION_LOOKAHEAD = 2   # frames the odometry may run ahead of the localization thread in ``steps``


class Repeat:
    """Repeat pipeline: feed frames with ``process`` / ``process_frame``, or a stream to ``steps``;
    ``latest`` holds the latest localization delivered."""

    def __init__(self, map_: Map, config: Config, source: str = "", start_index: int | None = None,
                 allow_partial: bool = False, warn: Callable[[str], None] | None = None):
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
        self.localizer = ExperienceLocalizer(self.camera, config.localization, config.estimation,
                                             config.stereo.pixel_sigma)
        self.place = route_place_index(map_, config.place, config.run.seed, warn)
        self._odometry_broken = False             # odometry failed since the previous leaf
        self.odometry = StereoOdometry(self.camera, OdometrySettings.of(config), keep_history=False)
        self.timer = self.odometry.timer          # odometry stages plus "map_write" and "localization"
        self.run = map_.begin_run("repeat", source=source, privileged=False)
        # taught submaps plus the experiences (earlier repeats) a recommender picks (vtr.navigation.experiences)
        self.submaps = ExperienceSubmaps(map_, self.chain.path, config.experiences,
                                         config.localization.neighbour_vertices, self.camera, self.place, (self.run,),
                                         warn)
        self.localizer.experiences = self.submaps     # estimates carry the experiences' placement error
        # the chain only asks place recognition for scores: the experiences' stand in for the teach's alone
        places = cast(PlaceIndex, self.submaps.places()) if self.submaps.trusted else self.place
        self.locator = ChainLocalizer(self.chain, self.localizer, places, self._submap, config.localization,
                                      config.place, config.run.seed)
        self.latest: Localization | None = None
        self._leaf: int | None = None            # map id of the newest repeat vertex
        self._kf_of_leaf: dict[int, int] = {}        # odometry keyframe id of each recent leaf
        self._undelivered: list[RepeatStep] = []

    def process(self, images: StereoImages) -> RepeatStep:
        """Stereo-process a rectified pair, then :meth:`process_frame`."""
        return self.process_frame(self.odometry.stereo.process(images))

    def process_frame(self, frame: StereoFrame) -> RepeatStep:
        """Odometry on the frame; localize it when it becomes a new vertex."""
        return self._deliver(self._localize_step(*self._odometry(frame)))

    def _odometry(self, frame: StereoFrame) -> tuple[OdometryResult, dict[int, np.ndarray]]:
        """The frame's odometry and the window's keyframe poses right after it (what its localization reads)."""
        result = self.odometry.process_frame(frame)
        return result, self.odometry.window_poses() if result.new_keyframe is not None else {}

    def steps(self, frames: Iterable[StereoFrame]) -> Generator[RepeatStep, None, None]:
        """:meth:`process_frame` over ``frames``, in order.

        With ``features.threads`` of 2 or more, the map write and localization of each new vertex run on
        a thread of their own (in order) while the odometry goes on with up to ``LOCALIZATION_LOOKAHEAD``
        more frames; steps equal :meth:`process_frame`'s bit for bit. While the stream is open only that
        thread writes the map; closing it early (an error, Ctrl-C) lets the localization under way finish
        and drops those not started, and after a failed one (a full disk...) none runs: the vertices in
        the map are whole and in order.
        """
        if self.odometry.stereo.threads <= 1:
            yield from self._steps_inline(frames)
            return
        failed = threading.Event()

        def in_order(result: OdometryResult, window: dict[int, np.ndarray]) -> RepeatStep:
            if failed.is_set():                 # an earlier vertex failed: never write a later one
                raise CancelledError()
            try:
                return self._localize_step(result, window)
            except BaseException:
                failed.set()
                raise

        pending: deque[Future[RepeatStep]] = deque()
        pool = ThreadPoolExecutor(1, thread_name_prefix="vtr-localize")
        yielded: RepeatStep | None = None       # the newest step handed out (its caller may not have taken it)
        try:
            for frame in frames:
                with held_signals():            # Ctrl-C between frames, never inside a compiled kernel
                    result = self._odometry(frame)
                pending.append(pool.submit(in_order, *result))
                while pending and (len(pending) > LOCALIZATION_LOOKAHEAD or pending[0].done()):
                    yielded = self._deliver(pending.popleft().result())
                    yield yielded
            while pending:
                yielded = self._deliver(pending.popleft().result())
                yield yielded
            yielded = None
        finally:
            for future in pending:
                future.cancel()
            pool.shutdown(wait=True)
            # steps the map already holds but the stream did not deliver (it was closed early): a caller that
            # reports every step takes them with take_undelivered, so the map and its reports agree
            done = [] if yielded is None else [yielded]
            for future in pending:
                if future.cancelled() or future.exception() is not None:
                    break
                done.append(self._deliver(future.result()))
            self._undelivered = done

    def _steps_inline(self, frames: Iterable[StereoFrame]) -> Generator[RepeatStep, None, None]:
        """:meth:`process_frame` over ``frames`` on this thread. Each frame is processed with Ctrl-C and SIGTERM
        held, so a vertex written to the map is always localized and its step exists; a signal is delivered as
        the frame ends, and the step it interrupted (and the newest one handed out, which its caller may not
        have taken yet) is left for :meth:`take_undelivered`."""
        yielded: RepeatStep | None = None
        try:
            for frame in frames:
                with held_signals():
                    yielded = self.process_frame(frame)
                yield yielded
            yielded = None
        finally:
            self._undelivered = [] if yielded is None else [yielded]

    def take_undelivered(self) -> list[RepeatStep]:
        """Steps written to the map (and localized) that a stream closed early may not have delivered, in order
        (once): those it never yielded, after the last one it yielded (a caller that took that one skips it)."""
        out, self._undelivered = self._undelivered, []
        return out

    def _deliver(self, step: RepeatStep) -> RepeatStep:
        if step.localization is not None:
            self.latest = step.localization
        return step

    def _localize_step(self, result: OdometryResult, window: dict[int, np.ndarray] | None = None) -> RepeatStep:
        """The step of an odometry result: its keyframe written to the map and localized (``window``: the
        odometry window's keyframe poses right after it, by odometry keyframe id)."""
        loc, seconds = None, 0.0
        vid = self._leaf if self._leaf is not None else -1
        if result.kind == FrameKind.FAILURE:
            self._odometry_broken = True
        if result.new_keyframe is not None:
            kf = result.new_keyframe
            with self.timer("map_write"):
                v = self.map.add_keyframe(self.run, kf, self.camera.T_vehicle_sensor)
            self._leaf = v.id
            vid = v.id
            self._kf_of_leaf[v.id] = kf.id
            t0 = time.perf_counter()
            with self.timer("localization"):
                loc = self._localize(v.id, kf, window or {})
            seconds = time.perf_counter() - t0
        return RepeatStep(result, loc, vid, self.T_teach(result.T_world_frame), seconds,
                          localized=self.chain.localized, direction=self.chain.state.direction)

    def T_teach(self, T_world_frame: np.ndarray) -> np.ndarray:
        """A repeat camera pose (repeat run's world) in the teach run's first camera frame, via the chain."""
        return self.chain.T_teach(T_world_frame)

    def _localize(self, leaf_id: int, kf: Keyframe, window: dict[int, np.ndarray]) -> Localization:
        c = self.chain
        twig, branch = c.twig_id, c.branch_id
        broken, self._odometry_broken = self._odometry_broken, False
        # the leaves still in the odometry window where its latest adjustment put them
        current = {leaf: window[k] for leaf, k in self._kf_of_leaf.items() if k in window}
        self._kf_of_leaf = {leaf: k for leaf, k in self._kf_of_leaf.items() if k in window}
        self.submaps.set_leaf(kf.frame)
        attempt = self.locator.localize(leaf_id, kf, broken, current)
        est = attempt.estimate
        trunk_id = int(c.path.ids[attempt.trunk])
        covariance = est.covariance
        if attempt.success:
            assert est.T_leaf_trunk is not None
            covariance = usable_covariance(est.covariance, self.config.odometry.failure_variance)
            with self.localizer.timer("spatial_edge"):      # a map transaction of its own
                self.map.add_edge(leaf_id, trunk_id, est.T_leaf_trunk, covariance, "spatial", est.inliers)
        used = self.submaps.observe(self.submaps.chosen_submap(attempt.trunk), est, attempt.success)
        if used:
            self.submaps.record(self.run, used)
        record = None
        if attempt.success:      # landmarks.csv (the perception model's training data) holds successes only
            sub = self._submap(attempt.trunk)
            with self.localizer.timer("landmark_record"):
                record = landmark_record(self.submaps.frame(trunk_id), attempt.T_report, self.camera,
                                         sub.trunk_features(est.matched),
                                         sub.trunk_features(est.matched[est.inlier]),
                                         t_ns=kf.t_ns, leaf_id=leaf_id, trunk_id=trunk_id)
        s = c.state
        return Localization(t_ns=kf.t_ns, leaf_id=leaf_id, trunk_id=trunk_id, twig_id=twig, branch_id=branch,
                            success=attempt.success, matches=est.matches, inliers=est.inliers,
                            T_leaf_trunk=attempt.T_report, covariance=covariance,
                            consecutive_failures=s.consecutive_failures,
                            distance_since_success_m=s.distance_since_success_m, landmarks=record,
                            status=attempt.status, direction=s.direction, experiences=used)

    def _submap(self, trunk: int) -> TaughtSubmap:
        """The trunk and its ``neighbour_vertices`` taught neighbours on each side, with the experiences the
        recommender picks, as a submap in the trunk's frame (:class:`~vtr.navigation.experiences.ExperienceSubmaps`)."""
        with self.localizer.timer("submap"):
            return self.submaps.submap(trunk)
