"""How much of the scale error on a clip the data owes: stereo disparities against the ground-truth motion.

    python tools/scale_check.py datasets/kitti00_ramp_clip --out out/scale_check

Prints the robust line measured = slope * implied + offset (implied: the disparity the ground-truth
motion implies for features triangulated from two left views) and the near-point scale factors: the
ground-truth translation factor that frame k+1's view of frame k's stereo landmarks (disparity above
each threshold, held fixed) asks for. Writes scale_check.json and disparity_offset.png in --out.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vtr.app.scale_check import MIN_PARALLAX_DEG, disparity_offset, disparity_samples, near_point_scale
from vtr.config import Config
from vtr.io import open_source


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clip", type=Path)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    cfg = Config()
    with open_source(args.clip) as source:
        samples = disparity_samples(source, cfg)
        line = disparity_offset(samples)
        scales = near_point_scale(source, cfg)
    print(
        f"{args.clip}: measured = {line.slope:.4f} * implied {line.offset_px:+.3f} px "
        f"(robust sigma {line.sigma_px:.3f} px, {line.points} features)"
    )
    for thr, s in scales.items():
        print(f"  near-point scale, disparity >= {thr:4.1f} px: x{s:.4f}")
    if args.out is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "scale_check.json").write_text(
            json.dumps(
                {
                    "clip": str(args.clip),
                    "disparity_line": line.to_dict(),
                    "near_point_scale": {str(k): v for k, v in scales.items()},
                },
                indent=2,
            )
            + "\n"
        )
        ok = samples.parallax_deg >= MIN_PARALLAX_DEG
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.scatter(samples.implied_px[ok], samples.measured_px[ok] - samples.implied_px[ok], s=2, alpha=0.3)
        x = np.linspace(0, 60, 50)
        ax.plot(x, (line.slope - 1) * x + line.offset_px, "r", label=f"offset {line.offset_px:+.2f} px")
        ax.set(
            xlim=(0, 60),
            ylim=(-5, 5),
            xlabel="disparity implied by ground-truth motion (px)",
            ylabel="measured - implied (px)",
            title=args.clip.name,
        )
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.out / "disparity_offset.png", dpi=120)
        print(f"wrote {args.out / 'scale_check.json'}, {args.out / 'disparity_offset.png'}")


if __name__ == "__main__":
    main()
