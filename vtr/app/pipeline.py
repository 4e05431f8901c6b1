"""Run orchestration: ``vtr odometry``, ``teach`` and ``repeat`` as runs of one shape (:class:`OdometryRun`,
:class:`TeachRun`, :class:`RepeatRun`): built from frozen inputs (:class:`RunInputs` and the run's own), each
:meth:`run` reads as the same named steps: open (the source, the outputs: a typed record), loop (every frame),
evaluate, write, summarize, ``run.json`` last. The library never prints; progress goes to a callback
(docs/architecture.md).
"""

from __future__ import annotations

import time
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import DataError
from ..geometry import inv_T
from ..io.base import FrameSource, SourceOptions
from ..io.trajectory import write_tum
from ..signals import held_signals
from ..types import FrameKind, FrameRecord
from ..vo.odometry import OdometrySettings, StereoOdometry
from .evaluation import DriftMetrics, associate, drift_metrics
from .outputs import OutputFolder
from .repeat_pipeline import (
    GRAVITY_AGREEMENT_DEG,
    OpenRepeat,
    RepeatEvaluation,
    RepeatOptions,
    RepeatRun,
    RepeatSummary,
    StateSummary,
    append_landmarks,
    chain_errors,
    repeat_command,
    trunk_times,
    write_landmarks_csv,
)
from .run_inputs import OpenSource, Progress, RunInputs, frames_of, iterate, open_inputs
from .runfiles import ODOMETRY_OUTPUTS, TEACH_OUTPUTS
from .runfiles.frames_csv import write_frames_csv

__all__ = [  # the runs of every command (the repeat's from repeat_pipeline), what callers import from here
    "GRAVITY_AGREEMENT_DEG",
    "OdometryRun",
    "OdometrySummary",
    "OpenRepeat",
    "OpenSource",
    "Progress",
    "RepeatEvaluation",
    "RepeatOptions",
    "RepeatRun",
    "RepeatSummary",
    "RunInputs",
    "StateSummary",
    "TeachRun",
    "TeachSummary",
    "append_landmarks",
    "chain_errors",
    "frames_of",
    "iterate",
    "keyframe_note",
    "odometry_command",
    "open_inputs",
    "repeat_command",
    "run_odometry",
    "teach_command",
    "trunk_times",
    "write_landmarks_csv",
]


@dataclass(frozen=True)
class OdometrySummary:
    frames: int
    keyframes: int
    failures: int
    seconds: float
    drift: DriftMetrics | None
    note: str | None = None  # why the counts look odd (e.g. a camera that never moved enough)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")

    def to_dict(self) -> dict:
        d: dict[str, object] = {
            "frames": self.frames,
            "keyframes": self.keyframes,
            "failures": self.failures,
            "seconds": self.seconds,
            "fps": self.fps,
        }
        if self.drift is not None:
            d["drift"] = self.drift.to_dict()
        return d


def run_odometry(
    source: FrameSource, indices: list[int], config: Config, progress: Progress | None = None
) -> tuple[list[FrameRecord], np.ndarray, float]:
    """Odometry over the selected frames; returns per-frame records, final poses in the first
    camera frame (N, 4, 4; keyframes as refined by the window) and the elapsed seconds."""
    vo = StereoOdometry(source.camera, OdometrySettings.of(config))
    records = []
    t0 = time.perf_counter()
    for frame in frames_of(source, indices, vo.stereo, progress, "odometry"):
        with held_signals():  # Ctrl-C lands between frames
            records.append(vo.process_frame(frame).record())
    return records, vo.final_poses(), time.perf_counter() - t0


@dataclass(frozen=True)
class OdometryLoop:
    """Odometry over every selected frame: the frames' records, their final poses in the first camera frame
    (N, 4, 4) and the seconds it took."""

    records: list[FrameRecord]
    poses: np.ndarray
    seconds: float

    @property
    def t_ns(self) -> np.ndarray:
        return np.array([r.t_ns for r in self.records], np.int64)


@dataclass(frozen=True)
class OdometryEvaluation:
    """Odometry against the source's ground truth (None: it has none covering two frames): drift and the ground
    truth poses in the first camera's frame, for the plot."""

    drift: DriftMetrics | None
    T_first_gt: np.ndarray | None


