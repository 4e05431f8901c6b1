"""Perception chance constraint (thesis §7.3.2) with analytic gradients over an MPC horizon: landmark ``i`` is an inlier
with probability ``p_i`` of the ``PerceptionModel``, the inlier count is Poisson-binomial, and
``P(L >= L_min) >= 1 - delta`` becomes ``g = mu - c_bar sigma - L_min >= 0`` (or the conservative
``mu - c_bar sqrt(mu) - L_min``) under the normal approximation, evaluated by :class:`PerceptionConstraint` for ``N``
camera positions with yaws or optical axes in the trunk's frame ``o``. Gradients at clips, cuts and cone points, and
the numerics of the hot path: docs/perception_model.md, "Chance constraint" and "In code". The exact tails are
:mod:`perception_model.tails`'s (re-exported here)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.polynomial import chebyshev, polynomial
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError, PerceptionModelError
from .model import PerceptionModel
from .records import short_repr
from .settings import THESIS_C_BAR, THESIS_L_MIN, THESIS_PITCH_DOWN_RAD  # thesis defaults (§7.4)
from .tails import (  # noqa: F401 - re-exported: the distribution of the inlier count
    DEFAULT_MC_SAMPLES,
    MC_CHUNK_ELEMENTS,
    PmfMethod,
    TailComparison,
    c_bar_from_delta,
    compare_tails,
    delta_from_c_bar,
    inlier_moments,
    monte_carlo_tail,
    normal_tail,
    poisson_binomial_pmf,
    poisson_binomial_tail,
)

Kind = Literal["normal", "conservative"]
_VECTOR_DIM = 3


# --------------------------------------------------------------------------- the constraint
@dataclass(frozen=True)
class ConstraintEvaluation:
    """Constraint values along a horizon of N camera poses against M landmarks.

    ``p`` is ``(N, M)``; ``mu``, ``sigma``, ``g``, ``g_conservative`` are ``(N,)``. Gradients
    w.r.t. camera position are ``(N, 3)`` (per metre, frame ``o``), w.r.t. yaw ``(N,)`` (per
    radian); ``None`` when not requested (or, for yaw, when explicit axes were given).
    """

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    p: NDArray[np.float64]
    mu: NDArray[np.float64]
    sigma: NDArray[np.float64]
    g: NDArray[np.float64]
    g_conservative: NDArray[np.float64]
    dmu_dpos: NDArray[np.float64] | None = None
    dsigma_dpos: NDArray[np.float64] | None = None
    dg_dpos: NDArray[np.float64] | None = None
    dgc_dpos: NDArray[np.float64] | None = None
    dmu_dyaw: NDArray[np.float64] | None = None
    dsigma_dyaw: NDArray[np.float64] | None = None
    dg_dyaw: NDArray[np.float64] | None = None
    dgc_dyaw: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class Linearization:
    """First-order model ``g(y) ~ value + grad_pos . (pos - pos0) + grad_yaw (yaw - yaw0)`` per step.

    For one SQP step of an MPC: impose ``value_k + grad_k . (y_k - y0_k) >= 0`` for each step k.
    """

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    kind: str
    positions: NDArray[np.float64]
    yaw: NDArray[np.float64] | None
    value: NDArray[np.float64]
    grad_pos: NDArray[np.float64]
    grad_yaw: NDArray[np.float64] | None

    def predict(self, positions: ArrayLike, yaw: ArrayLike | None = None) -> NDArray[np.float64]:
        """Linearized constraint value at nearby poses."""
        d = np.asarray(positions, dtype=np.float64) - self.positions
        out = self.value + np.einsum("ij,ij->i", self.grad_pos, d)
        if self.grad_yaw is not None and yaw is not None and self.yaw is not None:
            out = out + self.grad_yaw * (np.asarray(yaw, dtype=np.float64) - self.yaw)
        return out

    def as_inequality(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(A, b)`` with one row per step such that the constraint reads ``A_k . y_k >= b_k``.

        ``y_k = (x, y, z, yaw)`` when yaw gradients exist, else ``(x, y, z)``.
        """
        if self.grad_yaw is not None and self.yaw is not None:
            a = np.column_stack([self.grad_pos, self.grad_yaw])
            y0 = np.column_stack([self.positions, self.yaw])
        else:
            a, y0 = self.grad_pos, self.positions
        return a, np.einsum("ij,ij->i", a, y0) - self.value


