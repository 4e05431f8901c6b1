"""Benchmark of the WNOA trajectory smoother: update cost per keyframe over a long run, query latency.

Feeds a synthetic noisy trajectory at 15 Hz keyframes into :class:`vtr.state.smoothing.TrajectorySmoother`
(default config: 5 s lag, so ~75 knots in the window) and reports:

* the time of ``add_pose`` around keyframe 100, 1000 and 10 000 (median and mean over a block of
  keyframes, CPU time of the thread and wall time) - it should stay flat because the fixed-lag window
  bounds the problem. On a shared machine the speed itself drifts: a fixed reference workload is
  timed at each checkpoint so the figures can be compared;
* the latency of ``state_at`` (median, single thread) for controller-like queries: interpolation
  inside the last segment and extrapolation after the last keyframe, with and without covariance.

Usage: ``python tools/bench_smoother.py [--keyframes 10000] [--queries 5000]`` (a few minutes at most).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from vtr.config import SmoothingConfig  # noqa: E402
from vtr.geometry import exp_se3  # noqa: E402
from vtr.state.smoothing import TrajectorySmoother  # noqa: E402

KEYFRAME_PERIOD_NS = 66_666_667  # 15 Hz
CONTROL_PERIOD_NS = 20_000_000  # 50 Hz
CHECKPOINTS = (100, 1000, 10_000)
BLOCK = 25  # keyframes averaged before each checkpoint (window full)
NOISE_ROT, NOISE_TRANS = 0.002, 0.01  # rad, m
SEED = 0
CIRCLE_RADIUS, CIRCLE_RATE = 10.0, 0.3  # m, rad/s
REFERENCE_SIZE, REFERENCE_REPEATS = 60, 20  # fixed workload timed next to each checkpoint


def trajectory(t: float) -> np.ndarray:
    """T_world_sensor of a circling flight (3 m/s, 10 m radius) with height and attitude oscillations.

    Statistically stationary, so keyframe 100 and keyframe 10 000 pose the same problem.
    """
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler(
        "ZYX", [CIRCLE_RATE * t + np.pi / 2, 0.05 * np.sin(1.3 * t), 0.1 * np.sin(2.0 * t)]
    ).as_matrix()
    T[:3, 3] = [
        CIRCLE_RADIUS * np.cos(CIRCLE_RATE * t),
        CIRCLE_RADIUS * np.sin(CIRCLE_RATE * t),
        10.0 + 2.0 * np.sin(0.3 * t),
    ]
    return T


def reference_workload_ms() -> float:
    """CPU time (ms) of a fixed numpy workload: a load indicator on a shared machine."""
    A = np.random.default_rng(SEED).normal(size=(REFERENCE_SIZE, REFERENCE_SIZE))
    a = time.thread_time()
    for _ in range(REFERENCE_REPEATS):
        np.linalg.inv(A)
    return (time.thread_time() - a) * 1e3


def run(n_keyframes: int, n_queries: int) -> None:
    rng = np.random.default_rng(SEED)
    cov = np.diag([NOISE_ROT**2] * 3 + [NOISE_TRANS**2] * 3)
    sm = TrajectorySmoother(SmoothingConfig())
    update_s = np.zeros(n_keyframes)  # wall time
    update_cpu = np.zeros(n_keyframes)  # CPU time of this thread (gtsam runs in it: no TBB in the wheel)
    reference = {}
    t_start = time.perf_counter()
    for k in range(n_keyframes):
        t_ns = k * KEYFRAME_PERIOD_NS
        M = trajectory(t_ns * 1e-9) @ exp_se3(np.r_[rng.normal(0, NOISE_ROT, 3), rng.normal(0, NOISE_TRANS, 3)])
        a, a_cpu = time.perf_counter(), time.thread_time()
        sm.add_pose(t_ns, M, cov)
        update_s[k] = time.perf_counter() - a
        update_cpu[k] = time.thread_time() - a_cpu
        if k + 1 in CHECKPOINTS:
            reference[k + 1] = reference_workload_ms()
    total = time.perf_counter() - t_start
    print(
        f"fed {n_keyframes} keyframes at 15 Hz in {total:.1f} s; window {sm.config.lag_s} s "
        f"(~{int(sm.config.lag_s * 1e9 / KEYFRAME_PERIOD_NS)} knots)"
    )
    print("update cost per keyframe (add_pose: ISAM2 update + refinement + cache refresh), ms:")
    for c in CHECKPOINTS:
        if c > n_keyframes:
            continue
        lo = max(0, c - BLOCK)
        wall, cpu = update_s[lo:c] * 1e3, update_cpu[lo:c] * 1e3
        print(
            f"  keyframes {lo:6d}-{c:6d}: CPU median {np.median(cpu):6.2f} mean {np.mean(cpu):6.2f} | "
            f"wall median {np.median(wall):6.2f} mean {np.mean(wall):6.2f} max {np.max(wall):6.2f} | "
            f"reference workload {reference[c]:5.2f}"
        )

    # Query latency, controller-like: times in the last segment and up to 0.2 s after the last keyframe.
    last = sm.last_time_ns
    offsets = rng.integers(-KEYFRAME_PERIOD_NS + 1, 10 * CONTROL_PERIOD_NS, size=n_queries)
    for label, with_cov in (("with covariance", True), ("pose/velocity/acceleration only", False)):
        for kind, sel in (("interpolated", offsets < 0), ("extrapolated", offsets > 0)):
            times = [int(last + o) for o in offsets[sel]]
            lat = np.zeros(len(times))
            cpu = np.zeros(len(times))
            for i, t in enumerate(times):
                a, a_cpu = time.perf_counter(), time.thread_time()
                sm.state_at(t, with_covariance=with_cov)
                lat[i] = time.perf_counter() - a
                cpu[i] = time.thread_time() - a_cpu
            print(
                f"state_at {kind:12s} {label:32s}: wall median {np.median(lat) * 1e6:6.1f} us "
                f"p99 {np.percentile(lat, 99) * 1e6:7.1f} us | CPU median {np.median(cpu) * 1e6:6.1f} us "
                f"({len(times)} queries)"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=max(CHECKPOINTS))
    ap.add_argument("--queries", type=int, default=5000)
    args = ap.parse_args()
    run(args.keyframes, args.queries)


if __name__ == "__main__":
    main()
