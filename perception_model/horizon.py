"""The chance constraint over an MPC horizon whose steps fall on different trunks: :class:`HorizonEvaluator` holds the
landmarks of every taught vertex in its own controller frame ``o`` and evaluates all steps in one compiled pass, each
exactly as ``PerceptionConstraint.evaluate`` does, with the gradients (position, axis yaw or optical axis) rotated back
to the map's gravity frame ``g``; a trunk without landmarks in view is a flag, never an error. Inputs, outputs and
flags: docs/perception_model.md, "In code" (Horizon)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .constraint import _build_view_factor, check_bounds
from .errors import GeometryError, PerceptionModelError
from .frames import rot_z
from .model import PerceptionModel
from .records import short_repr
from .settings import THESIS_C_BAR, THESIS_L_MIN, THESIS_PITCH_DOWN_RAD

#: Per-step flags of a horizon evaluation.
OK = 0
EMPTY_TRUNK = 1  # the trunk has no landmark
NO_LANDMARK_IN_VIEW = 2  # every landmark has p = 0 (outside the model's view cone)
OFF_ROUTE = 3  # past the route's ends or too far from it (set by the caller that knows the route)


@dataclass(frozen=True)
class TrunkLandmarks:
    """One taught vertex as the constraint sees it, in the gravity-aligned map frame g and its own o.

    ``position_g`` (3,) and ``yaw_g`` (rad): the trunk vehicle's origin and yaw in g (they define o);
    ``camera_o`` (3,): the taught camera centre in o; ``landmarks_o`` (M, 3): vectors ``p_is`` from the
    taught camera to each landmark, in o (M may be 0); ``pitch_down`` (rad): the taught camera's
    pitch below the horizon (used for yaw-defined axes).
    """

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    vertex_id: int
    position_g: NDArray[np.float64]
    yaw_g: float
    camera_o: NDArray[np.float64]
    landmarks_o: NDArray[np.float64]
    pitch_down: float = THESIS_PITCH_DOWN_RAD


@dataclass(frozen=True)
class HorizonEvaluation:
    """Values (N,) and gradients of the constraint along a horizon (gradients in frame g)."""

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    trunk: NDArray[np.int64]  # index of each step's trunk in the evaluator
    mu: NDArray[np.float64]
    sigma: NDArray[np.float64]
    g: NDArray[np.float64]
    g_conservative: NDArray[np.float64]
    flag: NDArray[np.int8]
    dg_dpos: NDArray[np.float64] | None = None
    dgc_dpos: NDArray[np.float64] | None = None
    dg_dyaw: NDArray[np.float64] | None = None
    dgc_dyaw: NDArray[np.float64] | None = None
    dg_daxis: NDArray[np.float64] | None = None
    dgc_daxis: NDArray[np.float64] | None = None
    dmu_dpos: NDArray[np.float64] | None = None
    dsigma_dpos: NDArray[np.float64] | None = None
    dmu_dyaw: NDArray[np.float64] | None = None
    dmu_daxis: NDArray[np.float64] | None = None
    distance_m: NDArray[np.float64] | None = None  # camera to its trunk's taught camera (m)


def _broadcast(values: ArrayLike, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    """``values`` as floats broadcast to ``shape`` (``GeometryError`` naming ``name`` when they do not fit)."""
    try:
        return np.broadcast_to(np.asarray(values, dtype=np.float64), shape)
    except (ValueError, TypeError):
        raise GeometryError(f"{name}: shape {np.shape(values)} does not fit the horizon {shape}") from None


def _kernel() -> Any:
    """The compiled loop (numba is imported on first evaluation only)."""
    from . import _horizon_kernel

    return _horizon_kernel


class HorizonEvaluator:
    """Value and gradient of the chance constraint for a whole horizon, each step against its own trunk."""

    def __init__(
        self,
        model: PerceptionModel,
        trunks: Sequence[TrunkLandmarks],
        *,
        l_min: float = THESIS_L_MIN,
        c_bar: float = THESIS_C_BAR,
    ) -> None:
        if len(trunks) == 0:
            raise PerceptionModelError("a horizon evaluator needs at least one trunk")
        check_bounds(l_min, c_bar)
        self.model = model
        self.l_min, self.c_bar = float(l_min), float(c_bar)
        self.trunks = list(trunks)
        t = len(trunks)
        counts = np.array([np.asarray(tr.landmarks_o).reshape(-1, 3).shape[0] for tr in trunks], dtype=np.int64)
        m = max(1, int(counts.max()))
        P = np.zeros((t, 3, m))
        U = np.zeros((t, 3, m))
        mask = np.zeros((t, m), dtype=bool)
        for i, tr in enumerate(trunks):
            pts = np.asarray(tr.landmarks_o, dtype=np.float64).reshape(-1, 3)
            if not np.all(np.isfinite(pts)):
                raise GeometryError(f"trunk {tr.vertex_id}: landmarks contain NaN/inf")
            dist = np.linalg.norm(pts, axis=1)
            if np.any(dist == 0.0):
                raise GeometryError(f"trunk {tr.vertex_id}: a landmark is at the taught camera")
            n = pts.shape[0]
            P[i, :, :n] = pts.T
            U[i, :, :n] = (-pts / dist[:, None]).T
            mask[i, :n] = True
            # padding: a far landmark straight above (never in view), masked out anyway
            P[i, 2, n:] = 1.0
            U[i, 2, n:] = -1.0
        self.counts = counts
        self._P, self._U, self._mask = P, U, mask
        self.position_g = np.array([np.asarray(tr.position_g, dtype=np.float64) for tr in trunks])
        self.yaw_g = np.array([float(tr.yaw_g) for tr in trunks])
        self.camera_o = np.array([np.asarray(tr.camera_o, dtype=np.float64) for tr in trunks])
        self.pitch_down = np.array([float(tr.pitch_down) for tr in trunks])
        self.vertex_ids = np.array([int(tr.vertex_id) for tr in trunks], dtype=np.int64)
        c1, c2r, c3r = model.constants_per_radian
        self._c1, self._c2r, self._c3r = c1, abs(c2r), c3r
        cut = model.theta_cutoff
        self._s_cut = 2.0 - 2.0 * math.cos(cut) if cut < math.pi else math.inf
        self._view = _build_view_factor(self._c1, self._c2r, self._s_cut)

    def __len__(self) -> int:
        return len(self.trunks)

    def camera_centres_g(self) -> NDArray[np.float64]:
        """Taught camera centres (T, 3) in g."""
        R = rot_z(self.yaw_g)
        return self.position_g + np.einsum("tij,tj->ti", R, self.camera_o)

    def evaluate(
        self,
        positions_g: ArrayLike,
        trunk: ArrayLike,
        yaw_g: ArrayLike | None = None,
        *,
        axes_g: ArrayLike | None = None,
        gradient: bool = True,
    ) -> HorizonEvaluation:
        """Evaluate camera centres ``positions_g`` (N, 3) against trunks ``trunk`` (N,) (indices into the trunks).

        Give the axis yaw ``yaw_g`` (N,) (radians in g) or the optical axes ``axes_g`` (N, 3).
        """
        x_g = np.asarray(positions_g, dtype=np.float64)
        if x_g.ndim == 1:
            x_g = x_g[None, :]
        n = x_g.shape[0]
        if x_g.shape != (n, 3) or not np.all(np.isfinite(x_g)):
            raise GeometryError(f"positions must be finite with shape (N, 3), got {x_g.shape}")
        if n == 0:
            raise GeometryError("positions: an empty horizon (shape (0, 3)); give at least one step")
        trunk_a = np.asarray(trunk)
        if trunk_a.dtype.kind not in "iu" or trunk_a.shape not in ((), (n,)):
            raise PerceptionModelError(
                f"trunk must be integer indices of shape ({n},), got {trunk_a.dtype} {trunk_a.shape}"
            )
        tr = np.broadcast_to(trunk_a.astype(np.int64), (n,))
        if tr.min() < 0 or tr.max() >= len(self.trunks):
            raise PerceptionModelError(f"trunk indices must be in [0, {len(self.trunks)})")
        if (yaw_g is None) == (axes_g is None):
            raise PerceptionModelError("give exactly one of yaw_g (N,) or axes_g (N, 3)")
        psi_t = self.yaw_g[tr]
        c, s_ = np.cos(psi_t), np.sin(psi_t)
        d = x_g - self.position_g[tr]
        # X: camera offset from the taught camera, in o  (Rz(psi_t)^T d - camera_o)
        X = np.empty((n, 3))
        X[:, 0] = c * d[:, 0] + s_ * d[:, 1]
        X[:, 1] = -s_ * d[:, 0] + c * d[:, 1]
        X[:, 2] = d[:, 2]
        X -= self.camera_o[tr]
        dz = None
        if yaw_g is not None:
            psi = _broadcast(yaw_g, (n,), "yaw") - psi_t
            if not np.all(np.isfinite(psi)):
                raise GeometryError("yaw contains NaN/inf")
            b = self.pitch_down[tr]
            cb = np.cos(b)
            z = np.stack([np.cos(psi) * cb, np.sin(psi) * cb, -np.sin(b)], axis=1)
            dz = np.stack([-np.sin(psi) * cb, np.cos(psi) * cb, np.zeros(n)], axis=1)
        else:
            assert axes_g is not None
            zg = _broadcast(axes_g, (n, 3), "axes")
            norm = np.linalg.norm(zg, axis=1)
            if not np.all(np.isfinite(norm)) or np.any(norm == 0.0):
                raise GeometryError("optical axes must be finite and non-zero")
            zg = zg / norm[:, None]
            z = np.stack([c * zg[:, 0] + s_ * zg[:, 1], -s_ * zg[:, 0] + c * zg[:, 1], zg[:, 2]], axis=1)
        mu = np.empty(n)
        var = np.empty(n)
        grads = np.zeros((4, n, 3))
        view = self._view
        poly = np.asarray(view.value if view else (), dtype=np.float64)
        dpoly = np.asarray(view.deriv if view else (), dtype=np.float64)
        bad = _kernel().horizon_moments(
            X,
            np.ascontiguousarray(z),
            np.ascontiguousarray(tr),
            self._P,
            self._U,
            self.counts,
            self._c1,
            self._c2r,
            self._c3r,
            self._s_cut,
            poly,
            dpoly,
            view.k1 if view else 1.0,
            view.k0 if view else 0.0,
            view.s_max if view else 0.0,
            gradient,
            mu,
            var,
            grads,
        )
        if bad >= 0:
            raise GeometryError(f"step {bad}: the camera coincides with a landmark (angles undefined)")
        sigma = np.sqrt(var)
        g = mu - self.c_bar * sigma - self.l_min
        gc = mu - self.c_bar * np.sqrt(mu) - self.l_min
        flag = np.zeros(n, dtype=np.int8)
        flag[mu <= 0.0] = NO_LANDMARK_IN_VIEW
        flag[self.counts[tr] == 0] = EMPTY_TRUNK
        distance = np.linalg.norm(X, axis=1)
        if not gradient:
            return HorizonEvaluation(tr.copy(), mu, sigma, g, gc, flag, distance_m=distance)
        k_sigma = np.divide(0.5, sigma, out=np.zeros_like(sigma), where=sigma > 0.0)
        root = np.sqrt(mu)
        k_sqrt = np.where(
            root > 0.0, 1.0 - np.divide(0.5 * self.c_bar, root, out=np.zeros_like(mu), where=root > 0.0), 0.0
        )
        dmu_o, dsig_o = grads[0], grads[1] * k_sigma[:, None]
        dg_o = dmu_o - self.c_bar * dsig_o
        dgc_o = dmu_o * k_sqrt[:, None]
        dax_mu, dax_sig = grads[2], grads[3] * k_sigma[:, None]
        dg_ax_o = dax_mu - self.c_bar * dax_sig
        dgc_ax_o = dax_mu * k_sqrt[:, None]

        def to_g(vec: NDArray[np.float64]) -> NDArray[np.float64]:
            out = np.empty_like(vec)
            out[:, 0] = c * vec[:, 0] - s_ * vec[:, 1]
            out[:, 1] = s_ * vec[:, 0] + c * vec[:, 1]
            out[:, 2] = vec[:, 2]
            return out

        dg_dyaw = dgc_dyaw = dmu_dyaw = None
        if dz is not None:
            dg_dyaw = np.einsum("nk,nk->n", dg_ax_o, dz)
            dgc_dyaw = np.einsum("nk,nk->n", dgc_ax_o, dz)
            dmu_dyaw = np.einsum("nk,nk->n", dax_mu, dz)
        return HorizonEvaluation(
            tr.copy(),
            mu,
            sigma,
            g,
            gc,
            flag,
            dg_dpos=to_g(dg_o),
            dgc_dpos=to_g(dgc_o),
            dg_dyaw=dg_dyaw,
            dgc_dyaw=dgc_dyaw,
            dg_daxis=to_g(dg_ax_o),
            dgc_daxis=to_g(dgc_ax_o),
            dmu_dpos=to_g(dmu_o),
            dsigma_dpos=to_g(dsig_o),
            dmu_dyaw=dmu_dyaw,
            dmu_daxis=to_g(dax_mu),
            distance_m=distance,
        )


__all__ = [
    "EMPTY_TRUNK",
    "NO_LANDMARK_IN_VIEW",
    "OFF_ROUTE",
    "OK",
    "HorizonEvaluation",
    "HorizonEvaluator",
    "TrunkLandmarks",
]
