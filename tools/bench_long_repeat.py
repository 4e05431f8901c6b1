"""Teach and repeat a synthetic route of more than 5 000 keyframes with the real pipeline, and show
that memory does not grow with route length.

The route is a circuit flown several times (multirotor, ZED-like camera at 12 m, 50 deg down, a
keyframe every ``--spacing`` m); one lap of teach frames and one lap of repeat frames (1 m to the
left) are rendered once and fed lap after lap with increasing time stamps, so the taught path has
laps x frames-per-lap vertices. Teach writes every keyframe to a map on disk; a repeat (``Repeat``,
new process state, the map reopened) localizes every keyframe against it. Resident memory is read
from /proc after 500 keyframes and at the end of each run.

usage: python tools/bench_long_repeat.py [--laps 11] [--radius 30] [--spacing 0.4] [--keep DIR]
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from vtr.app.repeat_run import run_repeat  # noqa: E402
from vtr.config import Config  # noqa: E402
from vtr.map import Map  # noqa: E402
from vtr.navigation.repeat import Repeat  # noqa: E402
from vtr.navigation.teach import Teach  # noqa: E402
from vtr.sim import synthetic as syn  # noqa: E402
from vtr.types import StereoImages  # noqa: E402

cv2.setNumThreads(1)
FRAME_INTERVAL_NS = 100_000_000  # 10 Hz
EARLY_KEYFRAMES = 500  # memory is read here and at the end


def rss_mb() -> float:
    """Current resident set size of this process (MB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def memory_line(rss: dict[str, float], keyframes: int) -> str:
    early = rss.get("early", float("nan"))
    return f"RSS {early:.1f} MB after {EARLY_KEYFRAMES} keyframes, {rss['end']:.1f} MB after {keyframes}"


def render_lap(scene, camera, T: np.ndarray, desc: str) -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for T_i in tqdm(T, desc=desc, unit="frame"):
        pair = syn.render_stereo(scene, camera, T_i)
        out.append((pair.left, pair.right))
    return out


def frames(lap: list[tuple[np.ndarray, np.ndarray]], laps: int):
    """The lap's frames, lap after lap, with time stamps that keep increasing."""
    for k in range(laps * len(lap)):
        left, right = lap[k % len(lap)]
        yield StereoImages(k * FRAME_INTERVAL_NS, k, left, right)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--laps", type=int, default=11)
    ap.add_argument("--radius", type=float, default=30.0, help="circuit radius (m)")
    ap.add_argument("--spacing", type=float, default=0.4, help="distance between frames (m)")
    ap.add_argument("--keep", type=Path, default=None, help="write the map here instead of a temporary folder")
    args = ap.parse_args()

    camera, scene = syn.zed_camera(), syn.aerial_scene(0)
    circumference = 2 * math.pi * args.radius
    n_lap = round(circumference / args.spacing)
    spacing = circumference / n_lap
    route = {"curvature_per_m": 1.0 / args.radius, "start_xy": (0.0, 0.0), "heading_rad": 0.0}
    T_teach = syn.aerial_route(circumference - spacing / 2, spacing, **route)
    T_repeat = syn.aerial_route(circumference - spacing / 2, spacing, lateral_offset_m=1.0, **route)
    teach_lap = render_lap(scene, camera, T_teach, "render teach lap")
    repeat_lap = render_lap(scene, camera, T_repeat, "render repeat lap")
    total = args.laps * n_lap
    config = Config()
    folder = args.keep or Path(tempfile.mkdtemp())
    path = folder / "long.vtrmap"
    print(f"route: {args.laps} laps x {n_lap} frames = {total} frames, {total * spacing / 1000:.2f} km")

    with Map.create(path, camera) as m:
        teach = Teach(m, camera, config, "synthetic circuit")
        rss_teach, t0 = {}, time.perf_counter()
        stream = teach.odometry.stereo.frames(frames(teach_lap, args.laps))  # as `vtr teach` runs it
        for k, frame in enumerate(tqdm(stream, total=total, desc="teach", unit="frame")):
            teach.process_frame(frame)
            if k + 1 == EARLY_KEYFRAMES:
                rss_teach["early"] = rss_mb()
        vertices = teach.finish()
        rss_teach["end"] = rss_mb()
        teach_fps = total / (time.perf_counter() - t0)
    size_mb = path.stat().st_size / 1e6

    with Map.open(path, "a") as m:
        rp = Repeat(m, config, "synthetic circuit, 1 m left")
        rss_repeat, counts, t0 = {}, {"frames": 0, "attempts": 0, "localized": 0}, time.perf_counter()
        bar = tqdm(total=total, desc="repeat", unit="frame")

        def watch(step) -> None:
            counts["frames"] += 1
            bar.update()
            if step.localization is not None:
                counts["attempts"] += 1
                counts["localized"] += step.localization.success
            if counts["frames"] == EARLY_KEYFRAMES:
                rss_repeat["early"] = rss_mb()

        run_repeat(rp, rp.odometry.stereo.frames(frames(repeat_lap, args.laps)), on_step=watch)  # as `vtr repeat`
        bar.close()
        attempts, localized = counts["attempts"], counts["localized"]
        rss_repeat["end"] = rss_mb()
        repeat_fps = total / (time.perf_counter() - t0)

    print(
        f"teach: {vertices} vertices, map {size_mb:.0f} MB, {teach_fps:.1f} frames/s; "
        + memory_line(rss_teach, vertices)
    )
    print(
        f"repeat: {localized}/{attempts} keyframes localized, {repeat_fps:.1f} frames/s; "
        + memory_line(rss_repeat, attempts)
    )
    if args.keep is None:
        for p in folder.iterdir():
            p.unlink()
        folder.rmdir()


if __name__ == "__main__":
    main()