class OdometryRun:
    """``vtr odometry`` as named steps (:meth:`run`): open the source and the outputs; loop every frame through
    the odometry; evaluate against ground truth; write ``trajectory_tum.txt``, ``frames.csv``, ``trajectory.png``;
    summarize; ``run.json`` (and ``config.yaml``) last."""

    def __init__(self, inputs: RunInputs, out: Path):
        self.inputs, self.out = inputs, Path(out)

    def run(self) -> OdometrySummary:
        with ExitStack() as stack:
            opened = open_inputs(stack, self.inputs, "odometry", self.out, ODOMETRY_OUTPUTS)
            loop = self.loop(opened)
            evaluation = self.evaluate(opened, loop)
            self.write(opened, loop, evaluation)
            summary = self.summarize(loop, evaluation)
            assert opened.log is not None
            opened.log.write(summary.to_dict())
        if not loop.records:
            raise DataError(f"{self.inputs.source_path}: no frames processed")
        return summary

    # -- the steps ----------------------------------------------------------------------------------------------

    def loop(self, opened: OpenSource) -> OdometryLoop:
        """Every selected frame through the odometry."""
        return OdometryLoop(*run_odometry(opened.source, opened.indices, self.inputs.config, self.inputs.progress))

    def evaluate(self, opened: OpenSource, loop: OdometryLoop) -> OdometryEvaluation:
        """Drift against the source's ground truth, when it has some at two of the frames."""
        truth = opened.source.ground_truth()
        if truth is None:
            return OdometryEvaluation(None, None)
        ie, ig = associate(loop.t_ns, truth.t_ns)
        if len(ie) < 2:
            return OdometryEvaluation(None, None)
        T_world_gt = truth.T_world_cam[ig]
        T_first_gt = inv_T(T_world_gt[0]) @ T_world_gt
        return OdometryEvaluation(drift_metrics(loop.poses[ie], T_first_gt), T_first_gt)

    def write(self, opened: OpenSource, loop: OdometryLoop, evaluation: OdometryEvaluation) -> None:
        """``trajectory_tum.txt``, ``frames.csv`` and ``trajectory.png``."""
        from .report import plot_trajectory

        folder = opened.folder
        assert folder is not None
        folder.write("trajectory_tum.txt", write_tum, loop.t_ns, loop.poses)
        folder.write("frames.csv", write_frames_csv, loop.records)
        folder.write(
            "trajectory.png",
            plot_trajectory,
            loop.poses,
            evaluation.T_first_gt,
            self._failures(loop),
            title=f"{self.inputs.source_path.name}: {len(loop.records)} frames",
        )

    def summarize(self, loop: OdometryLoop, evaluation: OdometryEvaluation) -> OdometrySummary:
        """The run's record (run.json's summary; the command line prints it)."""
        keyframes = sum(r.new_vertex for r in loop.records)
        return OdometrySummary(
            frames=len(loop.records),
            keyframes=keyframes,
            failures=int(self._failures(loop).sum()),
            seconds=loop.seconds,
            drift=evaluation.drift,
            note=keyframe_note(keyframes, len(loop.records), loop.poses, self.inputs.config),
        )

    @staticmethod
    def _failures(loop: OdometryLoop) -> np.ndarray:
        return np.array([r.kind == FrameKind.FAILURE for r in loop.records])


def odometry_command(
    source_path: Path,
    out: Path,
    frames: str | None,
    config: Config,
    source_options: SourceOptions | str | None = None,
    progress: Progress | None = None,
) -> OdometrySummary:
    """``vtr odometry``: trajectory_tum.txt, frames.csv, trajectory.png, run.json, config.yaml in ``out``
    (:class:`OdometryRun`'s steps)."""
    return OdometryRun(RunInputs(Path(source_path), frames, config, source_options, progress), out).run()


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
    return (
        f"only the first frame is a keyframe: the camera moved at most {moved:.2f} m and turned "
        f"{turned:.1f} deg from it, below the keyframe test (odometry.keyframe_translation_m "
        f"{o.keyframe_translation_m:g} m, keyframe_rotation_deg {o.keyframe_rotation_deg:g} deg): a nearly "
        "static log"
    )


# ---------------------------------------------------------------------------------------- teach


@dataclass(frozen=True)
class TeachSummary:
    frames: int
    vertices: int
    failures: int
    seconds: float
    map_path: Path
    gravity_up: tuple[float, float, float] | None = None  # kept in the map (None: none stored)


def _unit3(v: np.ndarray) -> tuple[float, float, float]:
    x, y, z = (float(a) for a in np.asarray(v, float) / np.linalg.norm(v))
    return x, y, z


