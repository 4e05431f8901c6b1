"""Localization integrity in one table: every case of the shipped clips (started at 1/3 and 2/3 of the route,
flown backward, frames removed mid-route, run past the taught end, the plain even/odd repeat) against ground
truth, then place recognition's time per query on a 5000-vertex map.

Per case: attempts, successes, wrong successes (> 0.30 m or 2 deg from ground truth), the attempt of the first
correct localization, the share correct after it, the median error of the correct ones, and how often the
reported sigma covers the error (3-sigma ellipsoid; an honest covariance covers ~99 %).

usage: python tools/bench_localization.py [--out out/bench_localization] [--vertices 5000]
Writes cases.csv and cases.json beside the printed table.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

from vtr.app.evaluation import integrity_of
from vtr.app.pipeline import repeat_command, teach_command
from vtr.app.runfiles.localization_csv import read_localization_csv
from vtr.config import Config
from vtr.io import open_source
from vtr.io.kitti import write_reordered_clip
from vtr.map import Map
from vtr.navigation.place import PlaceIndex

ROOT = Path(__file__).resolve().parents[1] / "datasets"
CLIPS = {"kitti06": ROOT / "kitti06_clip", "ramp": ROOT / "kitti00_ramp_clip"}


def _n(clip: Path) -> int:
    return len(list((clip / "image_0").glob("*.png")))


def cases(work: Path) -> list[tuple[str, str, str, Path, str]]:
    """(name, clip, teach frames, repeat clip, repeat frames)."""
    out = []
    for name, clip in CLIPS.items():
        n = _n(clip)
        third, two_thirds = (n // 3) | 1, (2 * n // 3) | 1
        rev = write_reordered_clip(clip, work / f"{name}_reversed", list(range(n - 1, -1, -1)))
        a, b = int(0.4 * n), int(0.6 * n)
        gap = write_reordered_clip(clip, work / f"{name}_gap", [i for i in range(n) if not a <= i < b])
        out += [
            (f"{name} even/odd", name, "0::2", clip, "1::2"),
            (f"{name} from 1/3", name, "0::2", clip, f"{third}::2"),
            (f"{name} from 2/3", name, "0::2", clip, f"{two_thirds}::2"),
            (f"{name} backward", name, "0::2", rev, "1::2"),
            (f"{name} gap {a}-{b}", name, "0::2", gap, "1::2"),
            (f"{name} past end", name, f"0:{n // 2}:2", clip, "1::2"),
        ]
    return out


def run_case(work: Path, name: str, clip_name: str, teach_frames: str, rep_clip: Path, rep_frames: str) -> dict:
    clip = CLIPS[clip_name]
    slug = name.replace(" ", "_").replace("/", "-")
    map_path = work / f"{slug}.vtrmap"
    teach_command(clip, map_path, teach_frames, Config())
    summary = repeat_command(rep_clip, map_path, work / slug, rep_frames, Config())
    rows = list(csv.DictReader(open(work / slug / "localization.csv")))
    locs = read_localization_csv(work / slug / "localization.csv")
    with Map.open(map_path) as m, open_source(rep_clip) as rep, open_source(clip) as teach:
        trunk_t = np.array([m.vertex(loc.trunk_id).t_ns for loc in locs], np.int64)
        integ = integrity_of(locs, trunk_t, rep.ground_truth(), teach.ground_truth())
    statuses: dict[str, int] = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    return {
        "case": name,
        "attempts": integ.attempts,
        "successes": integ.successes,
        "wrong": integ.wrong,
        "first_correct": integ.first_correct,
        "rate_after": integ.rate_after,
        "median_error_mm": 1000 * integ.median_error_m,
        "sigma_covers": integ.covered,
        "median_nees": integ.median_nees,
        "fps": summary.frames / summary.seconds,
        "statuses": statuses,
    }


def place_timing(vertices: int, seed: int = 0) -> dict:
    """Build and query a place index of ``vertices`` vertices (real ORB descriptors of the KITTI clip, each
    vertex a random subset with random bit flips, so no two are alike)."""
    from vtr.vo.stereo import StereoProcessor

    cfg = Config()
    rng = np.random.default_rng(seed)
    with open_source(CLIPS["kitti06"]) as src:
        sp = StereoProcessor(src.camera, cfg.features, cfg.stereo)
        real = [sp.process(im).features.descriptors for im in src.iter_frames(list(range(0, _n(CLIPS["kitti06"]), 5)))]

    def vertex(i: int) -> np.ndarray:
        r = np.random.default_rng(i)
        d = real[i % len(real)][r.choice(len(real[i % len(real)]), 1500, replace=False)].copy()
        flips = r.integers(0, 256, size=(len(d), 8))
        for k in range(flips.shape[1]):
            d[np.arange(len(d)), flips[:, k] // 8] ^= (1 << (flips[:, k] % 8)).astype(np.uint8)
        return d

    t0 = time.perf_counter()
    index = PlaceIndex.build(lambda: (vertex(i) for i in range(vertices)), vertices, cfg.place)
    build_s = time.perf_counter() - t0
    queries = [real[int(k)] for k in rng.integers(0, len(real), 50)]
    index.query(queries[0], cfg.place.candidates)
    t0 = time.perf_counter()
    for q in queries:
        index.query(q, cfg.place.candidates)
    return {"vertices": vertices, "build_s": build_s, "query_ms": 1000 * (time.perf_counter() - t0) / len(queries)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_localization"))
    ap.add_argument("--vertices", type=int, default=5000)
    args = ap.parse_args()
    work = args.out
    if work.exists() and any(work.iterdir()):
        raise SystemExit(f"{work}: not empty (choose another --out)")
    work.mkdir(parents=True, exist_ok=True)
    results = []
    print(
        f"{'case':<22} {'att':>4} {'succ':>4} {'wrong':>5} {'first':>5} {'after':>6} {'med mm':>7} "
        f"{'3sig cov':>8} {'NEES':>6}"
    )
    for case in cases(work):
        r = run_case(work, *case)
        results.append(r)
        print(
            f"{r['case']:<22} {r['attempts']:>4} {r['successes']:>4} {r['wrong']:>5} {str(r['first_correct']):>5} "
            f"{100 * r['rate_after']:>5.0f}% {r['median_error_mm']:>7.1f} {100 * r['sigma_covers']:>7.0f}% "
            f"{r['median_nees']:>6.2f}",
            flush=True,
        )
    timing = place_timing(args.vertices)
    print(
        f"place recognition on {timing['vertices']} vertices: build {timing['build_s']:.1f} s, "
        f"query {timing['query_ms']:.2f} ms"
    )
    with open(work / "cases.csv", "w", newline="") as f:
        w = csv.DictWriter(f, [k for k in results[0] if k != "statuses"])
        w.writeheader()
        for r in results:
            w.writerow({k: v for k, v in r.items() if k != "statuses"})
    (work / "cases.json").write_text(json.dumps({"cases": results, "place_recognition": timing}, indent=1))
    print(f"wrote {work / 'cases.csv'}, {work / 'cases.json'}")


if __name__ == "__main__":
    main()
