"""Benchmark of the on-disk pose-graph map on a long synthetic route.

Writes a teach run of ``--vertices`` keyframes (``--features`` random features each, about
two thirds with depth) spaced ``--spacing`` metres apart, one transaction per vertex with its
temporal edge (``Map.add_keyframe``), and reports write time per vertex, bytes per keyframe and per km. Then, in a fresh
process, walks the route the way a repeat does: at each step a nearest-vertex query, the
window -10..+20 along the privileged path and a read of every vertex in it (through the bounded
LRU cache), recording resident memory after 500 steps and at the end. Flat memory means the
store does not grow with route length.

    python tools/bench_map.py                       # 5000 keyframes x 600 features
    python tools/bench_map.py --vertices 500 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

WINDOW_BACK, WINDOW_FORWARD = 10, 20  # VT&R3 localization window along the path
RSS_EARLY_STEP = 500  # compare memory after this many steps with the end
FEATURE_DEPTH_FRACTION = 2 / 3
IMAGE_W, IMAGE_H = 1226, 370
FX, BASELINE = 718.856, 0.537


def rss_kb() -> dict[str, int]:
    """Current and peak resident set size (kB) of this process (Linux /proc)."""
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0])
    return out


def synthetic_frame(rng: np.random.Generator, n: int, index: int):
    """A StereoFrame-like keyframe with random features (duck-typed: no image processing imported)."""
    uv = np.column_stack([rng.uniform(0, IMAGE_W, n), rng.uniform(0, IMAGE_H, n)])
    disparity = rng.uniform(1.0, 80.0, n)
    z = FX * BASELINE / disparity
    points = np.column_stack([(uv[:, 0] - IMAGE_W / 2) * z / FX, (uv[:, 1] - IMAGE_H / 2) * z / FX, z])
    u_right = uv[:, 0] - disparity
    no_depth = rng.random(n) > FEATURE_DEPTH_FRACTION
    u_right[no_depth] = np.nan
    points[no_depth] = np.nan
    features = SimpleNamespace(
        uv=uv, octave=rng.integers(0, 8, n).astype(np.int32), descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8)
    )
    return SimpleNamespace(t_ns=index * 100_000_000, index=index, features=features, u_right=u_right, points=points)


def route_pose(i: int, spacing: float) -> np.ndarray:
    """A gently winding route in the x-z plane of the first camera (y down), metres."""
    s = i * spacing
    yaw = 0.3 * np.sin(s / 50.0)
    T = np.eye(4)
    c, sn = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, 0, sn], [0, 1, 0], [-sn, 0, c]]
    T[:3, 3] = [30.0 * np.sin(s / 80.0), 0.0, s]
    return T


def write(path: Path, n_vertices: int, n_features: int, spacing: float) -> dict:
    from vtr.camera import StereoCamera
    from vtr.map import Map
    from vtr.types import Keyframe

    camera = StereoCamera(
        fx=FX, fy=FX, cx=IMAGE_W / 2, cy=IMAGE_H / 2, baseline=BASELINE, width=IMAGE_W, height=IMAGE_H
    )
    rng = np.random.default_rng(0)
    cov = np.eye(6) * 1e-4
    t_write = 0.0
    rss_early = None
    with Map.create(path, camera) as m:
        run = m.begin_run("teach", source="bench_map synthetic route")
        for i in range(n_vertices):
            frame = synthetic_frame(rng, n_features, i)
            T = route_pose(i, spacing)
            kf = Keyframe(i, frame, T, cov, 100)  # vertex and temporal edge in one transaction
            t0 = time.perf_counter()
            m.add_keyframe(run, kf)
            t_write += time.perf_counter() - t0
            if i + 1 == RSS_EARLY_STEP:
                rss_early = rss_kb()["VmRSS"]
        rss_end = rss_kb()["VmRSS"]
    size = path.stat().st_size
    return {
        "vertices": n_vertices,
        "features_per_vertex": n_features,
        "spacing_m": spacing,
        "write_s_per_vertex": t_write / n_vertices,
        "bytes_on_disk": size,
        "bytes_per_keyframe": size / n_vertices,
        "bytes_per_km": size / n_vertices * 1000.0 / spacing,
        "write_rss_kb_after_500": rss_early,
        "write_rss_kb_end": rss_end,
    }


def walk(path: Path) -> dict:
    """Repeat-like read pattern over the whole privileged path; runs in its own process."""
    from vtr.map import Map

    base = rss_kb()["VmRSS"]
    with Map.open(path, "r") as m:
        t0 = time.perf_counter()
        taught = m.taught_path()
        ids, T = taught.ids, taught.T_world_vertex
        t_poses = time.perf_counter() - t0
        taught.nearest(T[0, :3, 3], 1)  # warm-up: imports scipy, builds the k-d tree
        m.vertex(int(ids[0]))
        warm = rss_kb()["VmRSS"]
        rss = {}
        t_nearest = t_window = 0.0
        reads = 0
        t_start = time.perf_counter()
        for step, T_v in enumerate(T):
            t0 = time.perf_counter()
            trunk = int(taught.nearest(T_v[:3, 3] + [0.3, 0.0, 0.1], 1)[0])
            t1 = time.perf_counter()
            lo, hi = taught.window(trunk, WINDOW_BACK, WINDOW_FORWARD)
            for vid in taught.ids[lo:hi].tolist():
                v = m.vertex(vid)
                reads += v.n_features
            t2 = time.perf_counter()
            t_nearest += t1 - t0
            t_window += t2 - t1
            if step + 1 == RSS_EARLY_STEP:
                rss["after_500"] = rss_kb()
        t_total = time.perf_counter() - t_start
        rss["end"] = rss_kb()
    n = len(ids)
    return {
        "walk_steps": n,
        "taught_path_s": t_poses,
        "walk_ms_per_step": 1e3 * t_total / n,
        "nearest_ms": 1e3 * t_nearest / n,
        "window_read_ms": 1e3 * t_window / n,
        "walk_rss_kb_at_open": base,
        "walk_rss_kb_warm": warm,
        "walk_rss_kb_after_500": rss.get("after_500", {}).get("VmRSS"),
        "walk_rss_kb_end": rss["end"]["VmRSS"],
        "walk_peak_rss_kb": rss["end"]["VmHWM"],
    }


def _mb(kb: int | None) -> str:
    return "n/a" if kb is None else f"{kb / 1e3:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vertices", type=int, default=5000)
    ap.add_argument("--features", type=int, default=600)
    ap.add_argument("--spacing", type=float, default=1.0, help="metres between keyframes")
    ap.add_argument("--dir", type=Path, default=None, help="where to write the map (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the map file")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    ap.add_argument("--walk-only", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.walk_only:
        print(json.dumps(walk(args.walk_only)))
        return

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path = Path(tmp) / "bench.vtrmap"
        res = write(path, args.vertices, args.features, args.spacing)
        out = subprocess.run(
            [sys.executable, __file__, "--walk-only", str(path)],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        )
        res.update(json.loads(out.stdout))
        if args.keep:
            kept = Path(args.dir or ".") / "bench.vtrmap"
            path.replace(kept)
            res["map"] = str(kept)
    print(
        f"route: {res['vertices']} keyframes x {res['features_per_vertex']} features, "
        f"{res['spacing_m']} m apart ({res['vertices'] * res['spacing_m'] / 1000:.1f} km)"
    )
    print(
        f"write: {1e3 * res['write_s_per_vertex']:.2f} ms/vertex "
        "(vertex + temporal edge in one commit, synchronous=FULL)"
    )
    print(
        f"size:  {res['bytes_on_disk'] / 1e6:.1f} MB, {res['bytes_per_keyframe'] / 1e3:.1f} kB/keyframe, "
        f"{res['bytes_per_km'] / 1e6:.1f} MB/km"
    )
    print(
        f"write RSS: {_mb(res['write_rss_kb_after_500'])} MB after 500 vertices, "
        f"{res['write_rss_kb_end'] / 1e3:.1f} MB after {res['vertices']}"
    )
    print(
        f"walk:  taught path in {1e3 * res['taught_path_s']:.1f} ms; {res['walk_ms_per_step']:.2f} ms/step "
        f"(nearest {res['nearest_ms']:.3f} ms, window -{WINDOW_BACK}..+{WINDOW_FORWARD} read "
        f"{res['window_read_ms']:.2f} ms)"
    )
    print(
        f"walk RSS: {res['walk_rss_kb_at_open'] / 1e3:.1f} MB at open, "
        f"{res['walk_rss_kb_warm'] / 1e3:.1f} MB after warm-up (scipy, k-d tree, first vertex), "
        f"{_mb(res['walk_rss_kb_after_500'])} MB after 500 steps, "
        f"{res['walk_rss_kb_end'] / 1e3:.1f} MB after {res['walk_steps']}, "
        f"peak {res['walk_peak_rss_kb'] / 1e3:.1f} MB"
    )
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
