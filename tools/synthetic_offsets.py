"""Teach an aerial route in a synthetic scene, repeat it with lateral (and vertical) offsets, and
measure localization: success rate, inliers and the estimated offset against the true one.

usage: python tools/synthetic_offsets.py [OUT_DIR] [--lateral 0,1,2,4,8] [--vertical 0] [--length 40]

Writes OUT_DIR/offsets.csv, OUT_DIR/inliers_vs_offset.png and, per repeat, landmarks.csv (input of
`perception-model fit`). The experiment itself is ``vtr.app.offsets.run_offset_repeats``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from vtr.app.offsets import run_offset_repeats


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for dz in sorted({r["vertical_m"] for r in rows}):
        sel = [r for r in rows if r["vertical_m"] == dz]
        ax.plot([r["lateral_m"] for r in sel], [r["median_inliers"] for r in sel], "o-", label=f"{dz:g} m up")
    ax.set_xlabel("lateral offset from the taught path [m]")
    ax.set_ylabel("median localization inliers")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="out/synthetic_offsets", type=Path)
    ap.add_argument("--lateral", default="0,1,2,4,8")
    ap.add_argument("--vertical", default="0")
    ap.add_argument("--length", type=float, default=40.0)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = run_offset_repeats(
        args.out, [float(v) for v in args.lateral.split(",")], [float(v) for v in args.vertical.split(",")], args.length
    )
    with open(args.out / "offsets.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, args.out / "inliers_vs_offset.png")
    for r in rows:
        print(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()))


if __name__ == "__main__":
    main()
