"""Odometry under imperceptible sensor noise: the drift of each clip clean and with Gaussian noise of
``--sigma`` grey levels (1: +-1 level) added to both images, one seed per variant, and its spread.

Per clip: t_err (KITTI-style, 10-40 m sub-segments, ``vtr.app.evaluation.drift_metrics``) of the clean run and of
each seed (with the disparity offset the odometry estimated online and removed, ``odometry.disparity_offset``), then
max, min, spread (max - min, percentage points), mean and standard deviation (the spread of five
variants is itself a noisy figure: pass more ``--seeds`` to judge a change). A run whose result moves by a fraction of a
point with noise no one can see is luck, not accuracy (docs/odometry_stability.md).

usage: python tools/bench_noise.py [CLIP ...] [--seeds 1 2 3 4] [--sigma 1] [--threads 1] [--out out/bench_noise]
        [--set section.key=value ...]
Defaults: datasets/kitti06_clip and datasets/kitti00_ramp_clip. Writes noise.csv, noise.json and noise.png
(t_err per variant, per clip) into --out, and each variant's trajectory_tum.txt under --out/CLIP/VARIANT.
The noise of a frame depends only on (seed, frame index), so a variant is the same images every time.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterable, Iterator  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from vtr.app.evaluation import associate, drift_metrics  # noqa: E402
from vtr.app.pipeline import frames_of  # noqa: E402
from vtr.config import Config  # noqa: E402
from vtr.geometry import inv_T  # noqa: E402
from vtr.io import open_source  # noqa: E402
from vtr.io.base import FrameSource  # noqa: E402
from vtr.io.trajectory import write_tum  # noqa: E402
from vtr.types import FrameKind, StereoImages  # noqa: E402
from vtr.vo.odometry import OdometrySettings, StereoOdometry  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CLIPS = (ROOT / "datasets" / "kitti06_clip", ROOT / "datasets" / "kitti00_ramp_clip")


def noisy(image: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    """``image`` (uint8) plus Gaussian noise of ``sigma`` grey levels, rounded and clipped to 0..255."""
    return np.clip(np.rint(image + rng.normal(0.0, sigma, image.shape)), 0, 255).astype(np.uint8)


def noisy_images(images: StereoImages, seed: int, sigma: float) -> StereoImages:
    """Both images of a pair with noise drawn from (``seed``, frame index): the same variant every time."""
    rng = np.random.default_rng((seed, images.index))
    return replace(images, left=noisy(images.left, rng, sigma), right=noisy(images.right, rng, sigma))


class NoisySource(FrameSource):
    """A source whose frames carry noise of ``sigma`` grey levels (seed ``seed``); None seed: the clean frames."""

    def __init__(self, source: FrameSource, seed: int | None, sigma: float):
        self.source, self.seed, self.sigma = source, seed, sigma
        self.path, self.camera = source.path, source.camera

    def __len__(self) -> int:
        return len(self.source)

    def timestamps(self) -> np.ndarray:
        return self.source.timestamps()

    def _load(self, index: int) -> StereoImages:
        images = self.source[index]
        return images if self.seed is None else noisy_images(images, self.seed, self.sigma)

    def iter_frames(self, indices: Iterable[int] | None = None) -> Iterator[StereoImages]:
        for images in self.source.iter_frames(indices):
            yield images if self.seed is None else noisy_images(images, self.seed, self.sigma)

    def ground_truth(self):
        return self.source.ground_truth()


def run_variant(clip: Path, seed: int | None, sigma: float, config: Config, out: Path | None = None) -> dict:
    """Odometry over every frame of ``clip`` (noisy with ``seed``, clean when None) and its drift."""
    with open_source(clip) as src:
        source = NoisySource(src, seed, sigma)
        vo = StereoOdometry(source.camera, OdometrySettings.of(config))  # as vtr.app.pipeline.run_odometry
        t0 = time.perf_counter()
        records = [
            vo.process_frame(frame).record()
            for frame in frames_of(source, list(range(len(source))), vo.stereo, None, "odometry")
        ]
        poses, seconds = vo.final_poses(), time.perf_counter() - t0
        gt = src.ground_truth()
    fit = None if vo.disparity_offset is None else vo.disparity_offset.fit
    t_ns = np.array([r.t_ns for r in records], np.int64)
    ie, ig = associate(t_ns, gt.t_ns)
    T_gt = gt.T_world_cam[ig]
    drift = drift_metrics(poses[ie], inv_T(T_gt[0]) @ T_gt)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        write_tum(out / "trajectory_tum.txt", t_ns, poses)
    return {
        "clip": clip.name,
        "variant": "clean" if seed is None else f"seed {seed}",
        "seed": seed,
        "sigma": 0.0 if seed is None else sigma,
        "t_err_pct": drift.t_err_pct,
        "r_err_deg_per_m": drift.r_err_deg_per_m,
        "end_pct": drift.end_pct,
        "length_ratio": drift.length_ratio,
        "failures": sum(r.kind == FrameKind.FAILURE for r in records),
        "disparity_offset_fit_px": float("nan") if fit is None else fit.offset_px,
        "disparity_offset_removed_px": vo.disparity_offset_px,
        "frames": len(records),
        "seconds": seconds,
    }


def spread(rows: list[dict]) -> dict:
    t = np.array([r["t_err_pct"] for r in rows])
    return {
        "clip": rows[0]["clip"],
        "max_pct": float(t.max()),
        "min_pct": float(t.min()),
        "spread_points": float(t.max() - t.min()),
        "mean_pct": float(t.mean()),
        "std_points": float(t.std()),
        "clean_pct": rows[0]["t_err_pct"],
    }


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clips = list(dict.fromkeys(r["clip"] for r in rows))
    fig, axes = plt.subplots(1, len(clips), figsize=(4.5 * len(clips), 3.6), squeeze=False)
    for ax, clip in zip(axes[0], clips, strict=True):
        mine = [r for r in rows if r["clip"] == clip]
        ax.bar(
            range(len(mine)),
            [r["t_err_pct"] for r in mine],
            color=["tab:blue" if r["seed"] is None else "tab:orange" for r in mine],
        )
        ax.set_xticks(range(len(mine)), [r["variant"] for r in mine], rotation=30)
        ax.set_ylabel("t_err (%)")
        s = spread(mine)
        ax.set_title(f"{clip}: spread {s['spread_points']:.2f} points")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def configured(overrides: list[str], threads: int) -> Config:
    data = Config().to_dict()
    for item in overrides:
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        data[section][name] = yaml.safe_load(value)
    config = Config.from_dict(data, "--set")
    config = config.replace("features", threads=threads)
    return config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clips", nargs="*", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--sigma", type=float, default=1.0, help="noise standard deviation (grey levels)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("out/bench_noise"))
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="a config override")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    config = configured(args.set, args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, summaries = [], []
    for clip in args.clips or CLIPS:
        mine = []
        for seed in [None, *args.seeds]:
            r = run_variant(
                clip, seed, args.sigma, config, args.out / clip.name / ("clean" if seed is None else f"seed{seed}")
            )
            mine.append(r)
            print(
                f"{clip.name:20s} {r['variant']:8s} t_err {r['t_err_pct']:.3f} %  r_err {r['r_err_deg_per_m']:.4f}"
                f" deg/m  path x{r['length_ratio']:.4f}  failures {r['failures']}  disparity offset fit"
                f" {r['disparity_offset_fit_px']:+.2f} px, removed {r['disparity_offset_removed_px']:+.2f}",
                flush=True,
            )
        s = spread(mine)
        print(
            f"{clip.name:20s} clean {s['clean_pct']:.3f} %  max {s['max_pct']:.3f} %  min {s['min_pct']:.3f} %  "
            f"spread {s['spread_points']:.3f} points  mean {s['mean_pct']:.3f} %  std {s['std_points']:.3f}",
            flush=True,
        )
        rows += mine
        summaries.append(s)
    fields = list(rows[0])
    with open(args.out / "noise.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fields)
        w.writeheader()
        w.writerows(rows)
    (args.out / "noise.json").write_text(
        json.dumps(
            {"sigma": args.sigma, "seeds": args.seeds, "overrides": args.set, "runs": rows, "clips": summaries},
            indent=1,
        )
    )
    plot(rows, args.out / "noise.png")
    print(
        "summary: "
        + "; ".join(
            f"{s['clip']} {s['min_pct']:.2f}-{s['max_pct']:.2f} % (clean {s['clean_pct']:.2f},"
            f" spread {s['spread_points']:.2f})"
            for s in summaries
        )
        + f"  [sigma {args.sigma:g} grey levels, seeds {' '.join(map(str, args.seeds))}; {args.out}]"
    )


if __name__ == "__main__":
    main()
