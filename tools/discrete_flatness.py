"""The thesis' §8.4.1 simulation (Fig. 8.2): tracking error against position noise for PD, the flatness MPC
and the discrete-time flatness controller, with perfect measurements and with vtr's smoother in the loop.

usage: python tools/discrete_flatness.py --out OUT [--trials 10] [--seed 0] [--sigmas 0.0001,...,0.05]
                                         [--loops perfect,estimator] [--calibrate]
                                         [--estimator-derivatives finite_difference|estimator]
                                         [--estimator-inputs prior|extrapolation]

Writes OUT/results.csv (loop, controller, sigma_m, mean_error_m, std_error_m, max_error_m, trials) and
OUT/error_vs_sigma.png (error against sigma on log axes, one line per controller, one panel per loop); prints a
progress line per loop, sigma and controller and a summary of the ordering of Fig. 8.2 at the end.
``--calibrate`` re-derives the tuning of the settings' defaults (no noise involved) and prints it;
``--estimator-derivatives estimator`` gives PD and the flatness MPC the estimator's own velocity and acceleration in
the estimator loop instead of finite differences of its positions; ``--estimator-inputs extrapolation`` keeps the
commands sent out of the smoother's prior (they only carry its outputs past the anchor, as OnlineRepeat does).
The model and settings: vtr/control/pitch_model.py; the controllers: vtr/control/discrete_flatness.py; the loop and
the sweep: vtr/control/flatness_sweep.py; docs/discrete_flatness.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from vtr.control.flatness_sweep import SweepRow, calibrate, noiseless_error_m, sweep, write_results_csv
from vtr.control.pitch_model import CONTROLLERS, LOOPS, DiscreteFlatnessSettings
from vtr.errors import VtrError

DEFAULT_SIGMAS_M = (0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)
#: Fig. 8.2's claims: at low noise the three agree within this fraction; the orderings hold at high noise.
LOW_SIGMA_M, HIGH_SIGMA_M, AGREEMENT = 0.0005, 0.005, 0.20
COLORS = {"pd": "tab:green", "flatness_mpc": "tab:blue", "discrete_flatness": "tab:red"}
LABELS = {"pd": "PD", "flatness_mpc": "Flatness MPC", "discrete_flatness": "Discrete-Flatness"}


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def names(allowed: Sequence[str]):
    def parse(text: str) -> list[str]:
        out = [x.strip() for x in text.split(",") if x.strip()]
        bad = [x for x in out if x not in allowed]
        if bad or not out:
            raise argparse.ArgumentTypeError(f"expected some of {', '.join(allowed)}, got {text!r}")
        return out

    return parse


def ordering(rows: Sequence[SweepRow]) -> list[tuple[str, bool, str]]:
    """Fig. 8.2's claims per loop and sigma: (claim, holds, figures)."""
    table = {(r.loop, r.controller, r.sigma_m): r.mean_error_m for r in rows}
    out = []
    for loop in dict.fromkeys(r.loop for r in rows):
        for sigma in sorted({r.sigma_m for r in rows if r.loop == loop}):
            e = {c: table.get((loop, c, sigma)) for c in CONTROLLERS}
            if any(v is None for v in e.values()):
                continue
            pd, mpc, df = e["pd"], e["flatness_mpc"], e["discrete_flatness"]
            figures = f"pd {pd:.4f}  flatness_mpc {mpc:.4f}  discrete_flatness {df:.4f} m"
            if sigma <= LOW_SIGMA_M:
                spread = max(e.values()) / min(e.values()) - 1  # type: ignore[type-var, operator]
                out.append(
                    (
                        f"{loop} sigma={sigma:g}: the three within {AGREEMENT:.0%} (spread {spread:.0%})",
                        spread <= AGREEMENT,
                        figures,
                    )
                )
            if sigma >= HIGH_SIGMA_M:
                out.append((f"{loop} sigma={sigma:g}: flatness MPC worse than PD", mpc > pd, figures))
                out.append((f"{loop} sigma={sigma:g}: discrete flatness better than both", df < min(pd, mpc), figures))
    return out


