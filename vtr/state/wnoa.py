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

STATE_DIM = 2 * POSE_DIM         # [pose tangent, body twist]
QC_BLOCKS = 4                    # the 2x2 unit matrices E_00, E_01, E_10, E_11 of a per-axis block


def noise_map(Jr: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Map (12x12) of local-variable noise ``(d xi, d xi')`` to the state perturbation ``(delta, d varpi)``."""
    B = np.zeros((STATE_DIM, STATE_DIM))
    B[:6, :6] = Jr
    B[6:, 6:] = Jr
    B[6:, :6] = E
    return B


def kron_basis(qc: np.ndarray) -> np.ndarray:
    """``E_ab ⊗ diag(qc)`` for the 2x2 unit matrices ``E_00, E_01, E_10, E_11`` (4x12x12)."""
    out = np.zeros((QC_BLOCKS, STATE_DIM, STATE_DIM))
    for n in range(QC_BLOCKS):
        unit = np.zeros((2, 2))
        unit[n // 2, n % 2] = 1.0
        out[n] = np.kron(unit, np.diag(qc))
    return out


def kron_qc(q2: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """``q2 ⊗ diag(qc)`` (12x12) for a per-axis 2x2 block ``q2``, with ``basis = kron_basis(qc)``."""
    return (q2.reshape(1, QC_BLOCKS) @ basis.reshape(QC_BLOCKS, -1)).reshape(STATE_DIM, STATE_DIM)


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
    m00, m01 = q00 + q01 * kappa, q01                  # Q(tau) Phi(kappa)^T
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


__all__ = [
    "STATE_DIM",
    "hermite_matrix",
    "kron_basis",
    "kron_qc",
    "local_variable",
    "noise_map",
    "wnoa_Phi",
    "wnoa_Q",
    "wnoa_conditional_Q",
    "wnoa_interpolation_matrices",
]
