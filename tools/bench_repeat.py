"""Repeat speed beside odometry speed, measured in one run: frames/s of ``Repeat.steps`` (odometry, the new vertices
written to the map and localized) and of ``StereoOdometry`` alone on the same frames of the KITTI clip (teach the
even frames, repeat the odd ones), with 1 and 2 threads, their ratio, CPU milliseconds per frame of each, the
localization's split per keyframe, and whether every thread count gives the same localizations.

usage: python tools/bench_repeat.py [--repeats N] [--threads 1 2] [--localization-thread own caller] [--frames 1::2]
                                   [--floor] [--out DIR]

Images are decoded before timing (load time is neither's time). On a shared machine the load of other jobs hits
any single figure: odometry and repeat are run back to back in each round (thread counts interleaved), the ratio
is taken within each round, and medians over the rounds are printed. CPU time (the process's, all threads) per
frame says what each costs whatever the load; CPU time of the caller's thread what the frame's own path costs (with
1 thread the repeat's map writes run on its writer thread: off that path); frames/s what a user sees. Writes
``bench_repeat.json`` and ``bench_repeat.csv`` (one row per run) to ``--out`` (default out/bench_repeat).

``--floor`` says what part of the gap each of the repeat's own jobs takes: in each round two more repeats run beside
the real one, one whose localization is free (each leaf's localization and map record replayed from the round's
real repeat: the odometry, the pipeline and the map writes remain) and one whose map writes are skipped (the odometry,
the pipeline and the localization remain). Their ratios to the same round's odometry are diagnostics, not results:
neither repeat is one a user could run.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from concurrent.futures import Future  # noqa: E402
from pathlib import Path  # noqa: E402
from unittest import mock  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vtr.app.evaluation import path_length  # noqa: E402
from vtr.app.pipeline import teach_command  # noqa: E402
from vtr.config import Config  # noqa: E402
from vtr.io import open_source, parse_frame_range  # noqa: E402
from vtr.map import Map  # noqa: E402
from vtr.map.localizations import Leaf  # noqa: E402
from vtr.navigation.localization import Localization  # noqa: E402
from vtr.navigation.repeat import Repeat  # noqa: E402
from vtr.types import StereoImages  # noqa: E402
from vtr.vo.odometry import OdometrySettings, StereoOdometry  # noqa: E402

CLIP = Path(__file__).resolve().parents[1] / "datasets" / "kitti06_clip"
TARGET_RATIO = 0.9  # issue 33: a repeat at least 0.9x the odometry's frames/s


def timed_odometry(images: list[StereoImages], camera, config: Config) -> dict:
    """Odometry alone over the preloaded ``images`` (the stereo pipeline of ``config.features.threads``)."""
    vo = StereoOdometry(camera, OdometrySettings.of(config), keep_history=True)
    c0, m0, t0 = time.process_time(), time.thread_time(), time.perf_counter()
    for frame in vo.stereo.frames(images):
        vo.process_frame(frame)
    seconds, cpu, main = time.perf_counter() - t0, time.process_time() - c0, time.thread_time() - m0
    n = len(images)
    return {"fps": n / seconds, "cpu_ms": 1000 * cpu / n, "main_cpu_ms": 1000 * main / n, "poses": vo.final_poses()}


class RecordingRepeat(Repeat):
    """A repeat that keeps each leaf's localization and map record (``answers``, by leaf id) for ``ReplayedRepeat``."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.answers: dict[int, tuple[Localization, Leaf]] = {}

    def _localize(self, leaf_id, kf, window):
        out = self.answers[leaf_id] = super()._localize(leaf_id, kf, window)
        return out


class ReplayedRepeat(Repeat):
    """``--floor``: a repeat whose localization costs nothing (each leaf's recorded answer handed back)."""

    def __init__(self, *args, answers: dict[int, tuple[Localization, Leaf]], **kwargs):
        super().__init__(*args, **kwargs)
        self.answers = answers

    def _localize(self, leaf_id, kf, window):
        return self.answers[leaf_id]


class SkippedWrites:
    """``--floor``: a LeafWriter that writes and reads nothing (each leaf's write done at once)."""

    def __init__(self, *args, **kwargs):
        pass

    def submit(self, *args, **kwargs) -> Future:
        done: Future = Future()
        done.set_result(None)
        return done

    def prefetch(self, vertex_ids) -> None:
        pass

    def close(self, cancel_pending: bool = False) -> None:
        pass


