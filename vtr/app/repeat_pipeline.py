"""``vtr repeat`` as named steps (:class:`RepeatRun`): the shape of every run of :mod:`vtr.app.pipeline` (open,
loop, evaluate, write, summarize, ``run.json`` last), the loop being the one repeat loop of
:mod:`vtr.app.repeat_run` (docs/architecture.md)."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config import Config
from ..errors import MapError
from ..geometry import distance_to_polyline
from ..io import open_source, parse_frame_range
from ..io.base import FrameSource, GroundTruth, SourceOptions
from ..io.trajectory import write_tum
from .evaluation import Integrity, LocalizationErrors, integrity_of, localization_errors
from .outputs import OutputFolder
from .run_inputs import Progress, RunInputs, frames_of
from .runfiles import REPEAT_OUTPUTS
from .runfiles.run_json import RunLog

if TYPE_CHECKING:
    from perception_model.landmarks_file import LandmarksWriter

    from ..map import Map, TaughtPath
    from ..navigation.localization import Localization
    from ..navigation.repeat import Repeat, RepeatStep
    from ..navigation.repeat_state import StateTable
    from .repeat_run import RepeatLoop

#: an explicit up direction further than this from the map's stored one is reported (degrees)
GRAVITY_AGREEMENT_DEG = 1.0


@dataclass(frozen=True)
class StateSummary:
    """``state.csv`` of a repeat: its rate and rows, the smoother's cost per frame, the median smoothed distances
    to the taught path (None: never localized), the rows by status, the pauses without frames."""

    rate_hz: float
    rows: int
    smoother_ms_per_frame: float
    median_abs_lateral_m: float | None
    median_abs_vertical_m: float | None
    statuses: dict[str, int]
    pauses_s: list[float]

    @classmethod
    def of(
        cls, state: StateTable, rate_hz: float, smoother_seconds: float, frames: int, pauses_s: Sequence[float]
    ) -> StateSummary:
        lateral, vertical = np.abs(state.lateral), np.abs(state.vertical)
        return cls(
            rate_hz=rate_hz,
            rows=len(state),
            smoother_ms_per_frame=1000 * smoother_seconds / max(frames, 1),
            median_abs_lateral_m=float(np.nanmedian(lateral)) if np.isfinite(lateral).any() else None,
            median_abs_vertical_m=float(np.nanmedian(vertical)) if np.isfinite(vertical).any() else None,
            statuses=(
                {str(k): int(v) for k, v in zip(*np.unique(state.status, return_counts=True), strict=True)}
                if state.status is not None
                else {}
            ),
            pauses_s=[round(p, 3) for p in pauses_s],
        )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


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
    state: StateSummary | None = None  # state.csv: rate, rows, smoother cost, smoothed path errors
    statuses: dict | None = None  # attempts by localization.csv status
    integrity: Integrity | None = None  # correct / wrong successes when ground truth covers teach and repeat
    ground_truth_note: str | None = None  # why the repeat was not judged against ground truth (None: it was)
    experiences: dict | None = None  # trusted experiences available, successes that used one, keyframes per run

    @property
    def success_rate(self) -> float:
        return self.localized / self.vertices if self.vertices else float("nan")

    def to_dict(self) -> dict:
        return {
            "frames": self.frames,
            "vertices": self.vertices,
            "localized": self.localized,
            "success_rate": self.success_rate,
            "seconds": self.seconds,
            "fps": self.frames / self.seconds if self.seconds > 0 else None,
            "localization_ms_per_vertex": 1000 * self.localization_seconds / max(self.vertices, 1),
            "median_inliers": self.median_inliers,
            "median_path_error_m": self.path_error_m,
            "median_error_m": self.errors.median_translation_m if self.errors else None,
            "median_error_deg": self.errors.median_rotation_deg if self.errors else None,
            "state": self.state.to_dict() if self.state else None,
            "statuses": self.statuses,
            "integrity": self.integrity.to_dict() if self.integrity else None,
            "ground_truth_not_used": self.ground_truth_note,
            "experiences": self.experiences,
        }


def write_landmarks_csv(path: Path, localizations: list[Localization]) -> None:
    """``landmarks.csv`` (``perception_model``'s format and writer) of the successful localizations."""
    from perception_model.landmarks_file import LandmarksWriter

    with LandmarksWriter(path) as w:
        for loc in localizations:
            append_landmarks(w, loc)


def append_landmarks(writer: LandmarksWriter, loc: Localization) -> None:
    """Rows of one localization for ``landmarks.csv``: its landmark record when it succeeded."""
    if loc.success and loc.landmarks is not None:
        writer.write(loc.landmarks)


@dataclass(frozen=True)
class RepeatOptions:
    """How a repeat runs besides its inputs: the state's output rate (Hz, checked), a partial route allowed, a start
    hint (a path index or a distance along the taught path; None: place recognition finds it), the map left
    untouched (a private copy), an explicit up direction, and who is told of a warning."""

    rate_hz: float
    allow_partial: bool = False
    start_vertex: int | None = None
    start_distance_m: float | None = None
    read_only_map: bool = False
    gravity_up: np.ndarray | None = None
    warn: Callable[[str], None] | None = None


def repeat_command(
    source_path: Path,
    map_path: Path,
    out: Path,
    frames: str | None,
    config: Config,
    source_options: SourceOptions | str | None = None,
    progress: Progress | None = None,
    rate_hz: float | None = None,
    allow_partial: bool = False,
    start_vertex: int | None = None,
    start_distance_m: float | None = None,
    read_only_map: bool = False,
    gravity_up: np.ndarray | None = None,
    warn: Callable[[str], None] | None = None,
) -> RepeatSummary:
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

    options = RepeatOptions(
        check_rate(config.smoothing.rate_hz if rate_hz is None else rate_hz),
        allow_partial,
        start_vertex,
        start_distance_m,
        read_only_map,
        gravity_up,
        warn,
    )
    return RepeatRun(
        RunInputs(Path(source_path), frames, config, source_options, progress), map_path, out, options
    ).run()


@dataclass(frozen=True)
class OpenRepeat:
    """A repeat's first step done: the source and its selected frames, the map (or its private copy), the output
    folder and log, and the :class:`~vtr.navigation.repeat.Repeat` at its start hint."""

    source: FrameSource
    indices: list[int]
    folder: OutputFolder
    log: RunLog
    map: Map
    repeat: Repeat


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

    def __init__(self, inputs: RunInputs, map_path: Path, out: Path, options: RepeatOptions):
        self.inputs, self.map_path, self.out, self.options = inputs, Path(map_path), Path(out), options

    def run(self) -> RepeatSummary:
        with ExitStack() as stack:
            opened = self.open(stack)
            loop = self.loop(opened)
            evaluation = self.evaluate(opened, loop)
            state = self.write(opened, loop, evaluation)
            summary = self.summarize(opened, loop, evaluation, state)
            opened.log.write(summary.to_dict())
        return summary

    # -- the steps ----------------------------------------------------------------------------------------------

    def open(self, stack: ExitStack) -> OpenRepeat:
        """The source, the map (or its private copy) and the output folder, checked before any work; the
        :class:`~vtr.navigation.repeat.Repeat` at the start hint."""
        from ..map import Map
        from ..navigation.repeat import Repeat

        o = self.options
        work_map = self._private_copy(stack) if o.read_only_map else self.map_path
        with _naming_the_map(work_map, self.map_path):  # what is wrong with the map names the user's file
            source = stack.enter_context(open_source(self.inputs.source_path, self.inputs.source_options))
            route = stack.enter_context(Map.open(work_map, "a"))
            route.check_camera(source.camera)
            indices = parse_frame_range(self.inputs.frames, len(source), str(self.inputs.source_path))
            folder = OutputFolder.prepare(self.out, [self.inputs.source_path], REPEAT_OUTPUTS)
            log = RunLog(self.out, "repeat", self.inputs.config, [self.inputs.source_path, self.map_path])
            _check_path_to_follow(route)
            start = _start_hint(route, o.start_vertex, o.start_distance_m)
            repeat = Repeat(
                route,
                self.inputs.config,
                source=str(self.inputs.source_path),
                start_index=start,
                allow_partial=o.allow_partial,
                warn=o.warn,
            )
        return OpenRepeat(source, indices, folder, log, route, repeat)

    def loop(self, opened: OpenRepeat) -> RepeatLoop:
        """Every frame through the repeat loop; a row of ``localization.csv`` and the rows of ``landmarks.csv`` (the
        input of ``perception-model fit``) per localization attempt as it comes."""
        from perception_model.landmarks_file import LandmarksWriter

        from .repeat_run import run_repeat
        from .runfiles.localization_csv import LocalizationWriter

        with (
            opened.folder.open("localization.csv") as loc_file,
            LandmarksWriter(opened.folder.create("landmarks.csv")) as lm_csv,
        ):
            loc_csv = LocalizationWriter(loc_file)

            def report(step: RepeatStep) -> None:
                if step.localization is not None:
                    loc_csv.write(step.localization)
                    append_landmarks(lm_csv, step.localization)

            frames = frames_of(
                opened.source, opened.indices, opened.repeat.odometry.stereo, self.inputs.progress, "repeat"
            )
            return run_repeat(opened.repeat, frames, on_step=report, gravity_up=self._gravity(opened.map))

    def _gravity(self, route: Map) -> np.ndarray | None:
        """The up direction of the controller state: an explicit one, else the map's (None: a level first camera).
        An explicit one that disagrees with the map's by more than ``GRAVITY_AGREEMENT_DEG`` is reported."""
        from ..map import check_gravity_up

        stored, warn = route.gravity_up, self.options.warn
        if self.options.gravity_up is None:
            return stored
        up = check_gravity_up(self.options.gravity_up, "--up")
        if stored is not None and warn is not None:
            angle = math.degrees(math.acos(float(np.clip(up @ stored, -1.0, 1.0))))
            if angle > GRAVITY_AGREEMENT_DEG:
                warn(
                    f"warning: --up {up.round(4).tolist()} differs from the map's gravity "
                    f"{stored.round(4).tolist()} by {angle:.1f} deg: using --up"
                )
        return up

    def evaluate(self, opened: OpenRepeat, loop: RepeatLoop) -> RepeatEvaluation:
        """Path-tracking errors, and errors and integrity against ground truth where the source has it."""
        chain = opened.repeat.chain
        errors = distance_to_polyline(loop.T_teach[:, :3, 3], chain.path.positions)
        errors[~loop.localized] = np.nan  # no path error where not localized, nor beyond the route's ends
        errors[chain.beyond_ends_m(loop.T_teach[:, :3, 3]) > 0] = np.nan
        localizations = list(loop.localizations)
        gt_errors = integrity = None
        note = _ground_truth_note(opened.source, opened.map, localizations)
        if note is None:  # ground truth covers the leaves and their trunks
            truth = opened.source.ground_truth()
            assert truth is not None  # a note says when there is none
            trunk_t_ns = trunk_times(localizations, chain.path)
            integrity = integrity_of(localizations, trunk_t_ns, truth, truth)
            ok = np.array([loc.success for loc in localizations])
            if ok.any():
                gt_errors = chain_errors([loc for loc in localizations if loc.success], trunk_t_ns[ok], truth)
        statuses: dict[str, int] = {}
        for loc in localizations:
            statuses[loc.status.value] = statuses.get(loc.status.value, 0) + 1
        return RepeatEvaluation(
            path_errors_m=errors, errors=gt_errors, integrity=integrity, statuses=statuses, ground_truth_note=note
        )

    def write(self, opened: OpenRepeat, loop: RepeatLoop, evaluation: RepeatEvaluation) -> StateTable:
        """``state.csv`` (the smoothed state at the output rate), ``trajectory_tum.txt``, ``report.png``."""
        from .report import plot_repeat
        from .runfiles.state_csv import write_state_csv

        folder = opened.folder
        state = loop.state_estimator.output(self.options.rate_hz)
        folder.write("state.csv", write_state_csv, state)
        folder.write("trajectory_tum.txt", write_tum, loop.t_ns, loop.T_teach)
        folder.write(
            "report.png",
            plot_repeat,
            list(loop.localizations),
            opened.repeat.chain.path,
            loop.T_teach,
            loop.t_ns,
            evaluation.path_errors_m,
            state,
            localized=loop.localized,
            title=f"repeat of {opened.source.path.name}",
            min_inliers=self.inputs.config.localization.min_inliers,
        )
        return state

    def summarize(
        self,
        opened: OpenRepeat,
        loop: RepeatLoop,
        evaluation: RepeatEvaluation,
        state: StateTable,
    ) -> RepeatSummary:
        """The run's record (run.json's summary; the command line prints it). Its seconds are the loop's, as the
        odometry's and the teach's: every frame through odometry, localization, the map writes and the state
        estimator, the run finished in the map; the reports written after it (``state.csv`` at the output rate,
        ``report.png``) are not in its frames/s (``tools/bench_processes.py`` times whole processes)."""
        ok = [loc for loc in loop.localizations if loc.success]
        state_summary = StateSummary.of(
            state, self.options.rate_hz, loop.state_estimator.seconds, len(loop.t_ns), loop.state_estimator.pauses_s
        )
        errors = evaluation.path_errors_m
        used: dict[str, int] = {}
        for loc in ok:
            for e in loc.experiences:
                used[str(e)] = used.get(str(e), 0) + 1
        experiences = {
            "available": len(opened.repeat.submaps.trusted),
            "localized_with_experience": sum(1 for loc in ok if loc.experiences),
            "used": used,
        }
        return RepeatSummary(
            frames=len(loop.t_ns),
            vertices=len(loop.localizations),
            localized=len(ok),
            seconds=loop.seconds,
            localization_seconds=loop.localization_seconds,
            median_inliers=float(np.median([loc.inliers for loc in ok])) if ok else 0.0,
            path_error_m=float(np.nanmedian(errors)) if np.isfinite(errors).any() else float("nan"),
            errors=evaluation.errors,
            state=state_summary,
            statuses=evaluation.statuses,
            integrity=evaluation.integrity,
            ground_truth_note=evaluation.ground_truth_note,
            experiences=experiences,
        )

    def _private_copy(self, stack: ExitStack) -> Path:
        """A whole copy of the map in a private temporary folder that ``stack`` removes (and the next start removes
        if this process is killed: :mod:`vtr.app.private_copy`); the map itself is only read (and checked first, so
        that its errors name it)."""
        from ..map import Map
        from .private_copy import private_copy, remove_stale_copies

        stale, warn = remove_stale_copies(), self.options.warn
        if stale and warn is not None:
            warn(
                f"removed {len(stale)} private map copy folder(s) left by killed --read-only-map repeats "
                f"({stale[0]}{', ...' if len(stale) > 1 else ''})"
            )
        with Map.open(self.map_path) as route:  # a map, readable, and not being written by another process
            route.check_taught_route(self.options.allow_partial)
        return stack.enter_context(private_copy(self.map_path))


def _start_hint(route: Map, start_vertex: int | None, start_distance_m: float | None) -> int | None:
    """The path index a start hint names; ``MapError`` for a vertex or distance beyond the taught route."""
    from ..errors import ConfigError, MapError

    if start_vertex is not None and start_distance_m is not None:
        raise ConfigError("give either a start vertex or a start distance, not both")
    taught = route.taught_path()
    if start_vertex is not None:
        if not 0 <= start_vertex < len(taught):
            raise MapError(
                f"{route.path}: start vertex {start_vertex} is not on the taught path (0..{len(taught) - 1})"
            )
        return int(start_vertex)
    if start_distance_m is not None:
        arc = taught.arc_length_m()
        if not 0 <= start_distance_m <= arc[-1]:
            raise MapError(
                f"{route.path}: start distance {start_distance_m:g} m is beyond the taught route (0..{arc[-1]:.1f} m)"
            )
        return int(np.argmin(np.abs(arc - start_distance_m)))
    return None


def _check_path_to_follow(route: Map) -> None:
    """``MapError`` unless the taught path has a segment: path-tracking errors (and the controller's
    reference path) are undefined on a single point."""
    from ..errors import EstimationError, MapError
    from ..state.controller import ReferencePath

    taught = route.taught_path()
    try:
        ReferencePath(taught.positions)
    except EstimationError:
        raise MapError(
            f"{route.path}: the taught path has {len(taught)} vertex(es) but no segment (it needs two "
            "distinct positions to follow): teach a longer route"
        ) from None


def _ground_truth_note(source: FrameSource, route: Map, localizations: list[Localization]) -> str | None:
    """None when the repeat source's ground truth also covers the taught vertices (teach and repeat taken from one
    source, e.g. even and odd frames of a clip), so the repeat can be judged against it; else why it is not."""
    if not localizations:
        return "no localization was attempted"
    if source.ground_truth() is None:
        return f"{source.path} has no ground truth"
    teach = route.reference_run()
    taught_from = route.run(teach).source if teach is not None else None
    if taught_from != str(source.path):
        return (
            f"the repeat's source {source.path} is not the teach's ({taught_from or 'unknown'}): their ground "
            "truths need not share one frame"
        )
    return None


def trunk_times(localizations: Sequence[Localization], path: TaughtPath) -> np.ndarray:
    """(N,) int64 times of the localizations' trunks, vertices of the taught ``path`` (no vertex is read)."""
    return path.t_ns[[path.index(loc.trunk_id) for loc in localizations]].astype(np.int64)


def chain_errors(
    localizations: Sequence[Localization], trunk_t_ns: np.ndarray, truth: GroundTruth
) -> LocalizationErrors:
    """Errors of localizations ``T_leaf_trunk`` against ground truth ``truth`` that covers both the leaf times and
    the trunk times ``trunk_t_ns`` (:func:`trunk_times`)."""
    return localization_errors(
        np.array([loc.T_leaf_trunk for loc in localizations]),
        np.array([loc.t_ns for loc in localizations]),
        np.asarray(trunk_t_ns, np.int64),
        truth.t_ns,
        truth.T_world_cam,
    )
