"""Linear flat model of a multirotor (flat outputs position and yaw), as the flatness-based MPC sees it.

Flat outputs ``y = (p, psi)`` (frame g, metres and radians; yaw as in ``perception_model.frames``).
The flat state is the controller state of ``vtr.state.controller``: ``z = (p, v, a, psi)`` (10,), and
the flat input ``w = (j, psi_dot)`` (4,): jerk (m/s^3) and yaw rate (rad/s). Position is a chain of
three integrators per axis and yaw one integrator (the Brunovsky form of the flat model), so the
discrete model with the input held over ``dt`` is exact: ``z+ = A z + B w``.

The inverse term of the flatness-based controller maps the flat state back to the inner-loop
commands: thrust direction ``a + g e_z`` gives roll and pitch (:func:`attitude_from_flat`);
``MpcConfig.accel_max_mps2`` keeps that tilt bounded.
"""

from __future__ import annotations

import math

import numpy as np

from perception_model.frames import rot_z

GRAVITY_MPS2 = 9.81
N_STATE = 10
N_INPUT = 4
P, V, A, YAW = slice(0, 3), slice(3, 6), slice(6, 9), 9


def discrete_model(dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(A (10, 10), B (10, 4))`` of the flat model with the input held over ``dt_s`` (exact)."""
    if not dt_s > 0.0:
        raise ValueError(f"dt_s must be positive, got {dt_s}")
    I3 = np.eye(3)
    Ad = np.eye(N_STATE)
    Ad[P, V] = dt_s * I3
    Ad[P, A] = 0.5 * dt_s**2 * I3
    Ad[V, A] = dt_s * I3
    Bd = np.zeros((N_STATE, N_INPUT))
    Bd[P, 0:3] = dt_s**3 / 6.0 * I3
    Bd[V, 0:3] = 0.5 * dt_s**2 * I3
    Bd[A, 0:3] = dt_s * I3
    Bd[YAW, 3] = dt_s
    return Ad, Bd


def step(z: np.ndarray, w: np.ndarray, dt_s: float) -> np.ndarray:
    """Flat state after ``dt_s`` with input ``w`` held (the closed-loop plant)."""
    Ad, Bd = discrete_model(dt_s)
    return Ad @ np.asarray(z, float) + Bd @ np.asarray(w, float)


def attitude_from_flat(a: np.ndarray, yaw: float) -> tuple[float, float, float]:
    """``(thrust per mass m/s^2, roll rad, pitch rad)`` of a level-yawed multirotor with acceleration ``a`` (g)."""
    f = np.asarray(a, float) + np.array([0.0, 0.0, GRAVITY_MPS2])
    thrust = float(np.linalg.norm(f))
    b = rot_z(yaw).T @ (f / thrust)  # thrust direction in the yawed (heading) frame
    pitch = math.atan2(b[0], b[2])
    roll = math.atan2(-b[1], math.hypot(b[0], b[2]))
    return thrust, roll, pitch


__all__ = ["GRAVITY_MPS2", "N_INPUT", "N_STATE", "attitude_from_flat", "discrete_model", "step"]