def timed_repeat(map_path: Path, images: list[StereoImages], config: Config, kind=RecordingRepeat, **kw) -> dict:
    """``Repeat.steps`` over the preloaded ``images`` against the map at ``map_path`` (a fresh copy)."""
    with Map.open(map_path, "a") as m:
        rp = kind(m, config, str(CLIP), **kw)
        rp.timer.reset()
        c0, m0, t0 = time.process_time(), time.thread_time(), time.perf_counter()
        steps = list(rp.steps(rp.odometry.stereo.frames(images)))
        seconds, cpu, main = time.perf_counter() - t0, time.process_time() - c0, time.thread_time() - m0
        stages = dict(rp.timer.seconds)
        split = dict(rp.localizer.timer.seconds)
    n = len(images)
    locs = [s.localization for s in steps if s.localization is not None]
    key = [(loc.trunk_id, str(loc.status), loc.matches, loc.inliers, loc.T_leaf_trunk.tobytes()) for loc in locs]
    return {
        "fps": n / seconds,
        "cpu_ms": 1000 * cpu / n,
        "main_cpu_ms": 1000 * main / n,
        "keyframes": len(locs),
        "localized": sum(loc.success for loc in locs),
        "inliers": sum(loc.inliers for loc in locs if loc.success),
        "stages_ms_per_frame": {k: 1000 * v / n for k, v in stages.items()},
        "localization_split_ms_per_keyframe": {k: 1000 * v / max(len(locs), 1) for k, v in split.items()},
        "loc_ms": [1000 * s.localization_seconds for s in steps if s.localization is not None],
        "key": key,
        "answers": getattr(rp, "answers", {}),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="rounds (each: odometry then repeat, every thread count)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="vtr thread counts to compare")
    ap.add_argument("--frames", default="1::2", help="repeat frames of the clip (the teach takes the even ones)")
    ap.add_argument(
        "--localization-thread",
        nargs="+",
        default=["own"],
        choices=["own", "caller"],
        help="localization.thread of the repeat: its own thread (default) or the caller's; both: A/B in each round",
    )
    ap.add_argument("--cv-threads", type=int, default=1, help="cv2.setNumThreads (OpenCV's own pool)")
    ap.add_argument(
        "--floor",
        action="store_true",
        help="also time a repeat with its localization replayed and one with its map writes skipped (diagnostics)",
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_repeat"))
    args = ap.parse_args()
    cv2.setNumThreads(args.cv_threads)
    args.out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        taught = Path(tmp) / "route.vtrmap"
        teach = teach_command(CLIP, taught, "0::2", Config())
        with Map.open(taught) as m:
            km = path_length(m.taught_path().T_world_vertex) / 1000.0
            size = m.bytes_on_disk()
        print(
            f"map: {teach.vertices} keyframes over {1000 * km:.1f} m, {size / teach.vertices / 1024:.1f} KiB per "
            f"keyframe, {size / km / 2**20:.1f} MiB per km"
        )
        with open_source(CLIP) as src:
            idx = parse_frame_range(args.frames, len(src), str(CLIP))
            images = [src[i] for i in idx]  # decoded first: load time is not repeat time
            camera = src.camera
        copy = Path(tmp) / "repeat.vtrmap"
        for k in range(-1, args.repeats):  # round -1 warms up (kernels, caches) and is not kept
            for threads, where in ((t, w) for t in args.threads for w in args.localization_thread):
                # interleaved: a shared machine's load hits every count
                config = Config().replace("features", threads=threads).replace("localization", thread=where)
                label = threads if len(args.localization_thread) == 1 else f"{threads} ({where})"
                vo = timed_odometry(images, camera, config)
                copy.write_bytes(taught.read_bytes())
                rp = timed_repeat(copy, images, config)
                copy.unlink()
                floor = {}
                if args.floor:
                    copy.write_bytes(taught.read_bytes())
                    free = timed_repeat(copy, images, config, ReplayedRepeat, answers=rp["answers"])
                    copy.unlink()
                    copy.write_bytes(taught.read_bytes())
                    with mock.patch("vtr.navigation.repeat.LeafWriter", SkippedWrites):
                        unwritten = timed_repeat(copy, images, config)
                    copy.unlink()
                    floor = {
                        "ratio_localization_replayed": free["fps"] / vo["fps"],
                        "ratio_writes_skipped": unwritten["fps"] / vo["fps"],
                        "cpu_ms_localization_replayed": free["cpu_ms"],
                        "cpu_ms_writes_skipped": unwritten["cpu_ms"],
                    }
                if k >= 0:
                    rows.append(
                        {
                            "round": k,
                            "threads": label,
                            "odometry_fps": vo["fps"],
                            "repeat_fps": rp["fps"],
                            "ratio": rp["fps"] / vo["fps"],
                            "odometry_cpu_ms": vo["cpu_ms"],
                            "repeat_cpu_ms": rp["cpu_ms"],
                            "cpu_ratio": vo["cpu_ms"] / rp["cpu_ms"],
                            "odometry_main_cpu_ms": vo["main_cpu_ms"],
                            "repeat_main_cpu_ms": rp["main_cpu_ms"],
                            "main_cpu_ratio": vo["main_cpu_ms"] / rp["main_cpu_ms"],
                            **floor,
                            "_vo": vo,
                            "_rp": rp,
                        }
                    )
    summary: dict = {
        "clip": CLIP.name,
        "frames": args.frames,
        "n_frames": len(idx),
        "rounds": args.repeats,
        "load_average_before": list(load_before),
        "load_average_after": list(os.getloadavg()),
        "target_ratio": TARGET_RATIO,
        "threads": {},
    }
    labels = list(dict.fromkeys(r["threads"] for r in rows))
    first = rows[0]
    identical_loc = all(r["_rp"]["key"] == first["_rp"]["key"] for r in rows)
    identical_vo = all(np.array_equal(r["_vo"]["poses"], first["_vo"]["poses"]) for r in rows)
    print(
        f"{CLIP.name} frames {args.frames} ({len(idx)} frames), medians of {args.repeats} rounds "
        f"(odometry and repeat back to back in each round):"
    )
    for threads in labels:
        mine = [r for r in rows if r["threads"] == threads]
        med = {
            k: float(np.median([r[k] for r in mine]))
            for k in (
                "odometry_fps",
                "repeat_fps",
                "ratio",
                "odometry_cpu_ms",
                "repeat_cpu_ms",
                "cpu_ratio",
                "odometry_main_cpu_ms",
                "repeat_main_cpu_ms",
                "main_cpu_ratio",
            )
        }
        rp = mine[int(np.argsort([r["ratio"] for r in mine])[len(mine) // 2])]["_rp"]  # the median round's repeat
        summary["threads"][threads] = {
            **med,
            "ratio_range": [min(r["ratio"] for r in mine), max(r["ratio"] for r in mine)],
            "keyframes": rp["keyframes"],
            "localized": rp["localized"],
            "inliers": rp["inliers"],
            "localization_ms_median": float(np.median(rp["loc_ms"])),
            "stages_ms_per_frame": rp["stages_ms_per_frame"],
            "localization_split_ms_per_keyframe": rp["localization_split_ms_per_keyframe"],
        }
        s = summary["threads"][threads]
        if args.floor:
            for key in ("ratio_localization_replayed", "ratio_writes_skipped"):
                s[key] = float(np.median([r[key] for r in mine]))
                s[key + "_range"] = [min(r[key] for r in mine), max(r[key] for r in mine)]
            for key in ("cpu_ms_localization_replayed", "cpu_ms_writes_skipped"):
                s[key] = float(np.median([r[key] for r in mine]))
        print(
            f"  threads {threads}: odometry {med['odometry_fps']:.1f} frames/s, repeat {med['repeat_fps']:.1f} "
            f"frames/s: ratio {med['ratio']:.2f} (rounds {s['ratio_range'][0]:.2f}-{s['ratio_range'][1]:.2f}; "
            f"target >= {TARGET_RATIO}); CPU per frame odometry {med['odometry_cpu_ms']:.1f} ms, repeat "
            f"{med['repeat_cpu_ms']:.1f} ms (ratio {med['cpu_ratio']:.2f}); on the caller's thread "
            f"{med['odometry_main_cpu_ms']:.1f} / {med['repeat_main_cpu_ms']:.1f} ms (ratio "
            f"{med['main_cpu_ratio']:.2f})"
        )
        print(
            f"    {rp['localized']}/{rp['keyframes']} keyframes localized, {rp['inliers']} inliers in all, "
            f"localization {s['localization_ms_median']:.1f} ms median per keyframe"
        )
        print("    repeat ms/frame: " + "  ".join(f"{k} {v:.1f}" for k, v in rp["stages_ms_per_frame"].items()))
        if args.floor:
            print(
                f"    floor (diagnostics): localization replayed ratio {s['ratio_localization_replayed']:.2f} "
                f"(rounds {s['ratio_localization_replayed_range'][0]:.2f}-"
                f"{s['ratio_localization_replayed_range'][1]:.2f}), CPU {s['cpu_ms_localization_replayed']:.1f} ms "
                f"per frame; map writes skipped ratio {s['ratio_writes_skipped']:.2f} (rounds "
                f"{s['ratio_writes_skipped_range'][0]:.2f}-{s['ratio_writes_skipped_range'][1]:.2f}), CPU "
                f"{s['cpu_ms_writes_skipped']:.1f} ms per frame"
            )
        if rp["localization_split_ms_per_keyframe"]:
            print(
                "    localization ms/keyframe: "
                + "  ".join(f"{k} {v:.2f}" for k, v in rp["localization_split_ms_per_keyframe"].items())
            )
    summary["localizations_identical_across_threads_and_rounds"] = identical_loc
    summary["odometry_identical_across_threads_and_rounds"] = identical_vo
    print(
        f"  localizations {'identical' if identical_loc else 'DIFFERENT'} for every configuration ({labels}) in "
        "every round; "
        f"odometry trajectories {'identical' if identical_vo else 'DIFFERENT'}"
    )
    print(
        f"OpenCV threads {cv2.getNumThreads()}, BLAS 1; load average before {np.round(load_before, 2).tolist()}, "
        f"after {np.round(os.getloadavg(), 2).tolist()}"
    )
    (args.out / "bench_repeat.json").write_text(json.dumps(summary, indent=1))
    with open(args.out / "bench_repeat.csv", "w", newline="") as f:
        fields = [k for k in rows[0] if not k.startswith("_")]
        w = csv.DictWriter(f, fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: r[k] for k in fields})
    print(f"wrote {args.out / 'bench_repeat.json'}, {args.out / 'bench_repeat.csv'}")


if __name__ == "__main__":
    main()
