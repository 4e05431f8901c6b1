"""Three controllers of the thesis' §8.4.1 simulation (ch. 8, Fig. 8.2), vectorized over trials.

* :class:`PDController` - position and velocity error with the reference's acceleration fed forward;
* :class:`FlatnessMPC` - the flatness-based MPC of ch. 3 (triple integrator in the flat state ``(p, v, a)``, jerk
  input, cost on the tracking error and the linearized pitch command as eq. 3.8, feedforward linearization
  through the desired flat state), fed a state estimate;
* :class:`DiscreteFlatnessController` - ch. 8: a window of outputs and the inputs sent since, the output
  trajectory optimized with cost (8.16) from the first ``r = 3`` outputs the window fixes through the
  input-to-output map (8.13, 8.15), and the input read off the first four optimized outputs with the
  output-to-input map (8.12, 8.14). With ``window_length`` M > r the first outputs are the least-squares fit of
  the model's outputs under the inputs sent to M measured ones (:func:`fit_window`) instead of three raw ones.

The unconstrained quadratic programs are solved in closed form: each reduces to one precomputed gain row (no
solver per tick). The plant and settings are in :mod:`vtr.control.pitch_model`, the outputs in
:mod:`vtr.control.output_sources`, the closed loop in :mod:`vtr.control.flatness_sweep`; docs/discrete_flatness.md.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..errors import EstimationError
from .flat_model import GRAVITY_MPS2
from .output_sources import OutputSource
from .pitch_model import WINDOW, ControllerName, DiscreteFlatnessSettings, SpiralReference

#: Gauss-Newton iterations of the window fit (tan is the only nonlinearity: 2-3 reach round-off on the reference)
FIT_ITERATIONS = 6


class _Controller:
    """Shared clock and reference: tick k is at ``t_start_ns + k control_dt_ns`` and the reference starts there."""

    name: ControllerName

    def __init__(self, settings: DiscreteFlatnessSettings, t_start_ns: int) -> None:
        self.s = settings
        self.t_start_ns = int(t_start_ns)
        self.dt = settings.control_dt_s
        self.dt_ns = settings.control_dt_ns
        self.reference = SpiralReference(settings.amplitude_m, settings.omega_rps)

    def tick(self, t_ns: int) -> int:
        k, rest = divmod(int(t_ns) - self.t_start_ns, self.dt_ns)
        if rest:
            raise EstimationError(f"t_ns={t_ns}: not on the control grid ({self.dt_ns} ns from {self.t_start_ns})")
        return k

    def t_s(self, k: int) -> float:
        return k * self.dt

    def clip(self, u: np.ndarray) -> np.ndarray:
        m = self.s.command_max
        return np.clip(np.nan_to_num(u, nan=0.0, posinf=m, neginf=-m), -m, m)

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        raise NotImplementedError


class PDController(_Controller):
    """PD on position and velocity with the reference's flat feedforward (it is feasible):
    ``a = y_ref'' + kp (y_ref - p) + kd (y_ref' - v)``, ``theta_cmd = (atan(a / g) + tau theta_ref') / k``
    where ``theta_ref = atan(y_ref'' / g)`` (the pitch lag compensated along the reference only)."""

    name: ControllerName = "pd"

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        p, v, _ = source.state(t_ns).T
        r, dr, ddr, dddr = self.reference.derivatives(np.array(self.t_s(self.tick(t_ns))))
        a = ddr + self.s.pd_kp * (r - p) + self.s.pd_kd * (dr - v)
        dtheta_ref = (dddr / GRAVITY_MPS2) / (1.0 + (ddr / GRAVITY_MPS2) ** 2)
        return self.clip((np.arctan(a / GRAVITY_MPS2) + self.s.time_constant_s * dtheta_ref) / self.s.attitude_gain)


def _triple_integrator(dt: float) -> tuple[np.ndarray, np.ndarray]:
    A = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    B = np.array([dt**3 / 6.0, 0.5 * dt * dt, dt])
    return A, B


@functools.lru_cache(maxsize=16)
def _mpc_gains(horizon: int, dt: float, q: float, r: float, tau: float, gain: float) -> tuple[np.ndarray, np.ndarray]:
    """``(g_r (N,), g_z (3,))``: the flatness MPC's first jerk is ``g_r . r_{1..N} - g_z . z0``, the optimum of
    ``sum_{i=1..N} q (y_i - r_i)^2 + sum_{i=0..N-1} r u_i^2`` with ``u_i = (a_i + tau j_i) / (g k)`` (thesis eq. 3.8:
    the pitch command of the flat state and input, linearized about hover)."""
    N = horizon
    A, B = _triple_integrator(dt)
    P = np.zeros((N + 1, 3, 3))  # z_i = P_i z0 + H_i j  (i = 0..N)
    H = np.zeros((N + 1, 3, N))
    P[0] = np.eye(3)
    for i in range(N):
        P[i + 1] = A @ P[i]
        H[i + 1] = A @ H[i]
        H[i + 1][:, i] += B
    gk = GRAVITY_MPS2 * gain
    Y_z, Y_j = P[1:, 0, :], H[1:, 0, :]
    U_z, U_j = P[:N, 2, :] / gk, (H[:N, 2, :] + tau * np.eye(N)) / gk
    sq, sr = math.sqrt(q), math.sqrt(r)
    first = np.linalg.pinv(np.vstack([sq * Y_j, sr * U_j]))[0]
    return sq * first[:N], first[:N] @ (sq * Y_z) + first[N:] @ (sr * U_z)


@functools.lru_cache(maxsize=16)
def _discrete_flatness_gains(horizon: int, dt: float, q: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """``(g_r (N - 2,), g_f (3,))``: the optimal ``y*_{k+3} = g_r . r_{k+3..k+N} + g_f . (y_k, y_{k+1}, y_{k+2})``."""
    N = horizon
    D = np.zeros((N - 2, N + 1))
    for i in range(N - 2):
        D[i, i : i + 4] = (-1.0, 3.0, -3.0, 1.0)
    sq, sr = math.sqrt(q), math.sqrt(r) / dt**3
    free = N + 1 - WINDOW
    stacked = np.vstack([sq * np.eye(free), sr * D[:, WINDOW:]])
    pinv_first = np.linalg.lstsq(stacked, np.eye(stacked.shape[0]), rcond=None)[0][0]
    return sq * pinv_first[:free], -sr * pinv_first[free:] @ D[:, :WINDOW]


class FlatnessMPC(_Controller):
    """Ch. 3's flatness-based MPC in 1-D: flat state ``z = (p, v, a)`` (the estimate, here finite differences or
    the smoother's), flat input jerk ``j`` (exact discretization of the triple integrator), cost
    ``sum_{i=1..N} q (y_i - r_i)^2 + sum_{i<N} r u_i^2`` on the linearized pitch command ``u = (a + tau j) / (g k)``
    (eq. 3.8). Feedforward linearization (eq. 3.2, Theorem 1 with no delay): the plan's desired flat state at the
    current time (its start, the estimate) and its first jerk go through the inverse of the pitch dynamics,
    ``theta_d = atan(a_d / g)``, ``theta_cmd = (tau j cos^2(theta_d) / g + theta_d) / k``."""

    name: ControllerName = "flatness_mpc"

    def __init__(self, settings: DiscreteFlatnessSettings, t_start_ns: int) -> None:
        super().__init__(settings, t_start_ns)
        self.gain_reference, self.gain_state = _mpc_gains(
            settings.horizon,
            self.dt,
            settings.q_position,
            settings.r_command_flatness_mpc,
            settings.time_constant_s,
            settings.attitude_gain,
        )
        self.offsets = np.arange(1, settings.horizon + 1)

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        z = source.state(t_ns)
        r = self.reference.position(self.t_s(self.tick(t_ns)) + self.offsets * self.dt)
        jerk = self.gain_reference @ r - z @ self.gain_state
        theta = np.arctan(z[:, 2] / GRAVITY_MPS2)
        tau, k = self.s.time_constant_s, self.s.attitude_gain
        return self.clip((tau * jerk * np.cos(theta) ** 2 / GRAVITY_MPS2 + theta) / k)


def fit_window(
    measured: np.ndarray, sent: np.ndarray, dt: float, tau: float, gain: float, iterations: int = FIT_ITERATIONS
) -> np.ndarray:
    """Outputs (B, L + 3) at ticks ``0 .. L + 2`` of the Euler model at the control step under the inputs ``sent``
    (B, L) at ticks ``0 .. L - 1``, whose first M = ``measured.shape[1]`` (L >= M - 3) are the least-squares fit to
    ``measured`` (B, M) (Gauss-Newton). The model's free parameters are the window's first state ``(y_0, y_1,
    theta_0)``: ``theta_{i+1} = (1 - dt / tau) theta_i + (dt k / tau) u_i`` and ``y_{i+2} = 2 y_{i+1} - y_i +
    g dt^2 tan(theta_i)`` (the input-to-output map 8.13 applied along the window). With M = 3 the fit passes
    through the three measurements and this is (8.15)."""
    ym, u = np.asarray(measured, float), np.asarray(sent, float)
    B, M = ym.shape
    L = u.shape[1]
    if L < M - WINDOW or u.shape[0] != B:
        raise EstimationError(f"fit_window: {u.shape} inputs cannot span a window of {M} outputs")
    alpha, beta, c2 = 1.0 - dt / tau, dt * gain / tau, GRAVITY_MPS2 * dt * dt
    n_theta = L + 1
    drive = np.zeros((B, n_theta))  # theta_i = alpha^i theta_0 + drive_i
    for i in range(L):
        drive[:, i + 1] = alpha * drive[:, i] + beta * u[:, i]
    decay = alpha ** np.arange(n_theta)
    j = np.arange(L + 3)
    T = np.clip(j[:, None] - 1 - np.arange(n_theta)[None, :], 0, None).astype(float)  # y_j's weights on tan
    E = np.stack([1.0 - j, j.astype(float)], axis=1)  # y_j's on (y_0, y_1)
    Tm, Em = T[:M], E[:M]
    # start: tan(theta) ~ theta (a linear least squares shared by the batch)
    lin = np.column_stack([Em, c2 * Tm @ decay])
    p = np.linalg.lstsq(lin, (ym - c2 * drive @ Tm.T).T, rcond=None)[0].T
    for _ in range(iterations):
        theta = p[:, 2:3] * decay + drive
        residual = ym - (p[:, :2] @ Em.T + c2 * np.tan(theta) @ Tm.T)
        J = np.empty((B, M, 3))
        J[:, :, :2] = Em
        J[:, :, 2] = c2 * (decay / np.cos(theta) ** 2) @ Tm.T
        step = np.linalg.solve(np.einsum("bmi,bmj->bij", J, J), np.einsum("bmi,bm->bi", J, residual)[..., None])
        p = p + step[..., 0]
    theta = p[:, 2:3] * decay + drive
    return p[:, :2] @ E.T + c2 * np.tan(theta) @ T.T


class DiscreteFlatnessController(_Controller):
    """Ch. 8's predictive controller on a window of outputs and the inputs it sent.

    Euler model at the control step ``dt``: ``y_{k+2} - 2 y_{k+1} + y_k = g dt^2 tan(theta_k)`` and
    ``theta_{k+1} = theta_k + dt (k u_k - theta_k) / tau``, so
    output-to-input (8.12): ``u_k = (tau (theta_{k+1} - theta_k) / dt + theta_k) / k`` with ``theta_k`` from
    outputs ``k..k+2`` and ``theta_{k+1}`` from ``k+1..k+3``; input-to-output (8.13):
    ``y_{k+3} = 2 y_{k+2} - y_{k+1} + g dt^2 tan(theta_{k+1})``. Each tick the window of ``window_length`` outputs
    ends at the latest tick its source answers for (``window_end_ns``: the newest measurement, or now for an
    estimator that carries its outputs there with the commands sent); (8.13) with the inputs sent carries it to
    ``y_k, y_{k+1}, y_{k+2}`` (8.15; with M > 3 outputs, through the fit :func:`fit_window`), which fix the first
    ``r`` outputs of (8.16): ``min sum_{i=0..N} q (y_i - r_i)^2 + r' (y_{i+3} - 3 y_{i+2} + 3 y_{i+1} - y_i)^2`` with
    ``r' = r_jerk_discrete_flatness / dt^6`` (the third difference is ``dt^3`` times the jerk). Only ``y*_{k+3}``
    enters ``u_k`` (8.14), so the QP is one gain row.
    """

    name: ControllerName = "discrete_flatness"

    def __init__(self, settings: DiscreteFlatnessSettings, t_start_ns: int) -> None:
        super().__init__(settings, t_start_ns)
        self.gain_reference, self.gain_fixed = _discrete_flatness_gains(
            settings.horizon, self.dt, settings.q_position, settings.r_jerk_discrete_flatness
        )
        self.offsets = np.arange(WINDOW, settings.horizon + 1)
        self.inputs: dict[int, np.ndarray] = {}

    def _theta(self, y0: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
        return np.arctan((y2 - 2 * y1 + y0) / (GRAVITY_MPS2 * self.dt**2))

    def _sent(self, k: int, like: np.ndarray) -> np.ndarray:
        return self.inputs.get(k, np.zeros_like(like))

    def forward(self, y0: np.ndarray, y1: np.ndarray, y2: np.ndarray, u0: np.ndarray) -> np.ndarray:
        """Input-to-output map (8.13): ``y_{k+3}`` from ``y_k, y_{k+1}, y_{k+2}`` and ``u_k``."""
        th0 = self._theta(y0, y1, y2)
        th1 = th0 + self.dt * (self.s.attitude_gain * u0 - th0) / self.s.time_constant_s
        return 2 * y2 - y1 + GRAVITY_MPS2 * self.dt**2 * np.tan(th1)

    def inverse(self, y0: np.ndarray, y1: np.ndarray, y2: np.ndarray, y3: np.ndarray) -> np.ndarray:
        """Output-to-input map (8.12): ``u_k`` from ``y_k .. y_{k+3}``."""
        th0, th1 = self._theta(y0, y1, y2), self._theta(y1, y2, y3)
        return (self.s.time_constant_s * (th1 - th0) / self.dt + th0) / self.s.attitude_gain

    def fixed_outputs(self, k: int, source: OutputSource) -> np.ndarray:
        """``y_k, y_{k+1}, y_{k+2}`` (B, 3) from the source's window and the inputs sent (8.15)."""
        M = self.s.window_length
        j = (source.window_end_ns(self.t_start_ns + k * self.dt_ns) - self.t_start_ns) // self.dt_ns
        measured = source.window(self.t_start_ns + j * self.dt_ns, M, self.dt)  # ticks j-M+1 .. j
        if M == WINDOW:  # (8.15) as printed: the three measured outputs carried forward one input at a time
            ys = list(measured.T)
            for i in range(j - WINDOW + 1, k):
                ys.append(self.forward(ys[-3], ys[-2], ys[-1], self._sent(i, ys[-1])))
            return np.stack(ys[-WINDOW:], axis=1)
        sent = np.stack([self._sent(i, measured[:, 0]) for i in range(j - M + 1, k)], axis=1)
        return fit_window(measured, sent, self.dt, self.s.time_constant_s, self.s.attitude_gain)[:, -WINDOW:]

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        k = self.tick(t_ns)
        fixed = self.fixed_outputs(k, source)
        r = self.reference.position(self.t_s(k) + self.offsets * self.dt)
        y3 = fixed @ self.gain_fixed + self.gain_reference @ r
        u = self.clip(self.inverse(fixed[:, 0], fixed[:, 1], fixed[:, 2], y3))
        self.inputs[k] = u
        return u


CONTROLLER_TYPES: dict[ControllerName, type[_Controller]] = {
    "pd": PDController,
    "flatness_mpc": FlatnessMPC,
    "discrete_flatness": DiscreteFlatnessController,
}

__all__ = [
    "CONTROLLER_TYPES",
    "FIT_ITERATIONS",
    "DiscreteFlatnessController",
    "FlatnessMPC",
    "PDController",
    "fit_window",
]
