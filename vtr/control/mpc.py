"""Perception-aware flatness-based MPC (thesis ch. 3 eq. 3.8 with the chance constraint of §7.3.3).

One quadratic program per outer-loop tick (50 Hz) over the linear flat model
(:mod:`vtr.control.flat_model`, 10 Hz grid, N = 15):

    min  sum_k (y_k - r_k)' Q (y_k - r_k) + w_k' R w_k + rho * sum_k s_k
    s.t. z_{k+1} = A z_k + B w_k,   |v|, |a|, |j|, |psi_dot| bounded per axis,
         path rows (one of):
           none        -
           fixed d     |n_left . (p_k - c_k)| <= d + s_k,  |n_up . (p_k - c_k)| <= d + s_k
           perception  g(y0_k) + grad g(y0_k) . (y_k - y0_k) >= margin - s_k
         terminal set  v_N = 0, a_N = 0 (hover),   s_k >= 0.

``r_k`` runs along the taught path at the desired speed from the current along-track position;
``c_k``/normals are the taught path's closest segment to the previous prediction; the perception
row is the chance constraint ``mu - c_bar sigma - L_min`` of :class:`vtr.control.field.TaughtPathField`
linearized about the previous prediction (one SQP iteration a tick, as in the thesis), each step
against its own trunk (localizer's rule).

**Recursive feasibility.** The terminal set is hover: at step N the vehicle is at rest, and a
resting vehicle stays feasible for every constraint above (all are time-invariant functions of
``(p, psi)``), so the previous plan followed by hover is feasible for the next problem when the
constraint is exact and the grid aligned. Two things break that guarantee in practice: the
constraint is linearized (SQP) and the 50 Hz ticks shift a 10 Hz grid. The path rows are
therefore softened with an exact L1 penalty (``slack_weight``, far above any tracking cost) so the
QP always has a solution; slacks are reported every tick (``MpcSolution.max_slack``) and are zero
whenever the hard problem is feasible. The hover terminal set also makes the controller brake
in time: with a 1.5 s horizon it never plans faster than it can stop.

**Errors.** Inputs are checked where they enter (``EstimationError``: a state of 10 finite numbers, a trunk
index of the field, a reference of finite points, a finite non-zero camera axis). A start the bounds
exclude (a speed above ``speed_max_mps`` on an axis, say) makes the QP infeasible. A QP that OSQP does not
solve (``primal infeasible``, ``dual infeasible``, ...) raises ``MpcInfeasible`` (an ``EstimationError``)
instead of returning its iterate: that iterate is not a command (an infeasible QP's ``x`` held jerks of
2e9), and which fallback is safe (brake, hover, hand over to a pilot) depends on the vehicle, so the
caller decides. ``maximum iterations reached`` returns
the best iterate (finite, within the box bounds up to OSQP's tolerance) with that ``status``.
``ControlConfig`` owns ``l_min`` and ``c_bar``: the field's constraint is rebuilt with them.

QPs are solved by OSQP (sparse, warm-started; the constraint matrix keeps one sparsity pattern
and only its values are updated). Each QP is posed relative to the current position and yaw (OSQP's
tolerances are absolute: absolute map coordinates in the perception rows cost accuracy and speed).
Perception rows with gradients steeper than 1 inlier/m are divided by their gradient norm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp

from perception_model.frames import wrap_angle

from ..config import ControlConfig, check_section
from ..errors import EstimationError
from ..state.controller import ReferencePath
from .field import TaughtPathField
from .flat_model import N_INPUT, N_STATE, discrete_model

Mode = Literal["none", "fixed", "perception"]
_NZ, _NW = N_STATE, N_INPUT
ACCEPTED_STATUS = ("solved", "solved inaccurate", "maximum iterations reached")


class MpcInfeasible(EstimationError):
    """The tick's QP has no solution OSQP could find (infeasible start, inconsistent bounds): no command."""


@dataclass(frozen=True)
class MpcSolution:
    """One tick: the input to apply, the predicted flat states (N, 10), slacks and solver status."""

    w: np.ndarray
    z_pred: np.ndarray
    w_pred: np.ndarray
    max_slack: float
    status: str
    iterations: int
    trunk: np.ndarray | None  # predicted trunks (perception mode)


