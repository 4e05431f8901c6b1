"""Odometry speed with 1 and 2 threads: frames per second at native resolution, split into load / features /
stereo / matching / estimation / window bundle adjustment, peak memory, and whether the trajectories of
every thread count are identical.

usage: python tools/bench_odometry.py [SOURCE ...] [--frames A:B:S] [--repeats N] [--threads 1 2]
                                      [--cv-threads N] [--preload]
Defaults: the shipped KITTI clip (1226x370) and a synthetic aerial sequence (672x376, generated once
into /tmp). BLAS pools are pinned to one thread before numpy loads; OpenCV's own pool to --cv-threads (1).
With threads > 1, later frames are decoded and stereo-processed in the background while frame k is tracked
(``StereoProcessor.frames``): "load" is then the time spent waiting for the next stereo frame, and the
features and stereo stages overlap the others (their times are summed over the background workers).
``--preload`` decodes every frame before the clock starts (the ORB-SLAM3 anchor script times its tracking
that way): the frames/s are then those of the odometry alone.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from machine_load import second_core_available  # noqa: E402  (tools/machine_load.py)

from vtr.config import Config  # noqa: E402
from vtr.io import open_source, parse_frame_range  # noqa: E402
from vtr.vo.odometry import OdometrySettings, StereoOdometry  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC = Path("/tmp/vtr_bench_aerial")
STAGES = ("load", "features", "stereo", "matching", "estimation", "window_ba")


def synthetic_sequence() -> Path:
    from vtr.sim import synthetic as syn

    if not (SYNTHETIC / "times_ns.txt").is_file():
        T = syn.aerial_route(60.0, 1.0)
        syn.write_sequence(SYNTHETIC, syn.aerial_scene(0), syn.zed_camera(), T, syn.route_times(T, 10.0))
    return SYNTHETIC


def bench_once(path: Path, frames: str | None, threads: int, preload: bool = False) -> dict:
    """One odometry pass over ``path`` with ``threads``; ``preload`` decodes the frames first, untimed."""
    config = Config().replace("features", threads=threads)
    with open_source(path) as src:
        idx = parse_frame_range(frames, len(src), str(path))
        images = [src[i] for i in idx] if preload else src.iter_frames(idx)
        vo = StereoOdometry(src.camera, OdometrySettings.of(config))
        load = 0.0
        inline = vo.stereo.threads == 1  # one thread: waiting for a frame also runs its features and stereo

        def stereo_seconds() -> float:
            return sum(vo.timer.seconds.get(k, 0.0) for k in ("features", "stereo")) if inline else 0.0

        t0 = time.perf_counter()
        stream = vo.stereo.frames(images)
        while True:
            t, busy = time.perf_counter(), stereo_seconds()
            frame = next(stream, None)
            load += time.perf_counter() - t - (stereo_seconds() - busy)
            if frame is None:
                break
            vo.process_frame(frame)
        total = time.perf_counter() - t0
    stages = {"load": load, **vo.timer.seconds}
    return {
        "source": path.name,
        "size": f"{src.camera.width}x{src.camera.height}",
        "frames": len(idx),
        "fps": len(idx) / total,
        "ms_per_frame": 1000 * total / len(idx),
        "poses": vo.final_poses(),
        **{f"{k}_ms": 1000 * stages.get(k, 0.0) / len(idx) for k in STAGES},
    }


def bench(
    path: Path, frames: str | None, repeats: int, thread_counts: list[int], preload: bool = False
) -> dict[int, dict]:
    """Best of ``repeats`` passes per thread count, the counts interleaved (a shared machine's load hits
    them alike)."""
    best: dict[int, dict] = {}
    for _ in range(repeats):
        for threads in thread_counts:
            run = bench_once(path, frames, threads, preload)
            if threads not in best or run["fps"] > best[threads]["fps"]:
                best[threads] = run
    for run in best.values():
        run["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sources", nargs="*", type=Path)
    ap.add_argument("--frames", default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="vtr thread counts to compare")
    ap.add_argument("--cv-threads", type=int, default=1, help="cv2.setNumThreads (OpenCV's own pool)")
    ap.add_argument("--preload", action="store_true", help="decode every frame before timing (load is then 0)")
    args = ap.parse_args()
    cv2.setNumThreads(args.cv_threads)
    sources = args.sources or [ROOT / "datasets" / "kitti06_clip", synthetic_sequence()]
    for path in sources:
        print(f"second core available (2 threads of a GIL-free OpenCV workload vs 1): {second_core_available():.2f}x")
        runs = bench(path, args.frames, args.repeats, args.threads, args.preload)
        for threads, r in runs.items():
            split = "  ".join(f"{k} {r[f'{k}_ms']:.1f}" for k in STAGES)
            print(
                f"{r['source']} ({r['size']}, {r['frames']} frames, best of {args.repeats}"
                f"{', preloaded' if args.preload else ''}) threads {threads}: "
                f"{r['fps']:.1f} frames/s, {r['ms_per_frame']:.1f} ms/frame  [{split} ms]  "
                f"peak RSS {r['peak_rss_mb']:.0f} MB"
            )
        first = runs[args.threads[0]]
        for threads, r in runs.items():
            if threads != args.threads[0]:
                print(
                    f"    threads {threads} vs {args.threads[0]}: {r['fps'] / first['fps']:.2f}x, trajectories "
                    f"{'identical' if np.array_equal(r['poses'], first['poses']) else 'DIFFERENT'}"
                )
    print(f"OpenCV threads {cv2.getNumThreads()}, BLAS 1; load average {np.round(os.getloadavg(), 2).tolist()}")


if __name__ == "__main__":
    main()
