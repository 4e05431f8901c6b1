"""The return flight on the controller side: a synthetic aerial route (camera 50 degrees down, 12 m above the
ground) taught with its gravity, repeated 2 m left of the taught heading forward and backward (on past the taught
start), each repeat's state.csv judged against ground truth (direction, lateral, vertical, vz, nothing localized past
the start).

usage: python tools/return_flight.py [--out OUT] [--speed 6] [--offset 2] [--past 10]

Writes OUT/return_flight.json, OUT/return_flight.csv and OUT/return_flight.png (lateral and vertical error along the
route, both flights); the experiment is ``vtr.app.return_flight.run_return_flight``.
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import asdict
from pathlib import Path

from vtr.app.return_flight import format_check, run_return_flight
from vtr.app.runfiles.state_csv import read_state_csv


def plot(out: Path, names: list[str]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for name in names:
        st = read_state_csv(out / name / "repeat" / "state.csv")
        t = (st.t_ns - st.t_ns[0]) * 1e-9
        axes[0].plot(t, st.lateral, label=f"{name}")
        axes[1].plot(t, st.vertical, label=f"{name}")
        axes[2].plot(t, st.velocity[:, 2], label=f"{name}")
    for ax, label in zip(axes, ("lateral_m (left of travel)", "vertical_m", "vz (m/s)"), strict=True):
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.legend()
    axes[2].set_xlabel("time since the repeat's first frame (s)")
    fig.tight_layout()
    path = out / "return_flight.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/return_flight", type=Path)
    ap.add_argument("--speed", type=float, default=6.0, help="flight speed (m/s; frames at 10 Hz)")
    ap.add_argument("--offset", type=float, default=2.0, help="left of the taught heading (m)")
    ap.add_argument("--past", type=float, default=10.0, help="flown past the taught start on the way back (m)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    checks = run_return_flight(
        args.out, offset_m=args.offset, speed_mps=args.speed, past_start_m=args.past, progress=print
    )
    with open(args.out / "return_flight.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(checks[0])))
        w.writeheader()
        w.writerows(asdict(c) for c in checks)
    png = plot(args.out, [c.name for c in checks])
    print("summary:")
    for c in checks:
        print("  " + format_check(c))
    print(f"wrote {args.out}/return_flight.json, return_flight.csv, {png.name}")


if __name__ == "__main__":
    main()
