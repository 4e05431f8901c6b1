"""White-noise-on-acceleration (WNOA) Gaussian-process algebra: the closed forms the smoother's prior
and queries are made of (pure numpy, no GTSAM; thesis §6.3.4; Barfoot, *State Estimation for
Robotics*, §11.1).

Per axis the GP state is ``gamma = [xi, xi']`` (value and rate of the local variable); over ``dt``
seconds it moves by the transition matrix :func:`wnoa_Phi` and gathers the process covariance
:func:`wnoa_Q` (a 2x2 block, multiplied by the power spectral density ``Qc`` of each axis,
:func:`kron_qc`). Inside a segment the posterior mean is the cubic Hermite curve
(:func:`hermite_matrix`, :func:`local_variable`), equal to ``Lambda gamma_1 + Psi gamma_2``
(:func:`wnoa_interpolation_matrices`), with covariance :func:`wnoa_conditional_Q` given both ends.
States are 12-vectors ``[pose tangent, body twist]`` (``STATE_DIM``) in GTSAM's tangent order.
"""

from __future__ import annotations

import numpy as np

from ..geometry import POSE_DIM

STATE_DIM = 2 * POSE_DIM  # [pose tangent, body twist]


def noise_map(Jr: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Map (12x12) of local-variable noise ``(d xi, d xi')`` to the state perturbation ``(delta, d varpi)``."""
    B = np.zeros((STATE_DIM, STATE_DIM))
    B[:6, :6] = Jr
    B[6:, 6:] = Jr
    B[6:, :6] = E
    return B


def kron_qc(q2: np.ndarray, qc: np.ndarray) -> np.ndarray:
    """``q2 ⊗ diag(qc)`` (12x12) for a per-axis 2x2 block ``q2`` and the PSD ``qc`` (6,)."""
    out = np.zeros((STATE_DIM, STATE_DIM))
    d = np.arange(POSE_DIM)
    for a in range(2):
        for b in range(2):
            out[a * POSE_DIM + d, b * POSE_DIM + d] = q2[a, b] * qc
    return out


# ----------------------------------------------------------------------------------------------
# WNOA scalar blocks (per axis; Qc factors out of the mean interpolation)


def wnoa_Q(dt: float) -> np.ndarray:
    """Per-axis WNOA process covariance over ``dt`` seconds (2x2, multiply by Qc): ``[[dt³/3, dt²/2], [dt²/2, dt]]``."""
    return np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])


def wnoa_Phi(dt: float) -> np.ndarray:
    """Per-axis WNOA transition matrix over ``dt`` seconds (2x2): ``[[1, dt], [0, 1]]``."""
    return np.array([[1.0, dt], [0.0, 1.0]])


