"""The one repeat loop: what ``vtr repeat``, the aerial mission, the offset experiment and the benchmarks all run.

A repeat is every frame through :meth:`Repeat.steps` (odometry, the new vertices written and localized, on
threads when configured), each step fed to the controller-state estimator and handed to the caller's
consumers (report rows) within :func:`held_signals`, so a step is reported whole or not at all; then the
run is finished in the map and the estimator closed. When anything stops the loop (an error, Ctrl-C,
SIGTERM) the steps the map already holds but the stream had not delivered are still handed to the
consumers before the error goes on: the map and the reports hold the same localized vertices.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from ..navigation.localization import Localization
from ..navigation.repeat import Repeat, RepeatStep
from ..navigation.repeat_state import RepeatStateEstimator
from ..signals import held_signals
from ..types import StereoFrame


@dataclass(frozen=True)
class RepeatLoop:
    """What one repeat's loop produced: per frame its time, its camera pose in the teach frame (the chain's)
    and whether the chain held a localization (its verdict); the localizations (with their landmark records only when
    kept); the controller-state estimator (finished); seconds in the loop and in localization."""

    t_ns: np.ndarray
    T_teach: np.ndarray
    localized: np.ndarray
    localizations: tuple[Localization, ...]
    state_estimator: RepeatStateEstimator
    seconds: float
    localization_seconds: float


def run_repeat(
    repeat: Repeat,
    frames: Iterable[StereoFrame],
    *,
    on_step: Callable[[RepeatStep], None] | None = None,
    keep_landmarks: bool = False,
    gravity_up: np.ndarray | None = None,
) -> RepeatLoop:
    """Run the repeat over ``frames`` (stereo frames, e.g. ``repeat.odometry.stereo.frames(images)``) and finish
    its run in the map. ``on_step`` receives every step in order (e.g. writes its report rows); with
    ``keep_landmarks`` the localizations keep their per-landmark records (memory grows with the route).
    ``gravity_up`` overrides the map's stored gravity (``Map.gravity_up``) for the controller state."""
    up = repeat.map.gravity_up if gravity_up is None else gravity_up
    state_estimator = RepeatStateEstimator.for_route(
        repeat.chain.path, repeat.config.smoothing, repeat.config.localization, repeat.camera.T_vehicle_sensor, up
    )
    t_ns: list[int] = []
    T_teach: list[np.ndarray] = []
    localized: list[bool] = []
    locs: list[Localization] = []
    t_loc = 0.0
    last_taken: RepeatStep | None = None

    def take(step: RepeatStep) -> None:
        nonlocal t_loc, last_taken
        last_taken = step
        t_loc += step.localization_seconds
        state_estimator.add(step)
        t_ns.append(step.odometry.t_ns)
        T_teach.append(step.T_teach_frame)
        localized.append(step.localized)
        if on_step is not None:
            on_step(step)
        if step.localization is not None:
            locs.append(step.localization if keep_landmarks else dataclasses.replace(step.localization, landmarks=None))

    t0 = time.perf_counter()
    steps = repeat.steps(frames)
    try:
        for step in steps:
            with held_signals():  # a step's reports, all or none
                take(step)
    except BaseException:
        steps.close()  # its localizations done: what the map holds but was not delivered
        with held_signals():
            for step in repeat.take_undelivered():
                if step is not last_taken:  # the newest step handed out, if the loop took it already
                    take(step)
        raise
    with held_signals():
        repeat.map.finish_run()  # every frame is in the map: the run is complete
        state_estimator.finish()
    return RepeatLoop(
        np.array(t_ns, np.int64),
        np.array(T_teach).reshape(-1, 4, 4),
        np.array(localized, bool),
        tuple(locs),
        state_estimator,
        time.perf_counter() - t0,
        t_loc,
    )


__all__ = ["RepeatLoop", "run_repeat"]