@dataclass(frozen=True)
class TeachLoop:
    """The teach over every selected frame, its map closed: the frames' records, the vertices written, the taught
    path's times and poses as stored, the up direction kept in the map, the seconds it took."""

    records: list[FrameRecord]
    vertices: int
    t_taught_ns: np.ndarray
    T_world_taught: np.ndarray
    up: np.ndarray | None
    seconds: float


class TeachRun:
    """``vtr teach`` as named steps (:meth:`run`): open the source and the outputs (``out`` is optional); loop every
    frame through the teach into a new map (the privileged path); write ``trajectory_tum.txt`` and ``frames.csv``;
    summarize; ``run.json`` last.

    ``gravity_up``: up in the first left camera's frame (``--up``); without it the source's own (a format whose
    ground truth is gravity-aligned), else none is stored and readers take the first camera as level. The run
    ends finished, or aborted with the reason on any exception (the keyframes still in the odometry window are
    written first); a teach that wrote no vertex leaves no map file."""

    def __init__(
        self, inputs: RunInputs, map_path: Path, out: Path | None = None, gravity_up: np.ndarray | None = None
    ):
        self.inputs, self.map_path, self.out, self.gravity_up = inputs, Path(map_path), out, gravity_up

    def run(self) -> TeachSummary:
        with ExitStack() as stack:
            opened = open_inputs(stack, self.inputs, "teach", self.out, TEACH_OUTPUTS)
            loop = self.loop(opened)
            summary = self.summarize(loop)
            if opened.folder is not None and opened.log is not None:
                self.write(opened.folder, loop)
                opened.log.write(
                    {
                        "frames": summary.frames,
                        "vertices": summary.vertices,
                        "failures": summary.failures,
                        "seconds": summary.seconds,
                        "map": str(self.map_path),
                        "gravity_up": None if summary.gravity_up is None else list(summary.gravity_up),
                    }
                )
        return summary

    # -- the steps ----------------------------------------------------------------------------------------------

    def loop(self, opened: OpenSource) -> TeachLoop:
        """Every selected frame through the teach, each keyframe written to a new map as it becomes final."""
        from ..map import Map
        from ..navigation.teach import Teach

        source, config = opened.source, self.inputs.config
        t0 = time.perf_counter()
        records: list[FrameRecord] = []
        up = (
            self.gravity_up
            if self.gravity_up is not None or not opened.indices
            else source.gravity_up(opened.indices[0])
        )
        with Map.create(self.map_path, source.camera, config.map, gravity_up=up) as taught:
            teach = Teach(taught, source.camera, config, source=str(self.inputs.source_path))
            try:
                for frame in frames_of(source, opened.indices, teach.odometry.stereo, self.inputs.progress, "teach"):
                    with held_signals():  # a frame's keyframes are all written or not made
                        records.append(teach.process_frame(frame).record())
                with held_signals():
                    vertices = teach.finish()
            except BaseException as err:  # error, Ctrl-C, SIGTERM, full disk: keep the window, say why
                teach.abort(err)  # (a map left without any vertex is removed when it closes)
                raise
            _, t_taught_ns = taught.timestamps(teach.run)
            _, T_world_taught = taught.poses(teach.run)
        return TeachLoop(records, vertices, t_taught_ns, T_world_taught, up, time.perf_counter() - t0)

    def write(self, folder: OutputFolder, loop: TeachLoop) -> None:
        """``trajectory_tum.txt`` (the taught path as stored) and ``frames.csv``."""
        folder.write("trajectory_tum.txt", write_tum, loop.t_taught_ns, loop.T_world_taught)
        folder.write("frames.csv", write_frames_csv, loop.records)

    def summarize(self, loop: TeachLoop) -> TeachSummary:
        """The run's record (run.json's summary; the command line prints it)."""
        failures = sum(r.kind == FrameKind.FAILURE for r in loop.records)
        return TeachSummary(
            frames=len(loop.records),
            vertices=loop.vertices,
            failures=failures,
            seconds=loop.seconds,
            map_path=self.map_path,
            gravity_up=None if loop.up is None else _unit3(loop.up),
        )


def teach_command(
    source_path: Path,
    map_path: Path,
    frames: str | None,
    config: Config,
    out: Path | None = None,
    source_options: SourceOptions | str | None = None,
    progress: Progress | None = None,
    gravity_up: np.ndarray | None = None,
) -> TeachSummary:
    """``vtr teach``: odometry over SOURCE, keyframes written to a new map (the privileged path);
    :class:`TeachRun`'s steps."""
    return TeachRun(
        RunInputs(Path(source_path), frames, config, source_options, progress), map_path, out, gravity_up
    ).run()
