"""Horizon evaluation benchmark: N = 15 steps x 800 landmarks, every step against its own trunk.

usage: python tools/bench_horizon.py [--repeats 2000]

Times ``HorizonEvaluator.evaluate`` (value and gradient w.r.t. position, yaw and optical axis) for
15 steps on 15 different trunks of 800 landmarks each, the same without gradient, the trunk
selection of a 15-step horizon (``TaughtPathField.select_trunks``, localizer's rule) and, for
reference, one single-trunk ``PerceptionConstraint`` over 15 steps. Prints medians and 90th
percentiles (milliseconds); the machine may be shared, so run it twice.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from perception_model import frames
from perception_model.constraint import PerceptionConstraint
from perception_model.horizon import HorizonEvaluator, TrunkLandmarks
from perception_model.model import PerceptionModel
from vtr.control.field import TaughtPathField, TaughtVertex

N_STEPS = 15
N_LANDMARKS = 800


def _time(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm (numba compile on first use)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1e3), float(np.percentile(ts, 90) * 1e3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2000)
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
        ("trunk selection, 15 steps", _time(lambda: field.select_trunks(pos, yaw - math.pi / 2, 0),
                                            args.repeats // 4)),
        ("single-trunk PerceptionConstraint (15 x 800)", _time(lambda: single.evaluate(pos - pos.mean(0), yaw),
                                                               args.repeats)),
    ]
    for name, (med, p90) in rows:
        print(f"{name:48s} median {med:6.3f} ms   p90 {p90:6.3f} ms")


if __name__ == "__main__":
    main()
