"""Run orchestration: each run reads as a short list of named steps (open source, loop frames
with a progress bar, save, summarize). The library never prints; progress goes to a callback.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import Config
from .errors import DataError
from .evaluation import DriftMetrics, associate, drift_metrics
from .geometry import inv_T
from .io import open_source, parse_frame_range
from .io.base import FrameSource
from .io.trajectory import write_tum
from .odometry import FrameKind, OdometryResult, StereoOdometry
from .runlog import RunLog

FRAMES_CSV_HEADER = ("t_ns", "result", "matches", "inliers", "keyframe_id")


@dataclass(frozen=True)
class OdometrySummary:
    frames: int
    keyframes: int
    failures: int
    seconds: float
    drift: DriftMetrics | None

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")

    def to_dict(self) -> dict:
        d = {"frames": self.frames, "keyframes": self.keyframes, "failures": self.failures,
             "seconds": self.seconds, "fps": self.fps}
        if self.drift is not None:
            d["drift"] = self.drift.to_dict()
        return d

    def lines(self) -> list[str]:
        out = [f"frames {self.frames}  keyframes {self.keyframes}  failures {self.failures}  "
               f"{self.fps:.1f} frames/s"]
        if self.drift is not None:
            out.append(f"drift vs ground truth: {self.drift}")
        return out


def iterate(items: Iterable, total: int, progress: Callable | None, desc: str):
    """Wrap an iterable with a progress bar factory (e.g. tqdm) when given."""
    return progress(items, total=total, desc=desc) if progress else items


def run_odometry(source: FrameSource, indices: list[int], config: Config,
                 progress: Callable | None = None) -> tuple[list[OdometryResult], np.ndarray, float]:
    """Odometry over the selected frames; returns per-frame results, final poses in the first
    camera frame (N, 4, 4; keyframes as refined by the window) and the elapsed seconds."""
    vo = StereoOdometry(source.camera, config)
    results = []
    t0 = time.perf_counter()
    for i in iterate(indices, len(indices), progress, "odometry"):
        results.append(vo.process(source[i]))
    poses = vo.final_poses(results)
    return results, poses, time.perf_counter() - t0


def write_frames_csv(path: Path, results: list[OdometryResult]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(FRAMES_CSV_HEADER)
        for r in results:
            w.writerow([r.t_ns, r.kind.value, r.matches, r.inliers, r.keyframe_id])


def odometry_command(source_path: Path, out: Path, frames: str | None, config: Config,
                     fmt: str | None = None, progress: Callable | None = None) -> OdometrySummary:
    """``vtr odometry``: trajectory_tum.txt, frames.csv, trajectory.png, run.json, config.yaml in ``out``."""
    from .report import plot_trajectory

    with open_source(source_path, fmt) as source:
        indices = parse_frame_range(frames, len(source), str(source_path))
        out.mkdir(parents=True, exist_ok=True)
        log = RunLog(out, "odometry", config, [source_path])
        results, poses, seconds = run_odometry(source, indices, config, progress)
        t_ns = np.array([r.t_ns for r in results], np.int64)
        write_tum(out / "trajectory_tum.txt", t_ns, poses)
        write_frames_csv(out / "frames.csv", results)
        drift, T_gt = None, None
        gt = source.ground_truth()
        if gt is not None:
            ie, ig = associate(t_ns, gt.t_ns)
            if len(ie) >= 2:
                T_gt = gt.T_world_cam[ig]
                T_gt = inv_T(T_gt[0]) @ T_gt
                drift = drift_metrics(poses[ie], T_gt)
        failures = np.array([r.kind == FrameKind.FAILURE for r in results])
        plot_trajectory(out / "trajectory.png", poses, T_gt, failures,
                        title=f"{source_path.name}: {len(results)} frames")
        summary = OdometrySummary(len(results), sum(r.new_keyframe is not None for r in results),
                                  int(failures.sum()), seconds, drift)
        log.write(summary.to_dict())
    if not results:
        raise DataError(f"{source_path}: no frames processed")
    return summary
