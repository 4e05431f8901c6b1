"""Benchmark: stream a large stereo ROS bag through ``open_source`` and show that memory stays flat.

Writes a bag of ``--frames`` stereo pairs (default 2000 pairs of 672x376 mono8 noise, the ZED
resolution of the thesis: ~1 GB) under ``--out`` (default /tmp), then reads it in a *fresh* process
(so the peak RSS is the reader's alone) through ``vtr.io.open_source``: the index pass on opening,
one streaming pass over every frame (frames/s), RSS after 200 frames and at the end, peak RSS, and
the cost of a few random accesses ``src[i]``.

    python tools/bench_bag_stream.py                       # rosbag1, 2000 frames
    python tools/bench_bag_stream.py --kind mcap --frames 3000
    python tools/bench_bag_stream.py --read BAG            # read phase only, on any stereo bag

The bag is deleted at the end unless ``--keep``.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

T0_NS = 1_600_000_000_000_000_000
FRAME_PERIOD_NS = 66_666_667  # 15 Hz, the thesis camera rate
NOISE_POOL = 8  # distinct noise images, rolled per frame so that every frame differs
EARLY_FRAME = 200
RANDOM_ACCESSES = 20
MB = 1 << 20


def rss_mb() -> float:
    """Current resident set size (MB) from /proc."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * resource.getpagesize() / MB


def peak_rss_mb() -> float:
    """Peak resident set size of this process (MB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def write(path: Path, kind: str, n: int, width: int, height: int) -> float:
    from vtr.camera import StereoCamera
    from vtr.io.rosbag_writer import RosbagWriter

    cam = StereoCamera(fx=350.0, fy=350.0, cx=width / 2, cy=height / 2, baseline=0.12, width=width, height=height)
    rng = np.random.default_rng(0)
    pool = rng.integers(0, 256, (NOISE_POOL, height, width), dtype=np.uint8)
    t = time.perf_counter()
    with RosbagWriter(path, cam, kind=kind) as w:
        for i in range(n):
            img = np.roll(pool[i % NOISE_POOL], i, axis=1)
            w.add(T0_NS + i * FRAME_PERIOD_NS, img, np.roll(img, -7, axis=1))
    return time.perf_counter() - t


def read(path: Path) -> dict:
    from vtr.io import open_source

    rss_start = rss_mb()
    t = time.perf_counter()
    src = open_source(path)
    t_open = time.perf_counter() - t
    n = len(src)
    rss_open = rss_mb()
    t = time.perf_counter()
    rss_early = None
    checksum = 0
    for f in src:
        checksum += int(f.left[0, 0]) + int(f.right[-1, -1])
        if f.index == min(EARLY_FRAME, n - 1):
            rss_early = rss_mb()
    t_stream = time.perf_counter() - t
    rss_end = rss_mb()
    rng = np.random.default_rng(1)
    idx = rng.integers(0, n, RANDOM_ACCESSES)
    t = time.perf_counter()
    for i in idx:
        src[int(i)]
    t_random = (time.perf_counter() - t) / RANDOM_ACCESSES
    src.close()
    return {
        "frames": n,
        "image_size": list(src.camera.size),
        "open_index_s": round(t_open, 3),
        "stream_fps": round(n / t_stream, 1),
        "stream_s": round(t_stream, 2),
        "random_access_ms": round(1e3 * t_random, 1),
        "rss_start_mb": round(rss_start, 1),
        "rss_after_open_mb": round(rss_open, 1),
        f"rss_after_{min(EARLY_FRAME, n - 1) + 1}_frames_mb": round(rss_early, 1),
        f"rss_after_{n}_frames_mb": round(rss_end, 1),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "rss_growth_early_to_end_mb": round(rss_end - rss_early, 1),
        "checksum": checksum,
    }


def bag_size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kind", choices=["rosbag1", "rosbag2", "mcap"], default="rosbag1")
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--size", default="672x376", help="WxH of the generated images")
    ap.add_argument("--out", type=Path, default=Path("/tmp"))
    ap.add_argument("--keep", action="store_true", help="keep the generated bag")
    ap.add_argument("--read", type=Path, default=None, help="only read (and report on) this bag")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON line")
    args = ap.parse_args()

    if args.read is not None:
        res = read(args.read)
        print(json.dumps(res) if args.json else "\n".join(f"{k}: {v}" for k, v in res.items()))
        return

    width, height = (int(v) for v in args.size.lower().split("x"))
    name = f"vtr_bench_{args.frames}x{width}x{height}" + (".bag" if args.kind == "rosbag1" else f"_{args.kind}")
    path = args.out / name
    if path.exists():
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    try:
        t_write = write(path, args.kind, args.frames, width, height)
        size = bag_size(path)
        print(
            f"wrote {args.frames} stereo frames {width}x{height} ({args.kind}) to {path}: {size / MB:.0f} MB "
            f"in {t_write:.1f} s",
            flush=True,
        )
        out = subprocess.run(
            [sys.executable, __file__, "--read", str(path), "--json"], check=True, capture_output=True, text=True
        ).stdout
        res = json.loads(out.strip().splitlines()[-1])
        res.update(kind=args.kind, bag_mb=round(size / MB, 1))
        if args.json:
            print(json.dumps(res))
        else:
            for k, v in res.items():
                print(f"  {k}: {v}")
            print(
                f"peak RSS {res['peak_rss_mb']} MB while streaming a {res['bag_mb']} MB bag at "
                f"{res['stream_fps']} frames/s; RSS grew {res['rss_growth_early_to_end_mb']} MB from frame "
                f"{EARLY_FRAME} to frame {res['frames']}"
            )
    finally:
        if not args.keep and path.exists():
            shutil.rmtree(path) if path.is_dir() else path.unlink()


if __name__ == "__main__":
    main()
