"""Closed-loop repeat simulation of the flatness-based MPC on a taught path (thesis §7.4 protocol).

The plant is the flat model itself (:mod:`vtr.control.flat_model`, exact integration of the held
input over each 50 Hz tick) and the **measurement model is the perception model**: at every tick
the vehicle's trunk follows the localizer's rule from the previous one, and ``mu``, ``sigma`` of
the inlier count come from :class:`vtr.control.field.TaughtPathField` at the flown pose. No image
is rendered in the loop (as in the thesis' simulation); the taught map and the model it uses are
real (taught and fitted through the pipeline). The route is flown in the MPC reference's direction
(``TaughtPathReference.direction``: -1 flies it back, from its taught end); path errors, progress and the end
are counted along travel, and the trunk follows the localizer's rule in that direction.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..config import ControlConfig
from .field import TaughtPathField
from .flat_model import N_STATE, step
from .mpc import PerceptionAwareMPC, TaughtPathReference

#: The run ends when the vehicle is this close (m, along the path) to the end of the taught path.
END_TOLERANCE_M = 1.0
#: ... or after this many times the path length at the desired speed.
TIME_LIMIT_FACTOR = 6.0


@dataclass(frozen=True)
class ClosedLoopResult:
    """One closed-loop repeat: per tick arrays (K,) / (K, 10) and the summary."""

    t_s: np.ndarray
    z: np.ndarray
    trunk: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray
    bound: np.ndarray  # mu - c_bar sigma
    lateral_m: np.ndarray  # left of travel
    vertical_m: np.ndarray
    max_slack_m: np.ndarray  # per tick: fixed path rows (m)
    max_slack_inliers: np.ndarray  # per tick: perception rows (inliers)
    flag: np.ndarray  # the field's flag at the flown pose (perception_model.horizon)
    tick_ms: np.ndarray
    completed: bool
    duration_s: float
    path_length_m: float
    direction: int = 1

    @property
    def avg_speed_mps(self) -> float:
        """Taught path length over the time to fly it (0 if the run did not finish)."""
        return self.path_length_m / self.duration_s if self.completed and self.duration_s > 0 else 0.0

    @property
    def min_bound(self) -> float:
        return float(self.bound.min())


def initial_state(field: TaughtPathField, index: int = 0) -> np.ndarray:
    """Hover at taught vertex ``index`` (negative: from the end, -1 the last) with its taught yaw (flat state
    (10,)); add pi to ``z[9]`` to face the other way."""
    z = np.zeros(N_STATE)
    z[:3] = field.vehicle_position_g[index]
    z[9] = field.vehicle_yaw_g[index]
    return z


def simulate(
    field: TaughtPathField,
    mpc: PerceptionAwareMPC,
    z0: np.ndarray,
    config: ControlConfig | None = None,
    *,
    time_limit_s: float | None = None,
) -> ClosedLoopResult:
    """Fly the taught path from flat state ``z0`` with ``mpc`` until its end in the direction of travel (see
    the module docstring)."""
    c = config or mpc.cfg
    ref: TaughtPathReference = mpc.reference
    dt = 1.0 / c.rate_hz
    limit = time_limit_s if time_limit_s is not None else TIME_LIMIT_FACTOR * ref.length / c.speed_mps
    z = np.asarray(z0, float).copy()
    trunk = field.nearest_trunk(z[:3])
    rows_t, rows_z, rows_tr, rows_mu, rows_sig, rows_g, rows_f = [], [], [], [], [], [], []
    slack_m, slack_in, tick = [], [], []
    t = 0.0
    completed = False
    camera = mpc.field_kwargs(1)
    while t <= limit:
        trunk = int(field.select_trunks(z[None, :3], z[9:10], trunk, direction=mpc.direction, **camera)[0])
        ev = field.evaluate(z[None, :3], z[9:10], trunk=np.array([trunk]), gradient=False, **camera)
        rows_t.append(t)
        rows_z.append(z.copy())
        rows_tr.append(trunk)
        rows_mu.append(float(ev.mu[0]))
        rows_sig.append(float(ev.sigma[0]))
        rows_g.append(float(ev.mu[0] - c.c_bar * ev.sigma[0]))
        rows_f.append(int(ev.flag[0]))
        if float(ref.path.error(z[:3]).along_track) >= ref.length - END_TOLERANCE_M:
            completed = True
            break
        t0 = time.perf_counter()
        sol = mpc.solve(z, trunk)
        tick.append((time.perf_counter() - t0) * 1e3)
        slack_m.append(sol.max_slack_m)
        slack_in.append(sol.max_slack_inliers)
        z = step(z, sol.w, dt)
        t += dt
    Z = np.array(rows_z)
    err = ref.path.error(Z[:, :3])
    return ClosedLoopResult(
        t_s=np.array(rows_t),
        z=Z,
        trunk=np.array(rows_tr, dtype=np.int64),
        mu=np.array(rows_mu),
        sigma=np.array(rows_sig),
        bound=np.array(rows_g),
        lateral_m=np.asarray(err.lateral),
        vertical_m=np.asarray(err.vertical),
        max_slack_m=np.array(slack_m),
        max_slack_inliers=np.array(slack_in),
        flag=np.array(rows_f, dtype=np.int8),
        tick_ms=np.array(tick),
        completed=completed,
        duration_s=float(rows_t[-1]),
        path_length_m=ref.length,
        direction=mpc.direction,
    )


__all__ = ["ClosedLoopResult", "initial_state", "simulate"]
