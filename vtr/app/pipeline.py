"""Run orchestration: each run reads as a short list of named steps (open source, loop frames
with a progress bar, save, summarize). The library never prints; progress goes to a callback.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config import Config
from ..errors import DataError, MapError
from ..geometry import distance_to_polyline, inv_T
from ..io import open_source, parse_frame_range
from ..io.base import FrameSource, GroundTruth, SourceOptions
from ..io.trajectory import write_tum
from ..signals import held_signals
from ..types import FrameKind, FrameRecord, StereoFrame
from ..vo.odometry import OdometrySettings, StereoOdometry
from ..vo.stereo import StereoProcessor
from .evaluation import (
    DriftMetrics,
    Integrity,
    LocalizationErrors,
    associate,
    drift_metrics,
    integrity_of,
    localization_errors,
)
from .outputs import OutputFolder
from .runfiles import ODOMETRY_OUTPUTS, REPEAT_OUTPUTS, TEACH_OUTPUTS
from .runfiles.frames_csv import write_frames_csv
from .runfiles.run_json import RunLog

if TYPE_CHECKING:
    from perception_model.landmarks_file import LandmarksWriter

    from ..map import Map, TaughtPath
    from ..navigation.localization import Localization
    from ..navigation.repeat import RepeatStep
    from ..navigation.repeat_state import StateTable
    from .repeat_run import RepeatLoop

@dataclass(frozen=True)
class OdometrySummary:
    frames: int
    keyframes: int
    failures: int
    seconds: float
    drift: DriftMetrics | None
    note: str | None = None            # why the counts look odd (e.g. a camera that never moved enough)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")

    def to_dict(self) -> dict:
        d: dict[str, object] = {"frames": self.frames, "keyframes": self.keyframes, "failures": self.failures,
                                "seconds": self.seconds, "fps": self.fps}
        if self.drift is not None:
            d["drift"] = self.drift.to_dict()
        return d


def iterate(items: Iterable[Any], total: int, progress: Callable[..., Any] | None, desc: str) -> Iterable[Any]:
    """Wrap an iterable with a progress bar factory (e.g. tqdm) when given."""
    return progress(items, total=total, desc=desc) if progress else items


def frames_of(source: FrameSource, indices: list[int], processor: StereoProcessor, progress: Callable | None,
              desc: str) -> Iterable[StereoFrame]:
    """The selected frames of ``source`` as stereo frames, behind the progress bar; with ``features.threads``
    of 2 or more the next ones are decoded and stereo-processed in the background
    (:meth:`StereoProcessor.frames`)."""
    return iterate(processor.frames(source.iter_frames(indices)), len(indices), progress, desc)


def run_odometry(source: FrameSource, indices: list[int], config: Config,
                 progress: Callable | None = None) -> tuple[list[FrameRecord], np.ndarray, float]:
    """Odometry over the selected frames; returns per-frame records, final poses in the first
    camera frame (N, 4, 4; keyframes as refined by the window) and the elapsed seconds."""
    vo = StereoOdometry(source.camera, OdometrySettings.of(config))
    records = []
    t0 = time.perf_counter()
    for frame in frames_of(source, indices, vo.stereo, progress, "odometry"):
        with held_signals():                    # Ctrl-C lands between frames
            records.append(vo.process_frame(frame).record())
    return records, vo.final_poses(), time.perf_counter() - t0


def odometry_command(source_path: Path, out: Path, frames: str | None, config: Config,
                     source_options: SourceOptions | str | None = None,
                     progress: Callable | None = None) -> OdometrySummary:
    """``vtr odometry``: trajectory_tum.txt, frames.csv, trajectory.png, run.json, config.yaml in ``out``."""
    from .report import plot_trajectory

    with open_source(source_path, source_options) as source:
        indices = parse_frame_range(frames, len(source), str(source_path))
        folder = OutputFolder.prepare(out, [source_path], ODOMETRY_OUTPUTS)
        log = RunLog(out, "odometry", config, [source_path])
        results, poses, seconds = run_odometry(source, indices, config, progress)
        t_ns = np.array([r.t_ns for r in results], np.int64)
        folder.write("trajectory_tum.txt", write_tum, t_ns, poses)
        folder.write("frames.csv", write_frames_csv, results)
        drift, T_gt = None, None
        gt = source.ground_truth()
        if gt is not None:
            ie, ig = associate(t_ns, gt.t_ns)
            if len(ie) >= 2:
                T_gt = gt.T_world_cam[ig]
                T_gt = inv_T(T_gt[0]) @ T_gt
                drift = drift_metrics(poses[ie], T_gt)
        failures = np.array([r.kind == FrameKind.FAILURE for r in results])
        folder.write("trajectory.png", plot_trajectory, poses, T_gt, failures,
                     title=f"{source_path.name}: {len(results)} frames")
        keyframes = sum(r.new_vertex for r in results)
        summary = OdometrySummary(frames=len(results), keyframes=keyframes, failures=int(failures.sum()),
                                  seconds=seconds, drift=drift,
                                  note=keyframe_note(keyframes, len(results), poses, config))
        log.write(summary.to_dict())
    if not results:
        raise DataError(f"{source_path}: no frames processed")
    return summary


def keyframe_note(keyframes: int, frames: int, poses: np.ndarray, config: Config) -> str | None:
    """Why a run of several frames made a single keyframe: the camera never moved past the keyframe test
    (``odometry.keyframe_translation_m`` / ``keyframe_rotation_deg``) from the first frame."""
    if keyframes > 1 or frames < 2 or len(poses) < 2:
        return None
    from ..geometry import rotation_angle

    rel = inv_T(poses[0]) @ poses
    moved = float(np.linalg.norm(rel[:, :3, 3], axis=1).max())
    turned = float(np.degrees(rotation_angle(rel[:, :3, :3])).max())
    o = config.odometry
    return (f"only the first frame is a keyframe: the camera moved at most {moved:.2f} m and turned "
            f"{turned:.1f} deg from it, below the keyframe test (odometry.keyframe_translation_m "
            f"{o.keyframe_translation_m:g} m, keyframe_rotation_deg {o.keyframe_rotation_deg:g} deg): a nearly "
            "static log")


# ---------------------------------------------------------------------------------------- teach


#: an explicit up direction further than this from the map's stored one is reported (degrees)
GRAVITY_AGREEMENT_DEG = 1.0


@dataclass(frozen=True)
class TeachSummary:
    frames: int
    vertices: int
    failures: int
    seconds: float
    map_path: Path
    gravity_up: tuple[float, float, float] | None = None   # kept in the map (None: none stored)


def _unit3(v: np.ndarray) -> tuple[float, float, float]:
    x, y, z = (float(a) for a in np.asarray(v, float) / np.linalg.norm(v))
    return x, y, z


def teach_command(source_path: Path, map_path: Path, frames: str | None, config: Config, out: Path | None = None,
                  source_options: SourceOptions | str | None = None,
                  progress: Callable | None = None, gravity_up: np.ndarray | None = None) -> TeachSummary:
    """``vtr teach``: odometry over SOURCE, keyframes written to a new map (the privileged path).

    ``gravity_up``: up in the first left camera's frame (``--up``); without it the source's own (a format whose
    ground truth is gravity-aligned), else none is stored and readers take the first camera as level.

    The run ends finished, or aborted with the reason on any exception (the keyframes still in the
    odometry window are written first); a teach that wrote no vertex leaves no map file."""
    from ..map import Map
    from ..navigation.teach import Teach

    with open_source(source_path, source_options) as source:
        indices = parse_frame_range(frames, len(source), str(source_path))
        folder = OutputFolder.prepare(out, [source_path], TEACH_OUTPUTS) if out is not None else None
        t0 = time.perf_counter()
        results = []
        up = gravity_up if gravity_up is not None or not indices else source.gravity_up(indices[0])
        with Map.create(map_path, source.camera, config.map, gravity_up=up) as m:
            teach = Teach(m, source.camera, config, source=str(source_path))
            try:
                for frame in frames_of(source, indices, teach.odometry.stereo, progress, "teach"):
                    with held_signals():        # a frame's keyframes are all written or not made
                        results.append(teach.process_frame(frame).record())
                with held_signals():
                    n_vertices = teach.finish()
            except BaseException as err:  # error, Ctrl-C, SIGTERM, full disk: keep the window, say why
                teach.abort(err)          # (a map left without any vertex is removed when it closes)
                raise
            _, t_taught = m.timestamps(teach.run)
            _, T_taught = m.poses(teach.run)
        seconds = time.perf_counter() - t0
        failures = sum(r.kind == FrameKind.FAILURE for r in results)
        summary = TeachSummary(frames=len(results), vertices=n_vertices, failures=failures, seconds=seconds,
                               map_path=map_path,
                               gravity_up=None if up is None else _unit3(up))
        if out is not None and folder is not None:
            log = RunLog(out, "teach", config, [source_path])
            folder.write("trajectory_tum.txt", write_tum, t_taught, T_taught)
            folder.write("frames.csv", write_frames_csv, results)
            log.write({"frames": summary.frames, "vertices": n_vertices, "failures": failures,
                       "seconds": seconds, "map": str(map_path),
                       "gravity_up": None if summary.gravity_up is None else list(summary.gravity_up)})
    return summary


# --------------------------------------------------------------------------------------- repeat

@dataclass(frozen=True)
class RepeatSummary:
    frames: int
    vertices: int
    localized: int
    seconds: float
    localization_seconds: float
    median_inliers: float
    path_error_m: float
    errors: LocalizationErrors | None = None
    state: dict | None = None          # state.csv: rate, rows, smoother cost, smoothed path errors
    statuses: dict | None = None       # attempts by localization.csv status
    integrity: Integrity | None = None  # correct / wrong successes when ground truth covers teach and repeat
    ground_truth_note: str | None = None   # why the repeat was not judged against ground truth (None: it was)
    experiences: dict | None = None    # trusted experiences available, successes that used one, keyframes per run

    @property
    def success_rate(self) -> float:
        return self.localized / self.vertices if self.vertices else float("nan")

    def to_dict(self) -> dict:
        return {"frames": self.frames, "vertices": self.vertices, "localized": self.localized,
                "success_rate": self.success_rate, "seconds": self.seconds,
                "fps": self.frames / self.seconds if self.seconds > 0 else None,
                "localization_ms_per_vertex": 1000 * self.localization_seconds / max(self.vertices, 1),
                "median_inliers": self.median_inliers, "median_path_error_m": self.path_error_m,
                "median_error_m": self.errors.median_translation_m if self.errors else None,
                "median_error_deg": self.errors.median_rotation_deg if self.errors else None,
                "state": self.state, "statuses": self.statuses,
                "integrity": self.integrity.to_dict() if self.integrity else None,
                "ground_truth_not_used": self.ground_truth_note, "experiences": self.experiences}


def write_landmarks_csv(path: Path, locs: list[Localization]) -> None:
    """``landmarks.csv`` (``perception_model``'s format and writer) of the successful localizations."""
    from perception_model.landmarks_file import LandmarksWriter

    with LandmarksWriter(path) as w:
        for loc in locs:
            append_landmarks(w, loc)


def append_landmarks(writer: LandmarksWriter, loc: Localization) -> None:
    """Rows of one localization for ``landmarks.csv``: its landmark record when it succeeded."""
    if loc.success and loc.landmarks is not None:
        writer.write(loc.landmarks)


def repeat_command(source_path: Path, map_path: Path, out: Path, frames: str | None, config: Config,
                   source_options: SourceOptions | str | None = None, progress: Callable | None = None,
                   rate_hz: float | None = None, allow_partial: bool = False, start_vertex: int | None = None,
                   start_distance_m: float | None = None, read_only_map: bool = False,
                   gravity_up: np.ndarray | None = None, warn: Callable[[str], None] | None = None) -> RepeatSummary:
    """``vtr repeat``: odometry on SOURCE stored as a repeat run, each vertex localized to the taught path;
    the smoothed controller state at ``rate_hz`` (default ``config.smoothing.rate_hz``) in state.csv.
    ``start_vertex`` (path index) or ``start_distance_m`` (along the taught path) is an optional hint of where
    the repeat starts; without it place recognition finds it.

    Refuses a map whose teach run is not finished unless ``allow_partial``. The repeat run ends
    finished once every frame is processed, or aborted with the reason on any exception. With
    ``read_only_map`` the map is left untouched: the repeat runs on a private copy in temporary space,
    removed at the end (the outputs in ``out`` are the same). ``gravity_up`` (up in the teach run's first camera)
    overrides the map's stored gravity for the controller state (``warn`` is told when they disagree). The steps are
    :class:`RepeatRun`'s."""
    from ..navigation.repeat_state import check_rate

    rate_hz = check_rate(config.smoothing.rate_hz if rate_hz is None else rate_hz)
    return RepeatRun(source_path, map_path, out, frames, config, source_options=source_options, progress=progress,
                     rate_hz=rate_hz, allow_partial=allow_partial, start_vertex=start_vertex,
                     start_distance_m=start_distance_m, read_only_map=read_only_map, gravity_up=gravity_up,
                     warn=warn).run()


@dataclass(frozen=True)
class RepeatEvaluation:
    """A repeat judged after its loop: the path-tracking error of each frame (m; NaN where not localized or beyond
    the route's ends), the localization errors and integrity against ground truth (when the source's ground truth
    covers teach and repeat), and the attempts by status."""

    path_errors_m: np.ndarray
    errors: LocalizationErrors | None
    integrity: Integrity | None
    statuses: dict[str, int]
    ground_truth_note: str | None = None


@contextlib.contextmanager
def _naming_the_map(work_map: Path, map_path: Path) -> Iterator[None]:
    """A ``MapError`` about the private copy of ``--read-only-map`` (a temporary file the user never named) is
    reported with the user's map instead: what is wrong with the copy is wrong with the map it was copied from."""
    try:
        yield
    except MapError as err:
        if work_map == map_path:
            raise
        raise MapError(str(err).replace(str(work_map), str(map_path))) from None


class RepeatRun:
    """``vtr repeat`` as named steps (:meth:`run`): open the source, the map and the outputs; loop every frame
    through the one repeat loop (:func:`~vtr.app.repeat_run.run_repeat`: the run finished in the map at its end),
    streaming ``localization.csv`` and ``landmarks.csv``; evaluate; write ``state.csv``, ``trajectory_tum.txt`` and
    ``report.png``; summarize; ``run.json`` last."""

    def __init__(self, source_path: Path, map_path: Path, out: Path, frames: str | None, config: Config, *,
                 source_options: SourceOptions | str | None = None, progress: Callable | None = None,
                 rate_hz: float, allow_partial: bool = False, start_vertex: int | None = None,
                 start_distance_m: float | None = None, read_only_map: bool = False,
                 gravity_up: np.ndarray | None = None, warn: Callable[[str], None] | None = None):
        self.source_path, self.map_path, self.out, self.frames = Path(source_path), Path(map_path), Path(out), frames
        self.gravity_up, self.warn = gravity_up, warn
        self.config, self.source_options, self.progress, self.rate_hz = config, source_options, progress, rate_hz
        self.allow_partial, self.read_only_map = allow_partial, read_only_map
        self.start_vertex, self.start_distance_m = start_vertex, start_distance_m

    def run(self) -> RepeatSummary:
        with contextlib.ExitStack() as stack:
            self.open(stack)
            loop = self.loop()
            t_after = time.perf_counter()
            evaluation = self.evaluate(loop)
            state = self.write(loop, evaluation)
            summary = self.summarize(loop, evaluation, state, time.perf_counter() - t_after)
            self.log.write(summary.to_dict())
        return summary

    # -- the steps ----------------------------------------------------------------------------------------------

    def open(self, stack: ExitStack) -> None:
        """The source, the map (or its private copy) and the output folder, checked before any work; the
        :class:`~vtr.navigation.repeat.Repeat` at the start hint."""
        from ..map import Map
        from ..navigation.repeat import Repeat

        work_map = self._private_copy(stack) if self.read_only_map else self.map_path
        with _naming_the_map(work_map, self.map_path):     # what is wrong with the map names the user's file
            self.source = stack.enter_context(open_source(self.source_path, self.source_options))
            self.map = m = stack.enter_context(Map.open(work_map, "a"))
            m.check_camera(self.source.camera)
            self.indices = parse_frame_range(self.frames, len(self.source), str(self.source_path))
            self.folder = OutputFolder.prepare(self.out, [self.source_path], REPEAT_OUTPUTS)
            self.log = RunLog(self.out, "repeat", self.config, [self.source_path, self.map_path])
            _check_path_to_follow(m)
            start = _start_hint(m, self.start_vertex, self.start_distance_m)
            self.repeat = Repeat(m, self.config, source=str(self.source_path), start_index=start,
                                 allow_partial=self.allow_partial, warn=self.warn)

    def loop(self) -> RepeatLoop:
        """Every frame through the repeat loop; a row of ``localization.csv`` and the rows of ``landmarks.csv`` (the
        input of ``perception-model fit``) per localization attempt as it comes."""
        from perception_model.landmarks_file import LandmarksWriter

        from .repeat_run import run_repeat
        from .runfiles.localization_csv import LocalizationWriter

        with self.folder.open("localization.csv") as loc_file, \
                LandmarksWriter(self.folder.create("landmarks.csv")) as lm_csv:
            loc_csv = LocalizationWriter(loc_file)

            def report(step: RepeatStep) -> None:
                if step.localization is not None:
                    loc_csv.write(step.localization)
                    append_landmarks(lm_csv, step.localization)

            frames = frames_of(self.source, self.indices, self.repeat.odometry.stereo, self.progress, "repeat")
            return run_repeat(self.repeat, frames, on_step=report, gravity_up=self._gravity())

    def _gravity(self) -> np.ndarray | None:
        """The up direction of the controller state: an explicit one, else the map's (None: a level first camera).
        An explicit one that disagrees with the map's by more than ``GRAVITY_AGREEMENT_DEG`` is reported."""
        from ..map import check_gravity_up

        stored = self.map.gravity_up
        if self.gravity_up is None:
            return stored
        up = check_gravity_up(self.gravity_up, "--up")
        if stored is not None and self.warn is not None:
            angle = math.degrees(math.acos(float(np.clip(up @ stored, -1.0, 1.0))))
            if angle > GRAVITY_AGREEMENT_DEG:
                self.warn(f"warning: --up {up.round(4).tolist()} differs from the map's gravity "
                          f"{stored.round(4).tolist()} by {angle:.1f} deg: using --up")
        return up

    def evaluate(self, loop: RepeatLoop) -> RepeatEvaluation:
        """Path-tracking errors, and errors and integrity against ground truth where the source has it."""
        chain, m, source = self.repeat.chain, self.map, self.source
        errors = distance_to_polyline(loop.T_teach[:, :3, 3], chain.path.positions)
        errors[~loop.localized] = np.nan          # no path error where not localized, nor beyond the route's ends
        errors[chain.beyond_ends_m(loop.T_teach[:, :3, 3]) > 0] = np.nan
        locs = list(loop.localizations)
        gt_errors = integrity = None
        note = _ground_truth_note(source, m, locs)
        if note is None:                              # ground truth covers the leaves and their trunks
            gt = source.ground_truth()
            assert gt is not None                     # a note says when there is none
            trunk_t_ns = trunk_times(locs, chain.path)
            integrity = integrity_of(locs, trunk_t_ns, gt, gt)
            ok = np.array([loc.success for loc in locs])
            if ok.any():
                gt_errors = chain_errors([loc for loc in locs if loc.success], trunk_t_ns[ok], gt)
        statuses: dict[str, int] = {}
        for loc in locs:
            statuses[loc.status.value] = statuses.get(loc.status.value, 0) + 1
        return RepeatEvaluation(path_errors_m=errors, errors=gt_errors, integrity=integrity, statuses=statuses,
                                ground_truth_note=note)

    def write(self, loop: RepeatLoop, evaluation: RepeatEvaluation) -> StateTable:
        """``state.csv`` (the smoothed state at the output rate), ``trajectory_tum.txt``, ``report.png``."""
        from .report import plot_repeat
        from .runfiles.state_csv import write_state_csv

        state = loop.state_estimator.output(self.rate_hz)
        self.folder.write("state.csv", write_state_csv, state)
        self.folder.write("trajectory_tum.txt", write_tum, loop.t_ns, loop.T_teach)
        self.folder.write("report.png", plot_repeat, list(loop.localizations), self.repeat.chain.path, loop.T_teach,
                          loop.t_ns, evaluation.path_errors_m, state, localized=loop.localized,
                          title=f"repeat of {self.source.path.name}",
                          min_inliers=self.config.localization.min_inliers)
        return state

    def summarize(self, loop: RepeatLoop, evaluation: RepeatEvaluation, state: StateTable,
                  seconds_after_loop: float) -> RepeatSummary:
        """The run's record (run.json's summary; the command line prints it)."""
        ok = [loc for loc in loop.localizations if loc.success]
        lateral, vertical = np.abs(state.lateral), np.abs(state.vertical)
        state_info = {"rate_hz": self.rate_hz, "rows": len(state),
                      "smoother_ms_per_frame": 1000 * loop.state_estimator.seconds / max(len(loop.t_ns), 1),
                      "median_abs_lateral_m": float(np.nanmedian(lateral)) if np.isfinite(lateral).any() else None,
                      "median_abs_vertical_m": float(np.nanmedian(vertical)) if np.isfinite(vertical).any() else None,
                      "statuses": ({str(k): int(v) for k, v in zip(*np.unique(state.status, return_counts=True),
                                                                   strict=True)} if state.status is not None else {}),
                      "pauses_s": [round(p, 3) for p in loop.state_estimator.pauses_s]}
        errors = evaluation.path_errors_m
        used: dict[str, int] = {}
        for loc in ok:
            for e in loc.experiences:
                used[str(e)] = used.get(str(e), 0) + 1
        experiences = {"available": len(self.repeat.submaps.trusted),
                       "localized_with_experience": sum(1 for loc in ok if loc.experiences), "used": used}
        return RepeatSummary(frames=len(loop.t_ns), vertices=len(loop.localizations), localized=len(ok),
                             seconds=loop.seconds + seconds_after_loop, localization_seconds=loop.localization_seconds,
                             median_inliers=float(np.median([loc.inliers for loc in ok])) if ok else 0.0,
                             path_error_m=float(np.nanmedian(errors)) if np.isfinite(errors).any() else float("nan"),
                             errors=evaluation.errors, state=state_info, statuses=evaluation.statuses,
                             integrity=evaluation.integrity, ground_truth_note=evaluation.ground_truth_note,
                             experiences=experiences)

    def _private_copy(self, stack: ExitStack) -> Path:
        """A whole copy of the map in a private temporary folder that ``stack`` removes (and the next start removes
        if this process is killed: :mod:`vtr.app.private_copy`); the map itself is only read (and checked first, so
        that its errors name it)."""
        from ..map import Map
        from .private_copy import private_copy, remove_stale_copies

        stale = remove_stale_copies()
        if stale and self.warn is not None:
            self.warn(f"removed {len(stale)} private map copy folder(s) left by killed --read-only-map repeats "
                      f"({stale[0]}{', ...' if len(stale) > 1 else ''})")
        with Map.open(self.map_path) as m:      # a map, readable, and not being written by another process
            m.check_taught_route(self.allow_partial)
        return stack.enter_context(private_copy(self.map_path))


def _start_hint(m: Map, start_vertex: int | None, start_distance_m: float | None) -> int | None:
    """The path index a start hint names; ``MapError`` for a vertex or distance beyond the taught route."""
    from ..errors import ConfigError, MapError

    if start_vertex is not None and start_distance_m is not None:
        raise ConfigError("give either a start vertex or a start distance, not both")
    taught = m.taught_path()
    if start_vertex is not None:
        if not 0 <= start_vertex < len(taught):
            raise MapError(f"{m.path}: start vertex {start_vertex} is not on the taught path (0..{len(taught) - 1})")
        return int(start_vertex)
    if start_distance_m is not None:
        arc = taught.arc_length_m()
        if not 0 <= start_distance_m <= arc[-1]:
            raise MapError(f"{m.path}: start distance {start_distance_m:g} m is beyond the taught route "
                           f"(0..{arc[-1]:.1f} m)")
        return int(np.argmin(np.abs(arc - start_distance_m)))
    return None


def _check_path_to_follow(m: Map) -> None:
    """``MapError`` unless the taught path has a segment: path-tracking errors (and the controller's
    reference path) are undefined on a single point."""
    from ..errors import EstimationError, MapError
    from ..state.controller import ReferencePath

    taught = m.taught_path()
    try:
        ReferencePath(taught.positions)
    except EstimationError:
        raise MapError(f"{m.path}: the taught path has {len(taught)} vertex(es) but no segment (it needs two distinct "
                       "positions to follow): teach a longer route") from None


def _ground_truth_note(source: FrameSource, m: Map, locs: list[Localization]) -> str | None:
    """None when the repeat source's ground truth also covers the taught vertices (teach and repeat taken from one
    source, e.g. even and odd frames of a clip), so the repeat can be judged against it; else why it is not."""
    if not locs:
        return "no localization was attempted"
    if source.ground_truth() is None:
        return f"{source.path} has no ground truth"
    teach = m.reference_run()
    taught_from = m.run(teach).source if teach is not None else None
    if taught_from != str(source.path):
        return (f"the repeat's source {source.path} is not the teach's ({taught_from or 'unknown'}): their ground "
                "truths need not share one frame")
    return None


def trunk_times(locs: Sequence[Localization], path: TaughtPath) -> np.ndarray:
    """(N,) int64 times of the localizations' trunks, vertices of the taught ``path`` (no vertex is read)."""
    return path.t_ns[[path.index(loc.trunk_id) for loc in locs]].astype(np.int64)


def chain_errors(locs: Sequence[Localization], trunk_t_ns: np.ndarray, gt: GroundTruth) -> LocalizationErrors:
    """Errors of localizations ``T_leaf_trunk`` against ground truth ``gt`` that covers both the leaf times and
    the trunk times ``trunk_t_ns`` (:func:`trunk_times`)."""
    return localization_errors(np.array([loc.T_leaf_trunk for loc in locs]), np.array([loc.t_ns for loc in locs]),
                               np.asarray(trunk_t_ns, np.int64), gt.t_ns, gt.T_world_cam)
