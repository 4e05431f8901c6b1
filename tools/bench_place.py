"""Place recognition at scale: query cost, memory and build time of the place index at 1 k, 5 k and 50 k taught
vertices of a synthetic long route, beside one odometry frame measured in the same run, and whether each query still
finds where it was taken.

usage: python tools/bench_place.py [--vertices 1000 5000 50000] [--queries 200] [--out out/bench_place]

The route: real ORB descriptors (every feature of every left image of the two shipped KITTI clips, about 150 000)
are the appearance of the world. Each landmark along the route takes one of them with ``LANDMARK_BITS`` of its 256
bits flipped (landmark id -> descriptor, deterministic: the world is never stored); vertex ``i`` sees the
``DESCRIPTORS_PER_VERTEX`` landmarks born over its last ``COVISIBLE_VERTICES`` vertices (so neighbours share most of
what they see, as keyframes 0.3 m apart do), each observed with ``OBSERVATION_BITS`` more flipped bits. A query is
a repeat keyframe half-way between vertices ``i`` and ``i + 1``: its landmarks observed afresh, plus
``CLUTTER_FRACTION`` descriptors of things the teach never saw. It is found when one of the index's
``place.candidates`` best vertices lies within one vertex of ``i`` or ``i + 1``.

Printed and written (``bench_place.json``, ``bench_place.csv``, ``bench_place.png``): per size, index build time,
bytes per vertex (the index's arrays) and in all, query ms (median and 95th percentile; the query's words included),
its ratio to one odometry frame (kitti06_clip, 1 thread, images decoded first, same run), and the share of queries
found.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vtr.config import Config  # noqa: E402
from vtr.io import open_source  # noqa: E402
from vtr.navigation.place import PlaceIndex  # noqa: E402
from vtr.vo.features import FeatureExtractor  # noqa: E402
from vtr.vo.odometry import OdometrySettings, StereoOdometry  # noqa: E402

ROOT = Path(__file__).resolve().parents[1] / "datasets"
CLIPS = (ROOT / "kitti06_clip", ROOT / "kitti00_ramp_clip")
DESCRIPTORS_PER_VERTEX = 2000  # a KITTI keyframe's features (features.n_features)
COVISIBLE_VERTICES = 10  # a landmark stays in view over this many vertices (3 m at 0.3 m per keyframe)
LANDMARK_BITS = 24  # bits flipped from a real descriptor to make a landmark (distinct places)
OBSERVATION_BITS = 12  # bits flipped per observation (two views of a landmark: ~24 bits apart)
CLUTTER_FRACTION = 0.2  # share of a query's descriptors the teach never saw
TARGET_MS = 5.0  # issue 33: at most 5 ms per query at 50 k vertices


def real_descriptors(config: Config) -> np.ndarray:
    """Every ORB descriptor of every left image of the shipped KITTI clips (N, 32) uint8."""
    out = []
    for clip in CLIPS:
        with open_source(clip) as src:
            fx = FeatureExtractor(config.features, src.camera.size)
            out += [fx.extract(im.left).descriptors for im in src.iter_frames(list(range(len(src))))]
    return np.unique(np.concatenate(out), axis=0)


class Route:
    """The synthetic route's world (see the module docstring); everything is a function of ids and the seed."""

    def __init__(self, pool: np.ndarray, seed: int = 0):
        self.pool = pool
        self.seed = seed
        self.born_per_vertex = DESCRIPTORS_PER_VERTEX // COVISIBLE_VERTICES
        self._blocks: dict[int, np.ndarray] = {}  # landmark descriptors of recent birth vertices

    def _block(self, block: int) -> np.ndarray:
        out = self._blocks.get(block)
        if out is None:
            if len(self._blocks) > 4 * COVISIBLE_VERTICES:
                self._blocks.clear()
            rng = np.random.default_rng([self.seed, block])
            base = rng.integers(0, len(self.pool), self.born_per_vertex)
            out = self._blocks[block] = self.pool[base] ^ self._flips(rng, self.born_per_vertex, LANDMARK_BITS)
        return out

    def _flips(self, rng: np.random.Generator, n: int, bits: int) -> np.ndarray:
        """(n, 32) uint8 masks with ``bits`` random bits set each (repeats allowed: at most ``bits``)."""
        mask = np.zeros((n, 256), np.uint8)
        mask[np.arange(n)[:, None], rng.integers(0, 256, (n, bits))] = 1
        return np.packbits(mask, axis=1)

    def landmarks(self, ids: np.ndarray) -> np.ndarray:
        """Descriptors (len(ids), 32) of landmarks ``ids``: a real descriptor with ``LANDMARK_BITS`` flipped."""
        out = np.empty((len(ids), 32), np.uint8)
        for block in np.unique(ids // self.born_per_vertex):  # one generator per birth vertex: deterministic
            sel = np.flatnonzero(ids // self.born_per_vertex == block)
            out[sel] = self._block(int(block))[ids[sel] % self.born_per_vertex]
        return out

    def seen_from(self, position: float) -> np.ndarray:
        """Ids of the landmarks in view at route ``position`` (in vertices): those born over the last window."""
        first = int(round((position - COVISIBLE_VERTICES + 1) * self.born_per_vertex))
        return np.arange(max(first, 0), max(first, 0) + DESCRIPTORS_PER_VERTEX)

    def view(self, position: float, salt: int, clutter: float = 0.0) -> np.ndarray:
        """One keyframe's descriptors at ``position``: its landmarks observed with noise, plus clutter."""
        rng = np.random.default_rng([self.seed, salt, int(position * 1000)])
        ids = self.seen_from(position)
        d = self.landmarks(ids) ^ self._flips(rng, len(ids), OBSERVATION_BITS)
        n_clutter = int(clutter * len(d))
        if n_clutter:
            d[rng.choice(len(d), n_clutter, replace=False)] = self.pool[rng.integers(0, len(self.pool), n_clutter)]
        return d


def odometry_frame_ms(config: Config) -> float:
    """Median over 3 passes of the ms per frame of 1-thread odometry on kitti06_clip (images decoded first)."""
    cfg = Config().replace("features", threads=1)
    with open_source(CLIPS[0]) as src:
        images = [src[i] for i in range(len(src))]
        camera = src.camera
    times = []
    for _ in range(3):
        vo = StereoOdometry(camera, OdometrySettings.of(cfg), keep_history=False)
        t0 = time.perf_counter()
        for im in images:
            vo.process(im)
        times.append(1000 * (time.perf_counter() - t0) / len(images))
    return float(np.median(times))


def bench_size(route: Route, vertices: int, queries: int, config: Config) -> dict:
    t0 = time.perf_counter()
    index = PlaceIndex.build(lambda: (route.view(i, salt=0) for i in range(vertices)), vertices, config.place)
    index.query(route.view(0.5, salt=1), config.place.candidates)  # derived query structures, if any, built now
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(vertices)
    at = rng.integers(0, vertices - 1, queries)
    views = [route.view(i + 0.5, salt=1, clutter=CLUTTER_FRACTION) for i in at]
    ms, cpu_ms, found = [], [], 0
    for i, d in zip(at, views, strict=True):
        t, c = time.perf_counter(), time.thread_time()
        match = index.query(d, config.place.candidates)
        ms.append(1000 * (time.perf_counter() - t))
        cpu_ms.append(1000 * (time.thread_time() - c))
        found += bool(np.any(np.abs(match.indices - (i + 0.5)) <= 1.5))
    size = index.nbytes()
    return {
        "vertices": vertices,
        "build_s": build_s,
        "query_ms_median": float(np.median(ms)),
        "query_ms_p95": float(np.percentile(ms, 95)),
        "query_cpu_ms_median": float(np.median(cpu_ms)),
        "bytes_per_vertex": size / vertices,
        "index_mib": size / 2**20,
        "found": found / queries,
        "queries": queries,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vertices", type=int, nargs="+", default=[1000, 5000, 50000])
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--out", type=Path, default=Path("out/bench_place"))
    args = ap.parse_args()
    cv2.setNumThreads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    config = Config()
    pool = real_descriptors(config)
    frame_ms = odometry_frame_ms(config)
    print(
        f"world: {len(pool)} real ORB descriptors of {len(CLIPS)} KITTI clips; {DESCRIPTORS_PER_VERTEX} descriptors "
        f"per vertex; one odometry frame (kitti06_clip, 1 thread) {frame_ms:.1f} ms"
    )
    route = Route(pool)
    rows = []
    for n in args.vertices:
        r = bench_size(route, n, args.queries, config)
        r["odometry_frame_ms"] = frame_ms
        r["query_per_odometry_frame"] = r["query_ms_median"] / frame_ms
        rows.append(r)
        print(
            f"{n:>6} vertices: build {r['build_s']:.1f} s, {r['bytes_per_vertex'] / 1024:.1f} KiB per vertex "
            f"({r['index_mib']:.0f} MiB), query {r['query_ms_median']:.2f} ms median ({r['query_ms_p95']:.2f} p95, "
            f"CPU {r['query_cpu_ms_median']:.2f}) "
            f"= {r['query_per_odometry_frame']:.2f} odometry frames, found {100 * r['found']:.1f} % "
            f"of {r['queries']} queries",
            flush=True,
        )
    big = max(rows, key=lambda r: r["vertices"])
    print(
        f"target: <= {TARGET_MS} ms per query at 50 k vertices -> {big['query_ms_median']:.2f} ms at "
        f"{big['vertices']} ({'met' if big['query_ms_median'] <= TARGET_MS else 'NOT met'}); load average "
        f"{np.round(os.getloadavg(), 2).tolist()}"
    )
    (args.out / "bench_place.json").write_text(
        json.dumps({"rows": rows, "target_ms": TARGET_MS, "load_average": list(os.getloadavg())}, indent=1)
    )
    with open(args.out / "bench_place.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.5))
        v = [r["vertices"] for r in rows]
        ax.loglog(v, [r["query_ms_median"] for r in rows], "o-", label="query (median)")
        ax.loglog(v, [r["query_ms_p95"] for r in rows], "s--", label="query (95th pct)")
        ax.loglog(v, [r["query_cpu_ms_median"] for r in rows], "^-", label="query CPU (median)")
        ax.axhline(frame_ms, color="grey", ls=":", label="one odometry frame")
        ax.axhline(TARGET_MS, color="red", ls=":", label=f"target {TARGET_MS} ms")
        ax.set_xlabel("taught vertices")
        ax.set_ylabel("ms per query")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.out / "bench_place.png", dpi=120)
    except ImportError:
        pass
    print(f"wrote {args.out / 'bench_place.json'}, {args.out / 'bench_place.csv'}")


if __name__ == "__main__":
    main()