@dataclass(frozen=True)
class _ViewFactor:
    """``c1 cos(c2 theta(s))`` and its derivative as polynomials in ``s = |z^ + v^|^2`` (hot path).

    ``s = 2 - 2 cos(theta)`` is the squared view chord; ``cos(c2 theta)`` is an analytic function
    of ``s`` on [0, 4), so a Chebyshev interpolant (converted to powers of ``x = k1 s + k0`` in
    [-1, 1]) reproduces it to ~1e-15 with a low degree. The derivative polynomial is the exact
    derivative of the value polynomial, so value and gradient are mutually consistent.
    ``s_max`` is the end of the polynomial's domain; beyond it (and up to the cut) the exact
    formula is used on the few entries concerned.
    """

    value: tuple[float, ...]  # power coefficients in x, highest first
    deriv: tuple[float, ...]  # d/ds of the value polynomial, powers of x, highest first
    k1: float
    k0: float
    s_max: float


#: The view-angle polynomial covers theta <= 90 deg (s <= 2) at most; exact formula beyond.
POLY_S_LIMIT = 2.0
#: Accepted maximum error of the polynomial (absolute on c1 cos(c2 theta)) and its highest degree.
POLY_TOL = 1e-14
POLY_MAX_DEGREE = 40
#: The derivative polynomial loses ~2 digits to differentiation: its accepted error is this factor larger.
POLY_DERIV_TOL_FACTOR = 100.0
_POLY_CHECK_POINTS = 4001