class TaughtPathReference:
    """The taught path (vehicle positions in g) as reference: arc length, points and headings."""

    def __init__(self, positions_g: np.ndarray) -> None:
        p = np.asarray(positions_g, float)
        if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
            raise EstimationError(f"reference: expected finite positions of shape (K, 3), got {p.shape}")
        self.path = ReferencePath(p)
        d = self.path.directions
        self.heading = np.arctan2(d[:, 1], d[:, 0])

    @property
    def length(self) -> float:
        return self.path.length

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (K, 3) and headings (K,) at arc lengths ``s`` (clipped to the path)."""
        s = np.clip(np.asarray(s, float), 0.0, self.path.length)
        seg = np.clip(np.searchsorted(self.path.cumulative, s, side="right") - 1, 0, len(self.path.lengths) - 1)
        pts = self.path.points[seg] + (s - self.path.cumulative[seg])[:, None] * self.path.directions[seg]
        return pts, self.heading[seg]


class PerceptionAwareMPC:
    """The MPC of the module docstring for one path-row ``mode``; call :meth:`solve` once per tick.

    ``camera_axis_g`` (3,): a gimbal holding the optical axis fixed in g (the thesis' experiment);
    default the camera mount of ``field`` (the axis turns with the vehicle's yaw).
    """

    def __init__(self, reference: TaughtPathReference, config: ControlConfig | None = None, *,
                 mode: Mode = "perception", fixed_bound_m: float = 0.0,
                 field: TaughtPathField | None = None, camera_axis_g: np.ndarray | None = None) -> None:
        import osqp

        self.cfg = c = config or ControlConfig()
        check_section(c, "control")  # a config built in code is checked against its declared domains too
        if mode not in ("none", "fixed", "perception"):
            raise EstimationError(f"unknown MPC mode {mode!r}")
        if mode == "perception" and field is None:
            raise EstimationError("the perception-aware MPC needs a TaughtPathField")
        if mode == "fixed" and not fixed_bound_m > 0.0:
            raise EstimationError(f"a fixed path-error bound must be positive, got {fixed_bound_m}")
        if mode == "fixed" and not np.isfinite(fixed_bound_m):
            raise EstimationError(f"a fixed path-error bound must be finite, got {fixed_bound_m}")
        if field is not None:           # ControlConfig owns l_min and c_bar (the field's landmarks are shared)
            field = field.with_bounds(c.l_min, c.c_bar)
        self.reference, self.mode, self.bound, self.field = reference, mode, float(fixed_bound_m), field
        if camera_axis_g is not None:
            axis = np.asarray(camera_axis_g, float)
            if axis.shape != (3,) or not np.all(np.isfinite(axis)) or not np.linalg.norm(axis) > 0:
                raise EstimationError(f"camera_axis_g: expected a finite non-zero 3-vector, got {axis!r}")
        self.camera_axis_g = None if camera_axis_g is None else np.asarray(camera_axis_g, float)
        n = self.n = int(c.horizon)
        self.Ad, self.Bd = discrete_model(c.dt_s)
        self.rows_per_step = {"none": 0, "fixed": 4, "perception": 1}[mode]
        self.n_soft = n if self.rows_per_step else 0
        self.nx = n * _NZ + n * _NW + self.n_soft
        self._build(osqp)
        self.z_prev: np.ndarray | None = None
        self.progress_m = 0.0

    # ------------------------------------------------------------------ indices
    def _iz(self, k: int) -> int:  # state z_{k+1}, k = 0..N-1
        return k * _NZ

    def _iw(self, k: int) -> int:
        return self.n * _NZ + k * _NW

    def _is(self, k: int) -> int:
        return self.n * (_NZ + _NW) + k

    def _build(self, osqp) -> None:
        c, n = self.cfg, self.n
        # cost: 1/2 x' P x + q' x  (P = 2 Q on outputs, 2 R on inputs)
        pd = np.zeros(self.nx)
        for k in range(n):
            pd[self._iz(k):self._iz(k) + 3] = 2.0 * c.q_position
            pd[self._iz(k) + 9] = 2.0 * c.q_yaw
            pd[self._iw(k):self._iw(k) + 3] = 2.0 * c.r_jerk
            pd[self._iw(k) + 3] = 2.0 * c.r_yaw_rate
        if self.n_soft:
            pd[self._is(0):] = c.slack_quadratic_weight  # strictly convex in the slacks (plus the L1 term in q)
        self.P = sp.diags(pd).tocsc()
        rows, cols, vals = [], [], []
        r = 0
        # dynamics: z_1 - B w_0 = A z0 ; z_{k+1} - A z_k - B w_k = 0
        for k in range(n):
            for i in range(_NZ):
                rows.append(r + i)
                cols.append(self._iz(k) + i)
                vals.append(1.0)
            if k > 0:
                ii, jj = np.nonzero(self.Ad)
                rows += list(r + ii)
                cols += list(self._iz(k - 1) + jj)
                vals += list(-self.Ad[ii, jj])
            ii, jj = np.nonzero(self.Bd)
            rows += list(r + ii)
            cols += list(self._iw(k) + jj)
            vals += list(-self.Bd[ii, jj])
            r += _NZ
        self.n_eq = r
        # boxes on v, a (every step) and on the inputs; slacks >= 0
        for k in range(n):
            for i in range(3, 9):
                rows.append(r)
                cols.append(self._iz(k) + i)
                vals.append(1.0)
                r += 1
            for i in range(_NW):
                rows.append(r)
                cols.append(self._iw(k) + i)
                vals.append(1.0)
                r += 1
        for k in range(self.n_soft):
            rows.append(r)
            cols.append(self._is(k))
            vals.append(1.0)
            r += 1
        self.n_box_end = r
        # path rows: pattern (x, y, z, psi of z_{k+1}, slack k); values set every tick
        self._path_coo_start = len(vals)
        self.path_row0 = r
        for k in range(n):
            for _ in range(self.rows_per_step):
                for i in (0, 1, 2, 9):
                    rows.append(r)
                    cols.append(self._iz(k) + i)
                    vals.append(1.0)
                rows.append(r)
                cols.append(self._is(k))
                vals.append(1.0)
                r += 1
        self.m = r
        coo_vals = np.array(vals)
        A = sp.csc_matrix((np.arange(1, len(vals) + 1, dtype=float), (rows, cols)), shape=(self.m, self.nx))
        self._perm = (A.data - 1).astype(np.int64)  # CSC data order -> construction order
        self._coo_vals = coo_vals
        A.data = coo_vals[self._perm]
        self.A = A
        self.l = np.zeros(self.m)
        self.u = np.zeros(self.m)
        self._set_boxes()
        self.q = np.zeros(self.nx)
        if self.n_soft:
            self.q[self._is(0):] = c.slack_weight
        self.solver = osqp.OSQP()
        self.solver.setup(self.P, self.q, self.A, self.l, self.u, verbose=False, warm_starting=True,
                          polishing=c.osqp_polishing == "enabled", eps_abs=c.osqp_eps, eps_rel=c.osqp_eps,
                          max_iter=c.osqp_max_iter)

    def _set_boxes(self) -> None:
        c, n = self.cfg, self.n
        r = self.n_eq
        for k in range(n):
            last = k == n - 1 and c.terminal_set == "hover"
            vmax = 0.0 if last else c.speed_max_mps
            amax = 0.0 if last else c.accel_max_mps2
            self.l[r:r + 3], self.u[r:r + 3] = -vmax, vmax
            self.l[r + 3:r + 6], self.u[r + 3:r + 6] = -amax, amax
            r += 6
            self.l[r:r + 3], self.u[r:r + 3] = -c.jerk_max_mps3, c.jerk_max_mps3
            self.l[r + 3], self.u[r + 3] = -c.yaw_rate_max_rps, c.yaw_rate_max_rps
            r += _NW
        self.l[r:r + self.n_soft], self.u[r:r + self.n_soft] = 0.0, np.inf

    # ------------------------------------------------------------------ one tick
    def _check_state(self, z0) -> np.ndarray:
        """``z0`` as 10 finite floats ``(p, v, a, psi)``."""
        try:
            z = np.asarray(z0, float)
        except (TypeError, ValueError):
            raise EstimationError(f"MPC state: expected 10 numbers (p, v, a, psi), got {type(z0).__name__}") \
                from None
        if z.shape != (_NZ,):
            raise EstimationError(f"MPC state: expected shape ({_NZ},) (p, v, a, psi), got {z.shape}")
        if not np.all(np.isfinite(z)):
            raise EstimationError(f"MPC state: not finite ({np.array2string(z, precision=3)})")
        return z

    def _why(self, z0: np.ndarray) -> str:
        """What of the start state breaks the bounds (for the infeasibility message), or ''."""
        c = self.cfg
        v, a = float(np.abs(z0[3:6]).max()), float(np.abs(z0[6:9]).max())
        if v > c.speed_max_mps:
            return f": the start's speed {v:g} m/s on an axis is above speed_max_mps {c.speed_max_mps:g}"
        if a > c.accel_max_mps2:
            return f": the start's acceleration {a:g} m/s^2 on an axis is above accel_max_mps2 {c.accel_max_mps2:g}"
        return ""

    def _initial_guess(self, z0: np.ndarray) -> np.ndarray:
        """Previous prediction (for linearization); at the first tick: hold position and yaw."""
        if self.z_prev is None:
            return np.tile(z0, (self.n, 1))
        return self.z_prev

    def solve(self, z0: np.ndarray, trunk: int | None = None) -> MpcSolution:
        """One QP from flat state ``z0`` (10,) in g; ``trunk`` is the current trunk index (perception mode)."""
        c, n = self.cfg, self.n
        z0 = self._check_state(z0)
        if self.mode == "perception" and trunk is not None:
            assert self.field is not None
            trunk = self.field._index(trunk, "trunk")
        # the QP works relative to the current position and yaw (small numbers: OSQP's tolerances are absolute)
        origin, yaw0 = z0[:3].copy(), float(z0[9])
        z0s = z0.copy()
        z0s[:3] = 0.0
        z0s[9] = 0.0
        # reference along the taught path at the desired speed
        s_now = float(self.reference.path.error(z0[:3]).along_track)
        self.progress_m = max(self.progress_m, min(s_now, self.reference.length))
        s_ref = self.progress_m + c.speed_mps * c.dt_s * np.arange(1, n + 1)
        r_pos, r_yaw = self.reference.at(s_ref)
        r_pos = r_pos - origin
        r_yaw = wrap_angle(r_yaw - yaw0)
        for k in range(n):
            self.q[self._iz(k):self._iz(k) + 3] = -2.0 * c.q_position * r_pos[k]
            self.q[self._iz(k) + 9] = -2.0 * c.q_yaw * r_yaw[k]
        self.l[:_NZ] = self.u[:_NZ] = self.Ad @ z0s
        guess = self._initial_guess(z0)
        trunks = None
        vals = self._coo_vals
        i0 = self._path_coo_start
        rr = self.path_row0
        if self.mode == "fixed":
            err = self.reference.path.error(guess[:, :3])
            seg = err.segment
            for k in range(n):
                ref_pt = err.reference_point[k] - origin
                for j, normal in enumerate((self.reference.path.left_normals[seg[k]],
                                            self.reference.path.up_normals[seg[k]])):
                    off = float(normal @ ref_pt)
                    for sign_i, sign in enumerate((1.0, -1.0)):  # n.p + s >= off - d ; -n.p + s >= -off - d
                        row = rr + 4 * k + 2 * j + sign_i
                        vals[i0:i0 + 3] = sign * normal
                        vals[i0 + 3] = 0.0
                        vals[i0 + 4] = 1.0
                        i0 += 5
                        self.l[row], self.u[row] = sign * off - self.bound, np.inf
        elif self.mode == "perception":
            assert self.field is not None
            start = int(trunk) if trunk is not None else self.field.nearest_trunk(z0[:3])
            axes = None if self.camera_axis_g is None else np.broadcast_to(self.camera_axis_g, (n, 3))
            ev = self.field.evaluate(guess[:, :3], guess[:, 9], previous=start, axes=axes)
            trunks = ev.trunk
            assert ev.dg_dpos is not None and ev.dg_dyaw is not None
            # g0 + dg.(y - y0) >= margin - s   <=>   dg.y + s >= margin - g0 + dg.y0
            rhs = c.perception_margin - ev.g + np.einsum("nk,nk->n", ev.dg_dpos, guess[:, :3] - origin) \
                + ev.dg_dyaw * (guess[:, 9] - yaw0)
            # rows with steep gradients are divided by the gradient norm (OSQP conditioning); the
            # slack is then in metres, else in inliers
            scale = 1.0 / np.maximum(np.sqrt(np.einsum("nk,nk->n", ev.dg_dpos, ev.dg_dpos) + ev.dg_dyaw**2), 1.0)
            for k in range(n):
                vals[i0:i0 + 3] = ev.dg_dpos[k] * scale[k]
                vals[i0 + 3] = ev.dg_dyaw[k] * scale[k]
                vals[i0 + 4] = 1.0
                i0 += 5
                self.l[rr + k], self.u[rr + k] = rhs[k] * scale[k], np.inf
        self.solver.update(q=self.q, l=self.l, u=self.u, Ax=vals[self._perm])
        res = self.solver.solve(raise_error=False)  # status checked below (max_iter: best iterate)
        status = str(res.info.status)
        x = res.x
        if status not in ACCEPTED_STATUS or x is None or not np.all(np.isfinite(x)):
            self.z_prev = None          # the next tick linearizes about a hold, not about this iterate
            raise MpcInfeasible(f"MPC: OSQP did not solve the tick's QP ({status}{self._why(z0)}); no command "
                                "(the caller's fallback applies)")
        z_pred = x[: n * _NZ].reshape(n, _NZ).copy()
        z_pred[:, :3] += origin
        z_pred[:, 9] += yaw0
        w_pred = x[n * _NZ: n * (_NZ + _NW)].reshape(n, _NW)
        slack = float(x[self._is(0):].max()) if self.n_soft else 0.0
        self.z_prev = z_pred
        return MpcSolution(w_pred[0].copy(), z_pred, w_pred, max(slack, 0.0), status, int(res.info.iter), trunks)


__all__ = ["MpcInfeasible", "MpcSolution", "PerceptionAwareMPC", "TaughtPathReference"]
