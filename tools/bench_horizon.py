"""Horizon evaluation benchmark: N = 15 steps x 800 landmarks, every step against its own trunk.

usage: python tools/bench_horizon.py [--repeats 2000] [--route-vertices 300] [--no-odometry]

Times ``HorizonEvaluator.evaluate`` (value and gradient w.r.t. position, yaw and optical axis) for
15 steps on 15 different trunks of 800 landmarks each, the same without gradient, the trunk
selection of a 15-step horizon (``TaughtPathField.select_trunks``, localizer's rule) and, for
reference, one single-trunk ``PerceptionConstraint`` over 15 steps. Then the constraint a control tick asks for
(``TaughtPathField.evaluate`` from the previous trunk, as ``OnlineRepeat.constraint``: trunk selection, the route's
distances and the horizon) on a straight route of ``--route-vertices`` vertices 1 m apart (camera 90 degrees to the
side, 800 landmarks each), horizons of 15 steps 0.5 m apart from 50 random places, and, unless ``--no-odometry``, that
tick's median as a fraction of one odometry frame (stereo + odometry on datasets/kitti06_clip, median over 20
frames, measured in the same run: the yardstick of tools/bench_online.py). Prints medians and 90th percentiles
(milliseconds); the machine may be shared, so run it twice.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from perception_model import frames
from perception_model.constraint import PerceptionConstraint
from perception_model.horizon import HorizonEvaluator, TrunkLandmarks
from perception_model.model import PerceptionModel
from vtr.config import Config
from vtr.control.field import CameraMount, TaughtPathField, TaughtVertex
from vtr.io import open_source
from vtr.vo.odometry import OdometrySettings, StereoOdometry

N_STEPS = 15
N_LANDMARKS = 800
KITTI06 = Path(__file__).resolve().parents[1] / "datasets" / "kitti06_clip"


def _time(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm (numba compile on first use)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1e3), float(np.percentile(ts, 90) * 1e3)


def odometry_frame_ms() -> float:
    """Median ms of one kitti06 frame through stereo + odometry alone (odd frames 1..39, the first two skipped)."""
    with open_source(KITTI06) as src:
        images = [src[i] for i in range(1, 40, 2)]
        odo = StereoOdometry(src.camera, OdometrySettings.of(Config()), keep_history=False)
    times = []
    for im in images:
        t0 = time.perf_counter()
        odo.process_frame(odo.stereo.process(im))
        times.append(time.perf_counter() - t0)
    return 1000 * float(np.median(times[2:]))


def route_constraint(n_vertices: int, model: PerceptionModel, repeats: int) -> tuple[float, float]:
    """Median and p90 ms of a 15-step ``TaughtPathField.evaluate`` from the previous trunk on a long route."""
    rng = np.random.default_rng(1)
    pitch = math.radians(50.0)
    verts = []
    for i in range(n_vertices):
        T = np.eye(4)
        T[:3, :3] = frames.camera_rotation(0.0, pitch, math.pi / 2)
        T[:3, 3] = (1.0 * i, 0.0, 12.0)
        lm_o = rng.uniform([-12.0, 6.0, -13.0], [12.0, 25.0, -9.0], (N_LANDMARKS, 3))
        verts.append(TaughtVertex(i, T, lm_o + T[:3, 3]))
    field = TaughtPathField(model, verts, T_g_map=np.eye(4), mount=CameraMount(math.pi / 2, np.zeros(3)))
    ticks = []
    for k in rng.integers(0, max(1, n_vertices - 10), 50):
        start = field.vehicle_position_g[k] + rng.normal(0, 0.5, 3)
        pos = start + np.arange(N_STEPS)[:, None] * np.array([0.5, 0.0, 0.0])
        ticks.append((pos, np.zeros(N_STEPS), int(k)))
    state = {"i": 0}

    def tick() -> None:
        pos, yaw, k = ticks[state["i"] % len(ticks)]
        state["i"] += 1
        field.evaluate(pos, yaw, previous=k)

    return _time(tick, repeats)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2000)
    ap.add_argument("--route-vertices", type=int, default=300, help="vertices of the long route (default 300)")
    ap.add_argument("--no-odometry", action="store_true", help="skip the odometry frame yardstick")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    model = PerceptionModel.thesis()
    pitch = math.radians(50.0)
    trunks, verts = [], []
    for i in range(N_STEPS):
        c = np.array([1.0 * i, 0.0, 12.0])
        lm_o = rng.uniform([-12.0, 6.0, -13.0], [12.0, 25.0, -9.0], (N_LANDMARKS, 3))
        trunks.append(TrunkLandmarks(i, c, 0.0, np.zeros(3), lm_o, pitch))
        T = np.eye(4)
        T[:3, :3] = frames.camera_rotation(0.0, pitch, math.pi / 2)
        T[:3, 3] = c
        verts.append(TaughtVertex(i, T, lm_o + c))
    ev = HorizonEvaluator(model, trunks)
    tr = np.arange(N_STEPS)
    pos = ev.camera_centres_g() + rng.normal(0, 1.0, (N_STEPS, 3))
    yaw = np.full(N_STEPS, math.pi / 2) + rng.normal(0, 0.1, N_STEPS)
    out = ev.evaluate(pos, tr, yaw)
    assert np.all(out.mu > 0)
    field = TaughtPathField(model, verts, T_g_map=np.eye(4))
    single = PerceptionConstraint(model, trunks[0].landmarks_o, pitch_down=pitch)
    rows = [
        ("horizon value+gradient (15 trunks x 800)", _time(lambda: ev.evaluate(pos, tr, yaw), args.repeats)),
        ("horizon value only", _time(lambda: ev.evaluate(pos, tr, yaw, gradient=False), args.repeats)),
        ("trunk selection, 15 steps", _time(lambda: field.select_trunks(pos, yaw - math.pi / 2, 0), args.repeats // 4)),
        (
            "single-trunk PerceptionConstraint (15 x 800)",
            _time(lambda: single.evaluate(pos - pos.mean(0), yaw), args.repeats),
        ),
    ]
    tick = route_constraint(args.route_vertices, model, args.repeats // 4)
    rows.append((f"constraint per tick ({args.route_vertices}-vertex route)", tick))
    for name, (med, p90) in rows:
        print(f"{name:48s} median {med:6.3f} ms   p90 {p90:6.3f} ms")
    if not args.no_odometry:
        odo = odometry_frame_ms()
        print(f"{'odometry frame (kitti06, stereo + odometry)':48s} median {odo:6.2f} ms")
        print(f"{'constraint per tick / odometry frame':48s} {tick[0] / odo:.3f} (median; p90 {tick[1] / odo:.3f})")


if __name__ == "__main__":
    main()