def _view_exact(s: NDArray[np.float64], c1: float, c2r: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact ``c1 cos(c2 theta)`` and its derivative w.r.t. ``s = 2 - 2 cos(theta)``."""
    theta = 2.0 * np.arcsin(np.minimum(np.sqrt(np.maximum(s, 0.0)) * 0.5, 1.0))
    value = c1 * np.cos(c2r * theta)
    sin_t = np.sin(theta)
    with np.errstate(divide="ignore", invalid="ignore"):
        deriv = np.where(sin_t > 0.0, -c1 * c2r * np.sin(c2r * theta) / (2.0 * sin_t), 0.0)
    return value, deriv


def _build_view_factor(c1: float, c2r: float, s_cut: float) -> _ViewFactor | None:
    """Fit the polynomial form of ``c1 cos(c2 theta(s))``; ``None`` if no degree is accurate enough."""

    s_max = min(s_cut, POLY_S_LIMIT)
    k1, k0 = 2.0 / s_max, -1.0
    grid = np.linspace(0.0, s_max, _POLY_CHECK_POINTS)
    exact, exact_d = _view_exact(grid, c1, c2r)
    interior = grid > 0.0
    for degree in range(4, POLY_MAX_DEGREE + 1):
        cheb = chebyshev.Chebyshev.interpolate(lambda t: _view_exact(t, c1, c2r)[0], degree, domain=[0.0, s_max])
        coef = chebyshev.cheb2poly(cheb.coef)
        dcoef = polynomial.polyder(coef) * k1
        x = grid * k1 + k0
        err = np.abs(polynomial.polyval(x, coef) - exact).max()
        derr = np.abs(polynomial.polyval(x, dcoef) - exact_d)[interior].max()
        d_scale = max(1.0, float(np.abs(exact_d).max()))
        if err <= POLY_TOL and derr <= POLY_TOL * POLY_DERIV_TOL_FACTOR * d_scale:
            return _ViewFactor(tuple(coef[::-1].tolist()), tuple(dcoef[::-1].tolist()), k1, k0, s_max)
    return None


def _horner(coefs: tuple[float, ...], x: NDArray[np.float64], out: NDArray[np.float64]) -> NDArray[np.float64]:
    """Evaluate a polynomial (highest power first) at ``x`` into ``out`` (in place, no temporaries)."""
    if len(coefs) == 1:
        out.fill(coefs[0])
        return out
    np.multiply(x, coefs[0], out=out)
    np.add(out, coefs[1], out=out)
    for c in coefs[2:]:
        np.multiply(out, x, out=out)
        np.add(out, c, out=out)
    return out


def check_bounds(l_min: float, c_bar: float) -> None:
    """``PerceptionModelError`` unless ``l_min`` (an inlier count) and ``c_bar`` (a normal quantile) are finite
    and non-negative: a negative one turns the chance constraint into one that any pose satisfies."""
    for name, v in (("l_min", l_min), ("c_bar", c_bar)):
        if (
            isinstance(v, bool)
            or not isinstance(v, int | float | np.integer | np.floating)
            or not math.isfinite(float(v))
            or v < 0
        ):
            raise PerceptionModelError(f"{name} must be a finite number >= 0, got {v!r}")


class PerceptionConstraint:
    """The chance constraint for one trunk: landmarks fixed, camera poses varying.

    ``landmarks``: ``(M, 3)`` vectors ``p_is`` from the taught camera to each landmark (metres,
    frame ``o``). ``l_min``: minimum inlier count; ``c_bar``: normal quantile (use
    ``c_bar_from_delta``); ``pitch_down``: camera pitch below the horizon for yaw-defined axes.

    Construction precomputes per-landmark unit rays and a polynomial form of the view factor;
    ``evaluate`` reuses preallocated ``(N, M)`` buffers (an instance is not safe to evaluate from
    several threads at once; make one per thread).
    """

    def __init__(
        self,
        model: PerceptionModel,
        landmarks: ArrayLike,
        *,
        l_min: float = THESIS_L_MIN,
        c_bar: float = THESIS_C_BAR,
        pitch_down: float = THESIS_PITCH_DOWN_RAD,
    ) -> None:
        pts = np.asarray(landmarks, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != _VECTOR_DIM or pts.shape[0] == 0:
            raise GeometryError(f"landmarks must have shape (M, 3) with M >= 1, got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise GeometryError("landmarks contain NaN/inf")
        dist = np.linalg.norm(pts, axis=1)
        if np.any(dist == 0.0):
            raise GeometryError(f"landmark {int(np.argmax(dist == 0.0))} is at the taught camera (parallax undefined)")
        if not (math.isfinite(c_bar) and math.isfinite(l_min) and math.isfinite(pitch_down)):
            raise PerceptionModelError("c_bar, l_min and pitch_down must be finite")
        check_bounds(l_min, c_bar)
        self.model = model
        self.l_min = float(l_min)
        self.c_bar = float(c_bar)
        self.pitch_down = float(pitch_down)
        self.landmarks = pts
        self._pt = np.ascontiguousarray(pts.T)  # (3, M)
        self._u = np.ascontiguousarray((-pts / dist[:, None]).T)  # (3, M): unit ray landmark -> taught camera
        self._u_rows = np.ascontiguousarray(self._u.T)  # (M, 3)
        self._affine = np.vstack([np.ones(pts.shape[0]), self._pt])  # (4, M): [1; P^T]
        c1, c2r, c3r = model.constants_per_radian
        self._c1, self._c2r, self._c3r = c1, abs(c2r), c3r
        cut = model.theta_cutoff
        # view-angle cut on the squared chord s = |z^ + v^|^2 = 2 - 2 cos(theta)
        self._s_cut = 2.0 - 2.0 * math.cos(cut) if cut < math.pi else math.inf
        self._view = _build_view_factor(self._c1, self._c2r, self._s_cut)
        self._work: dict[str, NDArray[Any]] = {}
        self._work_n = -1

    @property
    def n_landmarks(self) -> int:
        """Number of landmarks M."""
        return int(self.landmarks.shape[0])

    # ------------------------------------------------------------------ inputs
    def _workspace(self, n: int) -> dict[str, NDArray[Any]]:
        """Preallocated buffers, reused across calls with the same N (no allocation, no page faults).

        Landmark quantities are tiled to ``(N, M)`` here once, because numpy's elementwise loops
        are several times slower when an operand is broadcast.
        """
        if self._work_n != n:
            m = self.n_landmarks
            names = ("t0", "inv_r", "ha2", "ha", "s", "x", "e", "f", "raw", "beta", "zv")
            work: dict[str, NDArray[Any]] = {name: np.empty((n, m)) for name in names}
            for name in ("notcut", "inside"):
                work[name] = np.empty((n, m), dtype=bool)
            work["lin"] = np.empty((5 * n, m))  # rows: v_x, v_y, v_z, z.v, (dz/dyaw).v
            work["prod"] = np.empty((n, m))
            work["sq"] = np.empty((3, n, m))
            work["u"] = np.ascontiguousarray(np.broadcast_to(self._u[:, None, :], (3, n, m)))
            work["h"] = np.empty((5, n, m))  # per-landmark terms summed over landmarks
            work["hw"] = np.empty((5, n, m))
            work["a_stack"] = np.empty((2 * n, m))
            self._work, self._work_n = work, n
        return self._work

    def _axes(
        self, n: int, yaw: ArrayLike | None, axes: ArrayLike | None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Unit optical axes ``(N, 3)`` and, for yaw input, ``dz/dyaw`` ``(N, 3)``."""
        if (yaw is None) == (axes is None):
            raise PerceptionModelError("give exactly one of yaw (N,) or axes (N, 3)")
        if yaw is not None:
            psi = np.asarray(yaw, dtype=np.float64)
            if psi.shape != (n,):
                psi = np.broadcast_to(psi, (n,))
            if not math.isfinite(float(psi.sum())):
                raise GeometryError("yaw contains NaN/inf")
            cb, sb = math.cos(self.pitch_down), math.sin(self.pitch_down)
            cpsi, spsi = np.cos(psi), np.sin(psi)
            z = np.empty((n, 3))
            z[:, 0] = cpsi * cb
            z[:, 1] = spsi * cb
            z[:, 2] = -sb
            dz = np.zeros((n, 3))
            dz[:, 0] = -spsi * cb
            dz[:, 1] = cpsi * cb
            return z, dz
        zz = np.broadcast_to(np.asarray(axes, dtype=np.float64), (n, _VECTOR_DIM))
        norm = np.linalg.norm(zz, axis=1, keepdims=True)
        if not np.all(np.isfinite(norm)) or np.any(norm == 0.0):
            raise GeometryError("optical axes must be finite and non-zero")
        return zz / norm, None

    @staticmethod
    def _positions(positions: ArrayLike) -> NDArray[np.float64]:
        x = np.asarray(positions, dtype=np.float64)
        if x.ndim == 1:
            x = x[None, :]
        if x.ndim != 2 or x.shape[1] != _VECTOR_DIM:
            raise GeometryError(f"positions must have shape (N, 3), got {x.shape}")
        if x.shape[0] == 0:
            raise GeometryError("positions: none given (shape (0, 3)); evaluate at least one camera position")
        if not math.isfinite(float(x.sum())):
            raise GeometryError("positions contain NaN/inf")
        return x

    # ------------------------------------------------------------------ evaluation
    def _view_factor(self, w: dict[str, NDArray[Any]], deriv: bool) -> None:
        """Fill ``w["f"]`` = c1 cos(c2 theta) (and ``w["beta"]`` = its d/ds) from ``w["s"]``."""
        s, f = w["s"], w["f"]
        view = self._view
        if view is None:  # no accurate polynomial: exact formula everywhere
            value, d = _view_exact(s, self._c1, self._c2r)
            f[...] = value
            if deriv:
                w["beta"][...] = d
            return
        x = w["x"]
        np.multiply(s, view.k1, out=x)
        np.add(x, view.k0, out=x)
        _horner(view.value, x, f)
        if deriv:
            _horner(view.deriv, x, w["beta"])
        if view.s_max < self._s_cut:
            far = np.nonzero((s > view.s_max) & (s <= self._s_cut))
            if far[0].size:
                value, d = _view_exact(s[far], self._c1, self._c2r)
                f[far] = value
                if deriv:
                    w["beta"][far] = d

    def evaluate(
        self,
        positions: ArrayLike,
        yaw: ArrayLike | None = None,
        *,
        axes: ArrayLike | None = None,
        gradient: bool = True,
    ) -> ConstraintEvaluation:
        """Probabilities, moments, constraint values and (optionally) their analytic gradients.

        ``positions``: ``(N, 3)`` current camera offsets ``p_ao`` from the taught camera (frame
        ``o``, metres). Give ``yaw`` ``(N,)`` (radians; axis from yaw and the fixed pitch) or
        ``axes`` ``(N, 3)``. A camera exactly at a landmark raises ``GeometryError``.
        """
        x = self._positions(positions)
        n = x.shape[0]
        z, dz = self._axes(n, yaw, axes)
        w = self._workspace(n)
        mul, add, sub = np.multiply, np.add, np.subtract
        t0 = w["t0"]
        # v = p_ao - p_is (landmark -> camera) and the projections z.v, dz.v, elementwise into the rows of "lin"
        # (v_x, v_y, v_z, z.v, dz.v; z.v = z.X - z.P). Not as one (5N x 4) @ (4 x M) matmul: BLAS rounds a row
        # differently with its place in the matrix (blocking, FMA), so a path evaluated in chunks would differ
        # from the whole in the last bits
        lin, prod, pt = w["lin"], w["prod"], self._affine[1:]
        for k in range(3):
            sub(x[:, k : k + 1], pt[k], out=lin[k * n : (k + 1) * n])
        for r, axis in ((3, z), (4, dz)):
            if axis is None:
                continue
            out, tmp = lin[r * n : (r + 1) * n], prod[:n]
            mul(axis[:, 0:1], pt[0], out=out)
            for k in (1, 2):
                mul(axis[:, k : k + 1], pt[k], out=tmp)
                add(out, tmp, out=out)
            sub(np.einsum("ij,ij->i", axis, x)[:, None], out, out=out)
        lin = w["lin"]
        v = lin[: 3 * n].reshape(3, n, -1)
        sq = w["sq"]
        # r = |v|,  v^ = v / r
        inv_r = w["inv_r"]
        mul(v, v, out=sq)
        np.sum(sq, axis=0, out=inv_r)
        np.sqrt(inv_r, out=inv_r)
        if not inv_r.all():
            raise GeometryError("a camera position coincides with a landmark (angles undefined)")
        np.divide(1.0, inv_r, out=inv_r)
        mul(v, inv_r, out=v)  # v now holds the unit vectors v^
        # parallax chord h = |u^ - v^| = 2 sin(alpha / 2)  (difference form: accurate for small alpha)
        ha2, ha = w["ha2"], w["ha"]
        sub(w["u"], v, out=sq)
        mul(sq, sq, out=sq)
        np.sum(sq, axis=0, out=ha2)
        np.sqrt(ha2, out=ha)
        # view: cos(theta) = -z^.v^ ; squared chord s = |z^ + v^|^2 = 2 + 2 z^.v^
        zv = mul(lin[3 * n : 4 * n], inv_r, out=w["zv"])  # = -cos(theta)
        s = w["s"]
        mul(zv, 2.0, out=s)
        add(s, 2.0, out=s)
        # e = exp(c3 alpha) = exp(2 c3 asin(h / 2));  f = c1 cos(c2 theta);  raw = f e
        e = w["e"]
        mul(ha, 0.5, out=e)
        np.minimum(e, 1.0, out=e)
        np.arcsin(e, out=e)
        mul(e, 2.0 * self._c3r, out=e)
        np.exp(e, out=e)
        self._view_factor(w, gradient)
        raw = mul(w["f"], e, out=w["raw"])
        notcut = np.less_equal(s, self._s_cut, out=w["notcut"])
        p = np.clip(raw, 0.0, 1.0)  # (the polynomial may dip ~1e-15 below 0 at the cut)
        mul(p, notcut, out=p)  # p = 0 beyond the view cut
        mu = p.sum(axis=1)
        sub(1.0, p, out=t0)
        mul(t0, p, out=t0)
        var = t0.sum(axis=1)
        sigma = np.sqrt(var)
        g = mu - self.c_bar * sigma - self.l_min
        gc = mu - self.c_bar * np.sqrt(mu) - self.l_min
        if not gradient:
            return ConstraintEvaluation(p, mu, sigma, g, gc)

        # landmarks with 0 < p < 1 carry gradient; clipped or cut ones do not
        inside = np.less(raw, 1.0, out=w["inside"])
        np.logical_and(inside, notcut, out=inside)
        a_stack = w["a_stack"]
        a = a_stack[:n]
        # a = (dp/dalpha) / (r sin alpha);  sin alpha = h cos(alpha/2) = h sqrt(1 - h^2/4)
        mul(ha2, -0.25, out=t0)
        add(t0, 1.0, out=t0)
        np.maximum(t0, 0.0, out=t0)
        np.sqrt(t0, out=t0)
        mul(t0, ha, out=t0)
        mul(raw, self._c3r, out=a)
        mul(a, inv_r, out=a)
        mul(a, inside, out=a)
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(a, t0, out=a)
        if not t0.all():  # alpha = 0 exactly: cone point, zero subgradient
            np.copyto(a, 0.0, where=t0 == 0.0)
        # beta = 2 dp/ds (masked);  b = beta / r = (dp/dtheta) / (r sin theta)
        h = w["h"]
        beta = w["beta"]
        mul(beta, e, out=beta)
        mul(beta, 2.0, out=beta)
        mul(beta, inside, out=beta)
        b = mul(beta, inv_r, out=h[3])
        # q = a cos(alpha) + b cos(theta),  cos(alpha) = 1 - h^2/2,  cos(theta) = -z^.v^
        q = w["x"]
        mul(ha2, -0.5, out=q)
        add(q, 1.0, out=q)
        mul(q, a, out=q)
        mul(b, zv, out=t0)
        sub(q, t0, out=q)
        # per-landmark dp/dX = q v^ - a u^ + b z^ ; dp/dyaw = b (dz/dyaw . v)
        mul(v, q, out=h[:3])
        nh = 4
        if dz is not None:
            mul(b, lin[4 * n : 5 * n], out=h[4])
            nh = 5
        # sums over landmarks with weights 1 (for mu) and 1 - 2p (for sigma^2)
        mul(p, -2.0, out=t0)
        add(t0, 1.0, out=t0)
        hw = w["hw"]
        mul(h[:nh], t0, out=hw[:nh])
        mul(a, t0, out=a_stack[n:])
        s1 = h[:nh].sum(axis=2)  # (nh, N)
        s2 = hw[:nh].sum(axis=2)
        au = a_stack @ self._u_rows  # (2N, 3): sum a u^ with both weights
        dmu = s1[:3].T - au[:n] + s1[3][:, None] * z
        dvar = s2[:3].T - au[n:] + s2[3][:, None] * z
        k_sigma = np.divide(0.5, sigma, out=np.zeros_like(sigma), where=sigma > 0.0)
        root = np.sqrt(mu)
        k_sqrt = np.where(
            root > 0.0, 1.0 - np.divide(0.5 * self.c_bar, root, out=np.zeros_like(mu), where=root > 0.0), 0.0
        )
        dsigma = dvar * k_sigma[:, None]
        dmu_dyaw = dsig_yaw = dg_dyaw = dgc_dyaw = None
        if dz is not None:
            dmu_dyaw = s1[4]
            dsig_yaw = s2[4] * k_sigma
            dg_dyaw = dmu_dyaw - self.c_bar * dsig_yaw
            dgc_dyaw = dmu_dyaw * k_sqrt
        return ConstraintEvaluation(
            p,
            mu,
            sigma,
            g,
            gc,
            dmu_dpos=dmu,
            dsigma_dpos=dsigma,
            dg_dpos=dmu - self.c_bar * dsigma,
            dgc_dpos=dmu * k_sqrt[:, None],
            dmu_dyaw=dmu_dyaw,
            dsigma_dyaw=dsig_yaw,
            dg_dyaw=dg_dyaw,
            dgc_dyaw=dgc_dyaw,
        )

    def probabilities(
        self, positions: ArrayLike, yaw: ArrayLike | None = None, *, axes: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """``(N, M)`` inlier probabilities of every landmark from every camera pose."""
        return self.evaluate(positions, yaw, axes=axes, gradient=False).p

    def linearize(
        self,
        positions: ArrayLike,
        yaw: ArrayLike | None = None,
        *,
        axes: ArrayLike | None = None,
        kind: Kind = "normal",
    ) -> Linearization:
        """Value and gradient of ``g`` (``kind="normal"``) or ``g_c`` (``"conservative"``) about a horizon.

        ``positions`` ``(N, 3)`` and ``yaw`` ``(N,)`` are the previous MPC prediction; the result's
        ``as_inequality`` gives the linear constraint rows of one SQP step.
        """
        if kind not in ("normal", "conservative"):
            raise PerceptionModelError(f"unknown constraint kind {kind!r} (use 'normal' or 'conservative')")
        ev = self.evaluate(positions, yaw, axes=axes, gradient=True)
        x = self._positions(positions).copy()
        psi = None if yaw is None else np.broadcast_to(np.asarray(yaw, dtype=np.float64), (x.shape[0],)).copy()
        if kind == "normal":
            value, gpos, gyaw = ev.g, ev.dg_dpos, ev.dg_dyaw
        else:
            value, gpos, gyaw = ev.g_conservative, ev.dgc_dpos, ev.dgc_dyaw
        if gpos is None:  # pragma: no cover - evaluate(gradient=True) always sets it
            raise PerceptionModelError("gradient missing")
        return Linearization(kind, x, psi, value, gpos, gyaw)