def wnoa_interpolation_matrices(tau: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """GP interpolation matrices ``(Lambda, Psi)`` (2x2 each) at ``tau`` seconds into a segment of ``dt`` s.

    ``gamma(tau) = Lambda gamma_1 + Psi gamma_2`` with ``Psi = Q(tau) Phi(dt - tau)^T Q(dt)^-1`` and
    ``Lambda = Phi(tau) - Psi Phi(dt)`` (Barfoot, *State Estimation for Robotics*, §11.1).
    """
    Psi = wnoa_Q(tau) @ wnoa_Phi(dt - tau).T @ np.linalg.inv(wnoa_Q(dt))
    Lam = wnoa_Phi(tau) - Psi @ wnoa_Phi(dt)
    return Lam, Psi


def wnoa_conditional_Q(tau: float, dt: float) -> np.ndarray:
    """Per-axis covariance (2x2, multiply by Qc) of the GP state at ``tau`` given both segment ends.

    ``Q(tau) - Psi Phi(dt - tau) Q(tau)``, written out so a query does not invert matrices.
    """
    kappa = dt - tau
    q00, q01, q11 = tau**3 / 3.0, tau**2 / 2.0, tau
    # Psi = Q(tau) Phi(kappa)^T Q(dt)^-1 with Q(dt)^-1 = [[12/dt³, -6/dt²], [-6/dt², 4/dt]]
    i00, i01, i11 = 12.0 / dt**3, -6.0 / dt**2, 4.0 / dt
    m00, m01 = q00 + q01 * kappa, q01  # Q(tau) Phi(kappa)^T
    m10, m11 = q01 + q11 * kappa, q11
    p00, p01 = m00 * i00 + m01 * i01, m00 * i01 + m01 * i11
    p10, p11 = m10 * i00 + m11 * i01, m10 * i01 + m11 * i11
    # Psi Phi(kappa) Q(tau) = Psi M^T
    c00 = q00 - (p00 * m00 + p01 * m01)
    c01 = q01 - (p00 * m10 + p01 * m11)
    c11 = q11 - (p10 * m10 + p11 * m11)
    return np.array([[c00, c01], [c01, c11]])


def hermite_matrix(tau: float, dt: float) -> np.ndarray:
    """Rows: weights of ``[dt v1, xi21, dt g21]`` giving ``xi(tau)``, ``xi'(tau)``, ``xi''(tau)`` (3x3).

    The WNOA posterior mean in the local variable is the cubic Hermite curve with value 0 and slope
    ``v1`` at ``tau = 0``, value ``xi21`` and slope ``g21`` at ``tau = dt`` (equal to
    ``Lambda gamma_1 + Psi gamma_2``; see :func:`wnoa_interpolation_matrices`).
    """
    s = tau / dt
    s2, s3 = s * s, s * s * s
    return np.array(
        [
            [s3 - 2.0 * s2 + s, -2.0 * s3 + 3.0 * s2, s3 - s2],
            [(3.0 * s2 - 4.0 * s + 1.0) / dt, (-6.0 * s2 + 6.0 * s) / dt, (3.0 * s2 - 2.0 * s) / dt],
            [(6.0 * s - 4.0) / dt**2, (-12.0 * s + 6.0) / dt**2, (6.0 * s - 2.0) / dt**2],
        ]
    )


def local_variable(tau: float, dt: float, M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local variable ``xi(tau)`` (6,) and its first two time derivatives at ``tau`` seconds into a segment
    of ``dt`` s (the cubic Hermite mean), from the stacked control vectors ``M = [dt v1, xi21, dt g21]`` (3x6)."""
    out = hermite_matrix(tau, dt) @ M
    return out[0], out[1], out[2]


class MotionPsd:
    """The power spectral density ``Qc`` (6,) of the WNOA prior estimated from the vehicle's own motion: second
    differences of its mean body twists over two spans, which tell the motion's PSD from odometry's noise
    (docs/smoother.md, "Qc").

    A step is a relative pose ``Exp(xi)`` between consecutive keyframes over ``dt`` seconds; the mean twist over
    ``k`` consecutive steps is ``sum(xi) / sum(dt)`` (exact for a constant twist). The difference ``d`` of the mean
    twists of two adjacent spans of ``T1`` and ``T2`` seconds has, per axis, under the WNOA prior with keyframe
    positions measured with independent errors of variance ``r``, the expectation
    ``E[d^2] = Qc (T1 + T2) / 3 + r (1/T1^2 + 1/T2^2 + (1/T1 + 1/T2)^2)``: the motion's share grows with the span,
    the noise's falls. Adjacent spans of one step and of ``long_steps`` steps give two such moments per axis
    (averaged with exponential forgetting over ``window_s`` seconds of motion: a straight, a turn, a stop differ),
    solved for ``Qc`` and ``r`` (with ``r`` at 0 when the solution would make it negative). Until the
    forgetting-weighted count of long-span samples reaches ``min_samples`` the configured ``fallback`` is used, and
    the estimate never falls below ``floor_share`` of it (of ``configured`` when given: the configured ``Qc`` when the
    fallback is itself an estimate).
    """

    def __init__(
        self,
        fallback: np.ndarray,
        window_s: float,
        min_samples: float,
        floor_share: float,
        long_steps: int,
        configured: np.ndarray | None = None,
    ) -> None:
        self.fallback = np.asarray(fallback, float).copy()
        self.window_s = float(window_s)
        self.min_samples = float(min_samples)
        # the floor is a share of the configured Qc, also when the fallback is itself an estimate (a taught path's)
        self.floor = float(floor_share) * (self.fallback if configured is None else np.asarray(configured, float))
        self.spans = (1, int(long_steps))
        # per span: forgetting-weighted sums of d^2 (6,), of the two regressors and of the weights
        self._y = np.zeros((2, POSE_DIM))
        self._ab = np.zeros((2, 2))
        self._w = np.zeros(2)
        self._steps: list[tuple[np.ndarray, float]] = []

    @property
    def samples(self) -> float:
        """The forgetting-weighted count of long-span samples so far."""
        return float(self._w[1])

    @property
    def qc(self) -> np.ndarray:
        """The current estimate (6,) ``[rot x3 (rad²/s³), trans x3 (m²/s³)]``; the fallback until enough samples."""
        if self.window_s <= 0.0 or self._w[1] < self.min_samples or self._w[0] <= 0.0:
            return self.fallback.copy()
        y = self._y / self._w[:, None]  # mean d^2 per span and axis
        (a1, b1), (a2, b2) = self._ab / self._w[:, None]  # mean regressors per span
        det = a2 * b1 - a1 * b2
        qc = (y[1] * b1 - y[0] * b2) / det if det > 0.0 else y[1] / a2
        r = (y[0] - qc * a1) / b1
        qc = np.where(r < 0.0, (y[0] + y[1]) / (a1 + a2), qc)  # no noise: both spans measure Qc alone
        return np.maximum(qc, self.floor)

    def add(self, xi: np.ndarray, dt_s: float) -> None:
        """One keyframe step: ``xi`` (6,) = ``Log(T_prev_cur)`` over ``dt_s`` seconds (> 0)."""
        if not dt_s > 0.0 or self.window_s <= 0.0:
            return
        self._steps.append((np.asarray(xi, float), float(dt_s)))
        del self._steps[: -2 * self.spans[1]]
        keep = float(np.exp(-dt_s / self.window_s))
        self._y *= keep
        self._ab *= keep
        self._w *= keep
        for j, k in enumerate(self.spans):
            if len(self._steps) < 2 * k:
                continue
            before, after = self._steps[-2 * k : -k], self._steps[-k:]
            T1, T2 = sum(dt for _, dt in before), sum(dt for _, dt in after)
            d = sum(x for x, _ in after) / T2 - sum(x for x, _ in before) / T1
            self._y[j] += d**2
            self._ab[j] += ((T1 + T2) / 3.0, 1.0 / T1**2 + 1.0 / T2**2 + (1.0 / T1 + 1.0 / T2) ** 2)
            self._w[j] += 1.0

    def broken(self) -> None:
        """Odometry broke: the next step is not a neighbour of the last (no sample across the break)."""
        self._steps.clear()

    def of_poses(self, t_ns: np.ndarray, T_world: np.ndarray, max_step_s: float) -> np.ndarray:
        """The estimate over a whole sequence of keyframe poses (times ``t_ns`` (N,) int ns, ``T_world`` (N, 4, 4)),
        unforgotten: e.g. a taught path's motion, the prior of a repeat along it. A step longer than ``max_step_s``
        or not forward in time breaks the sequence. This estimator's settings, a fresh state; the fallback when the
        sequence gives too few samples."""
        from ..geometry import inv_T, log_se3

        est = MotionPsd(self.fallback, float("inf"), self.min_samples, 0.0, self.spans[1])
        est.floor = self.floor
        if self.window_s <= 0.0:
            return self.fallback.copy()
        dt = np.diff(np.asarray(t_ns, np.int64)) / 1e9
        for i, step_s in enumerate(dt):
            if 0.0 < step_s <= max_step_s:
                est.add(log_se3(inv_T(T_world[i]) @ T_world[i + 1]), float(step_s))
            else:
                est.broken()
        return est.qc


__all__ = [
    "MotionPsd",
    "STATE_DIM",
    "hermite_matrix",
    "kron_qc",
    "local_variable",
    "noise_map",
    "wnoa_Phi",
    "wnoa_Q",
    "wnoa_conditional_Q",
    "wnoa_interpolation_matrices",
]
