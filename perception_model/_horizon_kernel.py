"""Compiled (numba) inner loop of ``HorizonEvaluator``: one fused pass over steps x landmarks.

The formulas are those of ``constraint.PerceptionConstraint.evaluate`` (documented there and in
``horizon``); this module only owns the loop. Compiled on first use and cached next to the source.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, fastmath=False, nogil=True)
def horizon_moments(
    X: np.ndarray,  # (N, 3) camera offset from the taught camera, trunk o
    z: np.ndarray,  # (N, 3) unit optical axis, trunk o
    trunk: np.ndarray,  # (N,) int64
    P: np.ndarray,  # (T, 3, M) landmark vectors p_is
    U: np.ndarray,  # (T, 3, M) unit rays landmark -> taught camera
    counts: np.ndarray,  # (T,) int64 landmarks per trunk
    c1: float,
    c2r: float,
    c3r: float,
    s_cut: float,
    poly: np.ndarray,  # value polynomial in x = k1 s + k0, highest power first (empty: exact formula)
    dpoly: np.ndarray,  # its derivative w.r.t. s
    k1: float,
    k0: float,
    s_max: float,
    gradient: bool,
    out_mu: np.ndarray,  # (N,)
    out_var: np.ndarray,  # (N,)
    out_grad: np.ndarray,  # (4, N, 3): d mu/dX, d var/dX, d mu/dz, d var/dz
) -> int:
    """Fill the outputs; returns -1, or the index of a step whose camera coincides with a landmark."""
    n = X.shape[0]
    npoly = poly.shape[0]
    for k in range(n):
        t = trunk[k]
        x0, x1, x2 = X[k, 0], X[k, 1], X[k, 2]
        z0, z1, z2 = z[k, 0], z[k, 1], z[k, 2]
        mu = 0.0
        var = 0.0
        g = np.zeros(12)
        for j in range(counts[t]):
            v0 = x0 - P[t, 0, j]
            v1 = x1 - P[t, 1, j]
            v2 = x2 - P[t, 2, j]
            r2 = v0 * v0 + v1 * v1 + v2 * v2
            if r2 == 0.0:
                return k
            inv_r = 1.0 / math.sqrt(r2)
            h0 = v0 * inv_r
            h1 = v1 * inv_r
            h2 = v2 * inv_r
            zv = z0 * h0 + z1 * h1 + z2 * h2  # -cos(theta)
            s = 2.0 + 2.0 * zv
            if s > s_cut:
                continue
            u0, u1, u2 = U[t, 0, j], U[t, 1, j], U[t, 2, j]
            d0, d1, d2 = u0 - h0, u1 - h1, u2 - h2
            ha2 = d0 * d0 + d1 * d1 + d2 * d2
            ha = math.sqrt(ha2)
            e = math.exp(2.0 * c3r * math.asin(min(0.5 * ha, 1.0)))
            if npoly > 0 and s <= s_max:
                xx = s * k1 + k0
                f = poly[0]
                for c in poly[1:]:
                    f = f * xx + c
                beta = dpoly[0]
                for c in dpoly[1:]:
                    beta = beta * xx + c
            else:
                th = 2.0 * math.asin(min(math.sqrt(max(s, 0.0)) * 0.5, 1.0))
                f = c1 * math.cos(c2r * th)
                st = math.sin(th)
                beta = -c1 * c2r * math.sin(c2r * th) / (2.0 * st) if st > 0.0 else 0.0
            raw = f * e
            p = min(max(raw, 0.0), 1.0)
            mu += p
            var += p * (1.0 - p)
            if not gradient or raw >= 1.0 or raw <= 0.0:
                continue
            sin_a = ha * math.sqrt(max(1.0 - 0.25 * ha2, 0.0))
            a = raw * c3r * inv_r / sin_a if sin_a > 0.0 else 0.0
            bb = 2.0 * beta * e * inv_r
            q = a * (1.0 - 0.5 * ha2) - bb * zv
            gx0 = q * h0 - a * u0 + bb * z0
            gx1 = q * h1 - a * u1 + bb * z1
            gx2 = q * h2 - a * u2 + bb * z2
            w = 1.0 - 2.0 * p
            g[0] += gx0
            g[1] += gx1
            g[2] += gx2
            g[3] += w * gx0
            g[4] += w * gx1
            g[5] += w * gx2
            g[6] += bb * v0
            g[7] += bb * v1
            g[8] += bb * v2
            g[9] += w * bb * v0
            g[10] += w * bb * v1
            g[11] += w * bb * v2
        out_mu[k] = mu
        out_var[k] = var
        for i in range(4):
            for c in range(3):
                out_grad[i, k, c] = g[3 * i + c]
    return -1
