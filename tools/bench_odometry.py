"""Odometry speed on one core: frames per second at native resolution, split into load / features /
stereo / matching / estimation / window bundle adjustment, and peak memory.

usage: python tools/bench_odometry.py [SOURCE ...] [--frames A:B:S] [--repeats N]
Defaults: the shipped KITTI clip (1226x370) and a synthetic aerial sequence (672x376, generated once
into /tmp). Thread pools are pinned to one thread before numpy/OpenCV load.
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

from vtr.config import Config  # noqa: E402
from vtr.io import open_source, parse_frame_range  # noqa: E402
from vtr.vo.odometry import StereoOdometry  # noqa: E402

cv2.setNumThreads(1)
ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC = Path("/tmp/vtr_bench_aerial")
STAGES = ("load", "features", "stereo", "matching", "estimation", "window_ba")


def synthetic_sequence() -> Path:
    from vtr.sim import synthetic as syn

    if not (SYNTHETIC / "times_ns.txt").is_file():
        T = syn.aerial_route(60.0, 1.0)
        syn.write_sequence(SYNTHETIC, syn.aerial_scene(0), syn.zed_camera(), T, syn.route_times(T, 10.0))
    return SYNTHETIC


def bench(path: Path, frames: str | None, repeats: int) -> dict:
    best = None
    for _ in range(repeats):
        with open_source(path) as src:
            idx = parse_frame_range(frames, len(src), str(path))
            vo = StereoOdometry(src.camera, Config())
            load = 0.0
            t0 = time.perf_counter()
            for i in idx:
                t = time.perf_counter()
                images = src[i]
                load += time.perf_counter() - t
                vo.process(images)
            total = time.perf_counter() - t0
        stages = {"load": load, **vo.timer.seconds}
        run = {"source": path.name, "size": f"{src.camera.width}x{src.camera.height}", "frames": len(idx),
               "fps": len(idx) / total, "ms_per_frame": 1000 * total / len(idx),
               **{f"{k}_ms": 1000 * stages.get(k, 0.0) / len(idx) for k in STAGES}}
        if best is None or run["fps"] > best["fps"]:
            best = run
    best["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sources", nargs="*", type=Path)
    ap.add_argument("--frames", default=None)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    sources = args.sources or [ROOT / "datasets" / "kitti06_clip", synthetic_sequence()]
    for path in sources:
        r = bench(path, args.frames, args.repeats)
        split = "  ".join(f"{k} {r[f'{k}_ms']:.1f}" for k in STAGES)
        print(f"{r['source']} ({r['size']}, {r['frames']} frames, best of {args.repeats}): {r['fps']:.1f} frames/s, "
              f"{r['ms_per_frame']:.1f} ms/frame  [{split} ms]  peak RSS {r['peak_rss_mb']:.0f} MB")
    print("threads: 1 (OpenCV and BLAS);", f"load average {np.round(os.getloadavg(), 2).tolist()}")


if __name__ == "__main__":
    main()
