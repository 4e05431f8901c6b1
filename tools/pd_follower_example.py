"""Baseline PD path follower (thesis §6.3.4, eqs. 6.3-6.6) driven by the controller-facing API.

Pure kinematics, no images: a multirotor repeats an L-shaped taught route at 10 m height. "Vision"
is simulated as noisy poses ``T_world_vehicle`` at 15 Hz fed to :class:`vtr.state.smoothing.TrajectorySmoother`;
the controller runs at 50 Hz and each tick

1. queries the smoother now (``state_at``: extrapolation from the last keyframe),
2. finds the trunk (closest taught vertex, searched in a window around the previous trunk that reaches
   further ahead in the direction of travel: ``vtr.navigation.trunk.trunk_window``) and its pose from a
   simulated localization chain, ``T_world_trunk = T_world_leaf @ T_leaf_trunk``,
3. builds the gravity-aligned frame o at the trunk, the controller state ``z = (p, v, a, psi)`` and the
   reference path (straight segments through the next taught vertices *in the direction of travel*) in o,
4. projects the position on the path for ``p_ref``, sets ``v_ref = s_des * direction`` and applies the PD
   laws; commands ``(z_dot, psi_dot, theta, phi)`` drive the simulated vehicle (first-order attitude
   and climb-rate response).

The PD laws are written in the standard second-order form ``a = (p_ref - p)/tau² + 2 zeta (v_ref - v)/tau``
(the thesis text prints the two gains of eqs. 6.3/6.5 swapped, which is not dimensionally consistent);
the climb-rate command of eq. 6.3 is ``z_dot_ref + (2 zeta_z / tau_z)(z_ref - z)``.

``--direction backward`` flies the route back from its taught end (the return flight): the window, the
look-ahead and the remaining distance count along travel, and the yaw law holds the trunk's taught yaw (the
vehicle flies tail first, as the MPC's ``yaw_reference = "as_taught"``); lateral errors are left of travel.

Prints path-tracking error statistics (true position against the taught path) and the smoother's
estimation error. Runs in a few seconds:
``python tools/pd_follower_example.py [--speed 3] [--seed 0] [--direction forward|backward]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from vtr.config import SmoothingConfig
from vtr.conventions import NS_PER_S
from vtr.geometry import exp_se3, inv_T, make_T
from vtr.navigation.trunk import BACKWARD, FORWARD, trunk_window
from vtr.state.controller import ReferencePath, controller_state, gravity_aligned_T_o_t, trunk_in_world
from vtr.state.smoothing import TrajectorySmoother

G = 9.81  # m/s²
# Route and run
ALTITUDE_M = 10.0
ROUTE_CORNERS = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 30.0]])  # m, world (ENU) x-y
VERTEX_SPACING_M = 1.0  # taught (privileged) vertex every metre
START_OFFSET = np.array([0.0, 1.0, -0.5])  # m, initial offset from the first vertex (left, down)
GOAL_TOLERANCE_M = 0.5  # stop when this close to the end along the path
MAX_TIME_S = 60.0
# Rates
VISION_HZ = 15.0
CONTROL_HZ = 50.0
SIM_SUBSTEPS = 4  # integration steps per control tick
# Vision noise (per axis) and its covariance as told to the smoother
VISION_SIGMA_ROT = 0.005  # rad
VISION_SIGMA_TRANS = 0.02  # m
# Trunk search window (VT&R3: -10...+20 vertices) and look-ahead of the reference path
TRUNK_WINDOW_BACK, TRUNK_WINDOW_FORWARD = 10, 20
PATH_LOOKAHEAD_VERTICES = 5
# PD gains (eqs. 6.3-6.5)
ZETA_Z, TAU_Z = 1.0, 1.0
TAU_PSI = 1.0
ZETA_THETA, TAU_THETA = 1.0, 1.2
MAX_TILT_RAD = np.radians(25.0)
# Vehicle response
TAU_ATTITUDE_S = 0.08  # roll/pitch follow their commands with this lag
TAU_CLIMB_S = 0.2  # climb rate follows its command with this lag
LINEAR_DRAG = 0.1  # 1/s, horizontal
ARRIVAL_DECEL = 0.6  # m/s per m remaining: slow down before the end


def taught_vertices() -> np.ndarray:
    """Privileged vertex poses T_world_v (N, 4, 4): level, x axis along the route."""
    poses = []
    for a, b in zip(ROUTE_CORNERS[:-1], ROUTE_CORNERS[1:], strict=True):
        d = b - a
        length = np.linalg.norm(d)
        yaw = np.arctan2(d[1], d[0])
        for s in np.arange(0.0, length, VERTEX_SPACING_M):
            xy = a + d * s / length
            poses.append(make_T(Rotation.from_euler("z", yaw).as_matrix(), [xy[0], xy[1], ALTITUDE_M]))
    last = ROUTE_CORNERS[-1]
    poses.append(make_T(poses[-1][:3, :3], [last[0], last[1], ALTITUDE_M]))
    return np.stack(poses)


class Vehicle:
    """Kinematic multirotor: position, velocity, yaw, roll/pitch with first-order response."""

    def __init__(self, p: np.ndarray, yaw: float) -> None:
        self.p = np.array(p, float)
        self.v = np.zeros(3)
        self.yaw, self.pitch, self.roll = yaw, 0.0, 0.0

    def pose(self) -> np.ndarray:
        """T_world_vehicle (FLU vehicle frame, ENU world)."""
        R = Rotation.from_euler("ZYX", [self.yaw, self.pitch, self.roll]).as_matrix()
        return make_T(R, self.p)

    def step(self, dt: float, z_dot_cmd: float, yaw_rate_cmd: float, pitch_cmd: float, roll_cmd: float) -> None:
        self.pitch += (pitch_cmd - self.pitch) * dt / TAU_ATTITUDE_S
        self.roll += (roll_cmd - self.roll) * dt / TAU_ATTITUDE_S
        self.yaw += yaw_rate_cmd * dt
        # inverse of eq. 6.6: forward/left acceleration from pitch/roll, rotated by yaw
        a_fwd, a_left = G * np.sin(self.pitch), -G * np.sin(self.roll)
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        a_xy = np.array([c * a_fwd - s * a_left, s * a_fwd + c * a_left]) - LINEAR_DRAG * self.v[:2]
        self.v[:2] += a_xy * dt
        self.v[2] += (z_dot_cmd - self.v[2]) * dt / TAU_CLIMB_S
        self.p += self.v * dt


def wrap(a: float) -> float:
    return (a + np.pi) % (2 * np.pi) - np.pi


def run(speed: float, seed: int, direction: int = FORWARD) -> dict[str, np.ndarray | float]:
    rng = np.random.default_rng(seed)
    verts = taught_vertices()
    travel = np.arange(len(verts)) if direction == FORWARD else np.arange(len(verts))[::-1]
    full_path_world = ReferencePath(verts[travel, :3, 3])  # in the order of travel
    first = int(travel[0])
    start = verts[first] @ make_T(np.eye(3), START_OFFSET)
    veh = Vehicle(start[:3, 3], yaw=float(np.arctan2(verts[first, 1, 0], verts[first, 0, 0])))
    vision_cov = np.diag([VISION_SIGMA_ROT**2] * 3 + [VISION_SIGMA_TRANS**2] * 3)
    smoother = TrajectorySmoother(SmoothingConfig())
    dt_ctrl_ns = int(NS_PER_S / CONTROL_HZ)
    vision_period_ns = int(NS_PER_S / VISION_HZ)
    t_ns, next_vision_ns = 0, 0
    trunk = first
    leaf_t_ns, T_world_leaf_meas = None, None
    log = {k: [] for k in ("lateral", "vertical", "est_err", "speed", "ctrl_us")}
    while t_ns < MAX_TIME_S * NS_PER_S:
        # -- vision keyframes
        while next_vision_ns <= t_ns:
            noise = np.r_[rng.normal(0, VISION_SIGMA_ROT, 3), rng.normal(0, VISION_SIGMA_TRANS, 3)]
            T_meas = veh.pose() @ exp_se3(noise)
            smoother.add_pose(next_vision_ns, T_meas, vision_cov)
            leaf_t_ns, T_world_leaf_meas = next_vision_ns, T_meas
            next_vision_ns += vision_period_ns
        c0 = time.perf_counter()
        # -- controller tick
        state = smoother.state_at(t_ns)
        lo, hi = trunk_window(trunk, len(verts), TRUNK_WINDOW_BACK, TRUNK_WINDOW_FORWARD, direction)
        trunk = lo + int(np.argmin(np.linalg.norm(verts[lo:hi, :3, 3] - state.position, axis=1)))
        # simulated localization chain at the leaf: T_leaf_trunk as localization would estimate it
        T_leaf_trunk = inv_T(T_world_leaf_meas) @ verts[trunk]
        T_world_leaf = smoother.state_at(leaf_t_ns, with_covariance=False).pose
        T_world_trunk = trunk_in_world(T_world_leaf, T_leaf_trunk)
        T_o_t = gravity_aligned_T_o_t(T_world_trunk[:3, :3])
        # the previous vertex and the next ones, in the direction of travel
        if direction == FORWARD:
            ahead = verts[max(0, trunk - 1) : trunk + PATH_LOOKAHEAD_VERTICES + 1]
        else:
            ahead = verts[max(0, trunk - PATH_LOOKAHEAD_VERTICES) : trunk + 2][::-1]
        path = ReferencePath.from_world(ahead, T_world_trunk, T_o_t)
        cs = controller_state(state, T_world_trunk, T_o_t)
        err = path.error(cs.position)
        remaining = full_path_world.length - full_path_world.error(state.position).along_track
        if remaining < GOAL_TOLERANCE_M:
            break
        s_des = min(speed, ARRIVAL_DECEL * remaining)
        p_ref, v_ref = err.reference_point, s_des * err.direction
        # eq. 6.3 (climb rate), 6.4 (yaw rate; psi_ref = trunk yaw in o = 0), 6.5 (lateral PD), 6.6
        z_dot_cmd = v_ref[2] + 2 * ZETA_Z / TAU_Z * (p_ref[2] - cs.position[2])
        yaw_rate_cmd = wrap(0.0 - cs.yaw) / TAU_PSI
        a_xy = (p_ref[:2] - cs.position[:2]) / TAU_THETA**2 + 2 * ZETA_THETA / TAU_THETA * (v_ref[:2] - cs.velocity[:2])
        a_xy = a_xy + LINEAR_DRAG * cs.velocity[:2]  # feed-forward of the known drag
        psi = cs.yaw
        sin_theta = np.clip(a_xy[0] / G * np.cos(psi) + a_xy[1] / G * np.sin(psi), -1, 1)
        sin_phi = np.clip(-a_xy[0] / G * np.sin(psi) + a_xy[1] / G * np.cos(psi), -1, 1)
        theta_cmd = np.clip(np.arcsin(sin_theta), -MAX_TILT_RAD, MAX_TILT_RAD)
        phi_cmd = np.clip(-np.arcsin(sin_phi), -MAX_TILT_RAD, MAX_TILT_RAD)
        log["ctrl_us"].append((time.perf_counter() - c0) * 1e6)
        # -- log true tracking error and estimation error
        true_err = full_path_world.error(veh.p)
        log["lateral"].append(true_err.lateral)
        log["vertical"].append(true_err.vertical)
        log["est_err"].append(np.linalg.norm(state.position - veh.p))
        log["speed"].append(np.linalg.norm(veh.v))
        # -- simulate until the next tick (pitch/roll act along the vehicle's own heading, so the
        #    commands computed in o apply unchanged in world)
        for _ in range(SIM_SUBSTEPS):
            veh.step(1.0 / CONTROL_HZ / SIM_SUBSTEPS, z_dot_cmd, yaw_rate_cmd, theta_cmd, phi_cmd)
        t_ns += dt_ctrl_ns
    out = {k: np.asarray(v) for k, v in log.items()}
    out["time_s"] = t_ns / NS_PER_S
    out["remaining_m"] = float(remaining)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=3.0, help="desired speed s_des (m/s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--direction",
        choices=("forward", "backward"),
        default="forward",
        help="fly the route in taught order or back from its end",
    )
    args = ap.parse_args()
    wall = time.perf_counter()
    r = run(args.speed, args.seed, FORWARD if args.direction == "forward" else BACKWARD)
    settle = r["time_s"] > 0 and slice(int(CONTROL_HZ * 3), None)  # skip the initial offset transient

    def stats(name: str, a: np.ndarray, unit: str) -> None:
        a = np.abs(a)
        print(
            f"  {name:28s} mean {a.mean():6.3f}  rms {np.sqrt(np.mean(a**2)):6.3f}  "
            f"p95 {np.percentile(a, 95):6.3f}  max {a.max():6.3f} {unit}"
        )

    print(
        f"PD path follower ({args.direction}) at s_des = {args.speed} m/s, vision {VISION_HZ:.0f} Hz, "
        f"control {CONTROL_HZ:.0f} Hz"
    )
    print(
        f"route {ROUTE_CORNERS.tolist()} at {ALTITUDE_M} m; finished in {r['time_s']:.1f} s simulated "
        f"({r['remaining_m']:.2f} m from the end), {time.perf_counter() - wall:.1f} s wall"
    )
    print("true path-tracking error after the first 3 s:")
    stats("lateral", r["lateral"][settle], "m")
    stats("vertical", r["vertical"][settle], "m")
    print("smoother (extrapolated to the control time):")
    stats("position estimation error", r["est_err"], "m")
    stats("ground speed", r["speed"][settle], "m/s")
    stats("controller tick time", r["ctrl_us"], "us")


if __name__ == "__main__":
    main()