def plot(rows: Sequence[SweepRow], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loops = list(dict.fromkeys(r.loop for r in rows))
    fig, axes = plt.subplots(1, len(loops), figsize=(5.5 * len(loops), 4.2), squeeze=False, sharey=True)
    for ax, loop in zip(axes[0], loops, strict=True):
        for c in CONTROLLERS:
            rs = sorted((r for r in rows if r.loop == loop and r.controller == c), key=lambda r: r.sigma_m)
            if rs:
                ax.errorbar(
                    [r.sigma_m for r in rs],
                    [r.mean_error_m for r in rs],
                    yerr=[r.std_error_m for r in rs],
                    color=COLORS[c],
                    label=LABELS[c],
                    marker="o",
                    capsize=3,
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("position noise sigma (m)")
        ax.set_title({"perfect": "noisy positions at 50 Hz", "estimator": "smoother in the loop (10 Hz)"}[loop])
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("mean tracking error (m)")
    axes[0][0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for results.csv and error_vs_sigma.png")
    ap.add_argument("--trials", type=int, default=10, help="runs per controller and sigma (default 10)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise draws (default 0)")
    ap.add_argument(
        "--sigmas",
        type=floats,
        default=list(DEFAULT_SIGMAS_M),
        help="position noise levels in m, comma-separated (default %(default)s)",
    )
    ap.add_argument("--loops", type=names(LOOPS), default=list(LOOPS), help="perfect,estimator (default both)")
    ap.add_argument("--calibrate", action="store_true", help="re-derive and print the tuning, then sweep with it")
    ap.add_argument(
        "--estimator-derivatives",
        choices=("finite_difference", "estimator"),
        default="finite_difference",
        help="estimator loop: PD's and the MPC's velocity and acceleration (default %(default)s)",
    )
    ap.add_argument(
        "--estimator-inputs",
        choices=("prior", "extrapolation"),
        default="prior",
        help="estimator loop: where the smoother uses the commands sent (default %(default)s)",
    )
    args = ap.parse_args(argv)
    try:
        settings = DiscreteFlatnessSettings(
            estimator_derivatives=args.estimator_derivatives, estimator_inputs=args.estimator_inputs
        )
        if args.calibrate:
            say("calibrating (noiseless, perfect loop) ...")
            settings = calibrate(settings)
            say(
                f"calibrated: pd_kp={settings.pd_kp:.4g} pd_kd={settings.pd_kd:.4g} "
                f"r_command_flatness_mpc={settings.r_command_flatness_mpc:.3g} "
                f"r_jerk_discrete_flatness={settings.r_jerk_discrete_flatness:.3g}; noiseless errors "
                + ", ".join(f"{c} {noiseless_error_m(settings, c):.4f} m" for c in CONTROLLERS)
            )
        if args.out.exists() and not args.out.is_dir():
            raise VtrError(f"--out {args.out}: exists and is not a folder")
        args.out.mkdir(parents=True, exist_ok=True)
        started = time.perf_counter()
        total = len(args.loops) * len(args.sigmas) * len(CONTROLLERS)
        done = [0]

        def progress(r: SweepRow) -> None:
            done[0] += 1
            say(
                f"[{done[0]}/{total}] {r.loop} sigma={r.sigma_m:g} {r.controller}: mean error "
                f"{r.mean_error_m:.4f} m (std {r.std_error_m:.4f}, {r.trials} trials, "
                f"{time.perf_counter() - started:.0f} s)"
            )

        rows = sweep(settings, args.sigmas, args.trials, args.seed, loops=args.loops, progress=progress)
        write_results_csv(args.out / "results.csv", rows)
        plot(rows, args.out / "error_vs_sigma.png")
    except VtrError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(
        f"{len(rows)} rows in {time.perf_counter() - started:.0f} s -> {args.out / 'results.csv'}, "
        f"{args.out / 'error_vs_sigma.png'}"
    )
    print("Fig. 8.2 ordering:")
    for claim, holds, figures in ordering(rows):
        print(f"  {'holds' if holds else 'FAILS'}  {claim}:  {figures}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
