"""Benchmark of the perception chance constraint, and the normal-vs-exact-vs-Monte-Carlo table.

Times ``PerceptionConstraint.evaluate`` (values + analytic gradients w.r.t. position and yaw) for
an MPC horizon of N steps against M landmarks (default 15 x 800, the thesis setting), single
threaded, and prints median / min / p90 latency in milliseconds over many repetitions. Then, for
the same 800-landmark scene and a range of lateral offsets from the taught path, prints the
failure probability P(L < L_min) from the normal approximation (with and without continuity
correction), the exact Poisson-binomial distribution (recursion and DFT) and Monte Carlo.

Usage:  python tools/bench_constraint.py [--reps 2000] [--mc-samples 200000] [--no-table]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from perception_model.constraint import PerceptionConstraint, compare_tails  # noqa: E402
from perception_model.model import PerceptionModel  # noqa: E402
from perception_model.synthetic import ground_scene  # noqa: E402

#: Benchmark defaults (thesis §7.4: N = 15, L_min = 30, c_bar = 3, ~600-800 landmarks per trunk).
HORIZON = 15
LANDMARKS = 800
REPS = 2000
WARMUP = 50
SEED = 7
TARGET_MS = 1.0
STEP_M = 0.3  # spacing of horizon positions along the path (3 m/s at 10 Hz)
MAX_LATERAL_M = 2.0
MAX_YAW_DEV_RAD = math.radians(10.0)
TABLE_OFFSETS_M = (0.0, 2.0, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0)
MC_SAMPLES = 200_000
MS_PER_NS = 1e-6


def horizon(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """N camera positions moving forward with a lateral/vertical wobble, and yaws near 0."""
    k = np.arange(n)
    pos = np.column_stack([k * STEP_M, MAX_LATERAL_M * np.sin(0.3 * k), 0.2 * np.cos(0.5 * k)])
    yaw = rng.uniform(-MAX_YAW_DEV_RAD, MAX_YAW_DEV_RAD, n)
    return pos, yaw


def time_calls(fn, reps: int) -> np.ndarray:
    """Latency of each of ``reps`` calls in ms (after a warm-up)."""
    for _ in range(WARMUP):
        fn()
    out = np.empty(reps)
    for i in range(reps):
        t0 = time.perf_counter_ns()
        fn()
        out[i] = (time.perf_counter_ns() - t0) * MS_PER_NS
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=REPS)
    ap.add_argument("--horizon", type=int, default=HORIZON)
    ap.add_argument("--landmarks", type=int, default=LANDMARKS)
    ap.add_argument("--mc-samples", type=int, default=MC_SAMPLES)
    ap.add_argument("--no-table", action="store_true", help="skip the tail-probability table")
    args = ap.parse_args()

    rng = np.random.default_rng(SEED)
    model = PerceptionModel.thesis()
    scene = ground_scene(args.landmarks, rng)
    con = PerceptionConstraint(model, scene.landmarks)
    pos, yaw = horizon(rng, args.horizon)

    full = time_calls(lambda: con.evaluate(pos, yaw), args.reps)
    value = time_calls(lambda: con.evaluate(pos, yaw, gradient=False), args.reps)
    lin = time_calls(lambda: con.linearize(pos, yaw), args.reps)
    print(
        f"perception constraint: N = {args.horizon} steps x M = {args.landmarks} landmarks, "
        f"single thread, {args.reps} reps (numpy {np.__version__})"
    )
    print(f"{'call':34s} {'median ms':>10s} {'min ms':>8s} {'p90 ms':>8s}")
    for name, t in (
        ("evaluate (value + gradients)", full),
        ("evaluate (value only)", value),
        ("linearize (value + gradient, g)", lin),
    ):
        print(f"{name:34s} {np.median(t):10.3f} {t.min():8.3f} {np.percentile(t, 90):8.3f}")
    verdict = "meets" if np.median(full) <= TARGET_MS else "misses"
    print(f"target <= {TARGET_MS} ms (value + gradient): median {verdict} it")

    if args.no_table:
        return
    print()
    print(
        f"P(L < L_min), L_min = {con.l_min:g}, {args.landmarks} landmarks, camera offset sideways from the "
        f"taught camera (thesis scene: {scene.altitude:g} m altitude, pitched "
        f"{math.degrees(scene.pitch_down):g} deg down); Monte Carlo {args.mc_samples} samples"
    )
    head = (
        f"{'offset m':>8s} {'mu':>7s} {'sigma':>6s} {'g=mu-3s-L':>9s} {'normal':>10s} {'normal+cc':>10s} "
        f"{'exact':>10s} {'exact DFT':>10s} {'Monte Carlo':>11s} {'MC s.e.':>9s}"
    )
    print(head)
    mc_rng = np.random.default_rng(SEED + 1)
    for off in TABLE_OFFSETS_M:
        p = con.probabilities(np.array([[0.0, off, 0.0]]), np.array([scene.yaw]))[0]
        t = compare_tails(p, con.l_min, n_samples=args.mc_samples, rng=mc_rng)
        g = t.mu - con.c_bar * t.sigma - con.l_min
        print(
            f"{off:8.1f} {t.mu:7.1f} {t.sigma:6.2f} {g:9.2f} {t.normal:10.3e} {t.normal_continuity:10.3e} "
            f"{t.exact:10.3e} {t.exact_dft:10.3e} {t.monte_carlo:11.3e} {t.monte_carlo_se:9.1e}"
        )


if __name__ == "__main__":
    main()
