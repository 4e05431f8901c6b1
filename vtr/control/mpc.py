"""Perception-aware flatness-based MPC (thesis ch. 3 eq. 3.8 with the chance constraint of §7.3.3): one OSQP quadratic
program per outer-loop tick over the linear flat model (:mod:`vtr.control.flat_model`), tracking a reference along the
taught path in the direction of travel (:class:`TaughtPathReference`) under box bounds, softened path rows (none, a
fixed tube, or the field's perception constraint linearized about the previous plan) and a hover terminal set; a speed
governor slows the reference where the plan cannot keep the constraint, and a QP OSQP does not solve raises
``MpcInfeasible``. The problem, the governor, recursive feasibility, errors and the solver:
docs/perception_aware_mpc/README.md, "The controller"."""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Literal

import numpy as np
import scipy.sparse as sp

from perception_model.frames import wrap_angle

from ..config import ControlConfig
from ..errors import EstimationError
from ..navigation.trunk import FORWARD
from ..state.controller import MIN_SEGMENT_LENGTH_M, ReferencePath
from .field import TaughtPathField, check_direction
from .flat_model import N_INPUT, N_STATE, discrete_model

Mode = Literal["none", "fixed", "perception"]
#: The camera the perception rows see: on its mount (turns with the yaw), or a gimbal holding each step's
#: trunk's taught axis; a (3,) array is a gimbal holding that one axis in g.
CAMERA_MOUNT, CAMERA_TAUGHT_AXIS = "mount", "taught"
_NZ, _NW = N_STATE, N_INPUT
_ROW_STATES = (0, 1, 2, 9, 3, 4, 5)  # the states a path row reads (position, yaw, velocity)
_ROW = len(_ROW_STATES) + 1  # ... and its slack
ACCEPTED_STATUS = ("solved", "solved inaccurate", "maximum iterations reached")


class MpcInfeasible(EstimationError):
    """The tick's QP has no solution OSQP could find (infeasible start, inconsistent bounds): no command."""


@dataclass(frozen=True)
class MpcSolution:
    """One tick: the input to apply, the predicted flat states (N, 10), slacks and solver status.

    ``max_slack_m``: the largest slack of the fixed path rows (metres); ``max_slack_inliers``: of the
    perception rows (inliers). ``trunk`` and ``flag`` (N,): the predicted steps' trunks and field flags
    (perception mode, else None).
    """

    w: np.ndarray
    z_pred: np.ndarray
    w_pred: np.ndarray
    max_slack_m: float
    max_slack_inliers: float
    status: str
    iterations: int
    trunk: np.ndarray | None
    flag: np.ndarray | None = None


class TaughtPathReference:
    """The taught path (vehicle positions in g) as a reference in the direction of travel.

    ``direction`` +1 follows the taught order, -1 the route flown backward (the points reversed: arc length,
    ``path`` errors and progress count along travel; ``path.error(p).lateral`` is left of travel).
    ``yaw_g`` (K,), the taught vehicles' yaw in taught order, enables the ``"as_taught"`` yaw reference.
    """

    def __init__(self, positions_g: np.ndarray, direction: int = FORWARD, yaw_g: np.ndarray | None = None) -> None:
        p = np.asarray(positions_g, float)
        if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
            raise EstimationError(f"reference: expected finite positions of shape (K, 3), got {p.shape}")
        self.direction = check_direction(direction)
        order = np.arange(len(p)) if self.direction == FORWARD else np.arange(len(p))[::-1]
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p[order], axis=0), axis=1) > MIN_SEGMENT_LENGTH_M])
        self.taught_index = order[keep]  # travel-order point -> taught vertex index
        self.path = ReferencePath(p[self.taught_index])
        d = self.path.directions
        self.heading = np.arctan2(d[:, 1], d[:, 0])  # along travel, per segment
        self.taught_yaw = None
        if yaw_g is not None:
            y = np.asarray(yaw_g, float)
            if y.shape != (len(p),) or not np.all(np.isfinite(y)):
                raise EstimationError(f"reference yaw_g: expected {len(p)} finite angles, got shape {y.shape}")
            self.taught_yaw = y[self.taught_index]

    @classmethod
    def from_field(cls, field: TaughtPathField, direction: int = FORWARD) -> TaughtPathReference:
        """The field's taught vehicles (positions and yaw) in the direction of travel."""
        return cls(field.vehicle_position_g, direction, field.vehicle_yaw_g)

    @property
    def length(self) -> float:
        return self.path.length

    def at(self, s: np.ndarray, yaw: str = "along_travel") -> tuple[np.ndarray, np.ndarray]:
        """Points (K, 3) and yaw (K,) at travel arc lengths ``s`` (clipped to the path); ``yaw``
        ``"along_travel"`` (the segment's heading) or ``"as_taught"`` (taught yaw, interpolated)."""
        s = np.clip(np.asarray(s, float), 0.0, self.path.length)
        seg = np.clip(np.searchsorted(self.path.cumulative, s, side="right") - 1, 0, len(self.path.lengths) - 1)
        frac = s - self.path.cumulative[seg]
        pts = self.path.points[seg] + frac[:, None] * self.path.directions[seg]
        if yaw == "along_travel":
            return pts, self.heading[seg]
        if yaw != "as_taught":
            raise EstimationError(f"yaw reference: expected along_travel or as_taught, got {yaw!r}")
        if self.taught_yaw is None:
            raise EstimationError(
                "yaw reference as_taught needs the taught yaw (TaughtPathReference(yaw_g=...) "
                "or TaughtPathReference.from_field)"
            )
        t = frac / self.path.lengths[seg]
        a, b = self.taught_yaw[seg], self.taught_yaw[seg + 1]
        return pts, a + t * wrap_angle(b - a)


class PerceptionAwareMPC:
    """The MPC of the module docstring for one path-row ``mode``; call :meth:`solve` once per tick.

    The direction of travel is the ``reference``'s. ``camera``: ``"mount"`` (default; the camera mount of
    ``field``, the axis turns with the vehicle's yaw), ``"taught"`` (a gimbal holding each step's trunk's
    taught optical axis, the thesis' experiment) or a (3,) axis in g (a gimbal holding that one axis).
    """

    def __init__(
        self,
        reference: TaughtPathReference,
        config: ControlConfig | None = None,
        *,
        mode: Mode = "perception",
        fixed_bound_m: float = 0.0,
        field: TaughtPathField | None = None,
        camera: str | np.ndarray = CAMERA_MOUNT,
    ) -> None:
        import osqp  # osqp (~0.1 s) only when a controller is built

        self.cfg = c = config or ControlConfig()
        if mode not in ("none", "fixed", "perception"):
            raise EstimationError(f"unknown MPC mode {mode!r}")
        if mode == "perception" and field is None:
            raise EstimationError("the perception-aware MPC needs a TaughtPathField")
        if mode == "fixed" and not fixed_bound_m > 0.0:
            raise EstimationError(f"a fixed path-error bound must be positive, got {fixed_bound_m}")
        if mode == "fixed" and not np.isfinite(fixed_bound_m):
            raise EstimationError(f"a fixed path-error bound must be finite, got {fixed_bound_m}")
        if field is not None:  # ControlConfig owns l_min, c_bar, the form (the field's landmarks are shared)
            field = field.with_bounds(c.l_min, c.c_bar, form=c.constraint_form, control=c)
        self.reference, self.mode, self.bound, self.field = reference, mode, float(fixed_bound_m), field
        self.direction = reference.direction
        if c.yaw_reference == "as_taught" and reference.taught_yaw is None:
            raise EstimationError("yaw_reference as_taught needs the taught yaw: TaughtPathReference.from_field")
        self.camera_axis_g: np.ndarray | None = None
        if isinstance(camera, str):
            if camera not in (CAMERA_MOUNT, CAMERA_TAUGHT_AXIS):
                raise EstimationError(
                    f"camera: expected {CAMERA_MOUNT!r}, {CAMERA_TAUGHT_AXIS!r} or a 3-vector, got {camera!r}"
                )
            self.camera = camera
        else:
            axis = np.asarray(camera, float)
            if axis.shape != (3,) or not np.all(np.isfinite(axis)) or not np.linalg.norm(axis) > 0:
                raise EstimationError(f"camera: expected a finite non-zero 3-vector axis, got {axis!r}")
            self.camera, self.camera_axis_g = "axis", axis
        n = self.n = int(c.horizon)
        self.Ad, self.Bd = discrete_model(c.dt_s)
        self.rows_per_step = {"none": 0, "fixed": 4, "perception": 1}[mode]
        self.n_soft = n if self.rows_per_step else 0
        self.nx = n * _NZ + n * _NW + self.n_soft
        self._build(osqp)
        self.z_prev: np.ndarray | None = None
        self.progress_m: float | None = None  # along travel; set by the first tick (start anywhere)
        self.reference_speed_mps = float(c.speed_mps)  # the speed governor's (module docstring)

    def field_kwargs(self, n: int) -> dict:
        """The camera keywords of :meth:`TaughtPathField.evaluate` / ``select_trunks`` for ``n`` steps."""
        if self.camera == CAMERA_TAUGHT_AXIS:
            return {"taught_axes": True}
        if self.camera_axis_g is not None:
            return {"axes": np.broadcast_to(self.camera_axis_g, (n, 3))}
        return {}

    # ------------------------------------------------------------------ indices
    def _iz(self, k: int) -> int:  # state z_{k+1}, k = 0..N-1
        return k * _NZ

    def _iw(self, k: int) -> int:
        return self.n * _NZ + k * _NW

    def _is(self, k: int) -> int:
        return self.n * (_NZ + _NW) + k

    def _build(self, osqp: ModuleType) -> None:
        c, n = self.cfg, self.n
        # cost: 1/2 x' P x + q' x  (P = 2 Q on outputs, 2 R on inputs)
        pd = np.zeros(self.nx)
        for k in range(n):
            pd[self._iz(k) : self._iz(k) + 3] = 2.0 * c.q_position
            pd[self._iz(k) + 9] = 2.0 * c.q_yaw
            pd[self._iw(k) : self._iw(k) + 3] = 2.0 * c.r_jerk
            pd[self._iw(k) + 3] = 2.0 * c.r_yaw_rate
        if self.n_soft:
            pd[self._is(0) :] = c.slack_quadratic_weight  # strictly convex in the slacks (plus the L1 term in q)
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
        # path rows: pattern (x, y, z, psi, vx, vy, vz of z_{k+1}, slack k); values set every tick
        self._path_coo_start = len(vals)
        self.path_row0 = r
        for k in range(n):
            for _ in range(self.rows_per_step):
                for i in _ROW_STATES:
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
            self.q[self._is(0) :] = c.slack_weight
        self.solver = osqp.OSQP()
        self.solver.setup(
            self.P,
            self.q,
            self.A,
            self.l,
            self.u,
            verbose=False,
            warm_starting=True,
            polishing=c.osqp_polishing == "enabled",
            eps_abs=c.osqp_eps,
            eps_rel=c.osqp_eps,
            max_iter=c.osqp_max_iter,
        )

    def _set_boxes(self) -> None:
        c, n = self.cfg, self.n
        r = self.n_eq
        for k in range(n):
            last = k == n - 1 and c.terminal_set == "hover"
            vmax = 0.0 if last else c.speed_max_mps
            amax = 0.0 if last else c.accel_max_mps2
            self.l[r : r + 3], self.u[r : r + 3] = -vmax, vmax
            self.l[r + 3 : r + 6], self.u[r + 3 : r + 6] = -amax, amax
            r += 6
            self.l[r : r + 3], self.u[r : r + 3] = -c.jerk_max_mps3, c.jerk_max_mps3
            self.l[r + 3], self.u[r + 3] = -c.yaw_rate_max_rps, c.yaw_rate_max_rps
            r += _NW
        self.l[r : r + self.n_soft], self.u[r : r + self.n_soft] = 0.0, np.inf

    # ------------------------------------------------------------------ one tick
    def _check_state(self, z0: object) -> np.ndarray:
        """``z0`` as 10 finite floats ``(p, v, a, psi)``."""
        try:
            z = np.asarray(z0, float)
        except (TypeError, ValueError):
            raise EstimationError(f"MPC state: expected 10 numbers (p, v, a, psi), got {type(z0).__name__}") from None
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
        # reference along the taught path, in the direction of travel, at the desired speed
        s_now = min(float(self.reference.path.error(z0[:3]).along_track), self.reference.length)
        self.progress_m = s_now if self.progress_m is None else max(self.progress_m, s_now)
        s_ref = self.progress_m + self.reference_speed_mps * c.dt_s * np.arange(1, n + 1)
        r_pos, r_yaw = self.reference.at(s_ref, c.yaw_reference)
        r_pos = r_pos - origin
        r_yaw = wrap_angle(r_yaw - yaw0)
        for k in range(n):
            self.q[self._iz(k) : self._iz(k) + 3] = -2.0 * c.q_position * r_pos[k]
            self.q[self._iz(k) + 9] = -2.0 * c.q_yaw * r_yaw[k]
        self.l[:_NZ] = self.u[:_NZ] = self.Ad @ z0s
        guess = self._initial_guess(z0)
        trunks = flags = None
        unit = np.ones(n)  # inliers per unit of each perception row's slack
        vals = self._coo_vals
        i0 = self._path_coo_start
        rr = self.path_row0
        if self.mode == "fixed":
            err = self.reference.path.error(guess[:, :3])
            seg = err.segment
            for k in range(n):
                ref_pt = err.reference_point[k] - origin
                for j, normal in enumerate(
                    (self.reference.path.left_normals[seg[k]], self.reference.path.up_normals[seg[k]])
                ):
                    off = float(normal @ ref_pt)
                    for sign_i, sign in enumerate((1.0, -1.0)):  # n.p + s >= off - d ; -n.p + s >= -off - d
                        row = rr + 4 * k + 2 * j + sign_i
                        vals[i0 : i0 + _ROW] = 0.0
                        vals[i0 : i0 + 3] = sign * normal
                        vals[i0 + _ROW - 1] = 1.0
                        i0 += _ROW
                        self.l[row], self.u[row] = sign * off - self.bound, np.inf
        elif self.mode == "perception":
            assert self.field is not None
            start = int(trunk) if trunk is not None else self.field.nearest_trunk(z0[:3])
            ev = self.field.evaluate(
                guess[:, :3], guess[:, 9], previous=start, direction=self.direction, **self.field_kwargs(n)
            )
            trunks, flags = ev.trunk, ev.flag
            assert ev.dg_dpos is not None and ev.dg_dyaw is not None
            # g0 + dg.(y - y0) - b u.v >= margin - s   <=>   dg.y - b u.v + s >= margin - g0 + dg.y0
            rhs = (
                c.perception_margin
                - ev.g
                + np.einsum("nk,nk->n", ev.dg_dpos, guess[:, :3] - origin)
                + ev.dg_dyaw * (guess[:, 9] - yaw0)
            )
            dv = np.zeros((n, 3))
            if c.intersample == "velocity":
                v0 = guess[:, 3:6]
                speed0 = np.linalg.norm(v0, axis=1)
                u = np.divide(v0, speed0[:, None], out=np.zeros_like(v0), where=speed0[:, None] > 0.0)
                dv = -(0.5 * c.dt_s * np.linalg.norm(ev.dg_dpos, axis=1))[:, None] * u
            # rows with steep gradients are divided by the gradient norm (OSQP conditioning); the
            # slack is then in metres, else in inliers
            unit = np.maximum(np.sqrt(np.einsum("nk,nk->n", ev.dg_dpos, ev.dg_dpos) + ev.dg_dyaw**2), 1.0)
            scale = 1.0 / unit
            row = rr
            for k in range(n):
                vals[i0 : i0 + 3] = ev.dg_dpos[k] * scale[k]
                vals[i0 + 3] = ev.dg_dyaw[k] * scale[k]
                vals[i0 + 4 : i0 + 7] = dv[k] * scale[k]
                vals[i0 + 7] = 1.0
                i0 += _ROW
                self.l[row], self.u[row] = rhs[k] * scale[k], np.inf
                row += 1
        self.solver.update(q=self.q, l=self.l, u=self.u, Ax=vals[self._perm])
        res = self.solver.solve(raise_error=False)  # status checked below (max_iter: best iterate)
        status = str(res.info.status)
        x = res.x
        if status not in ACCEPTED_STATUS or x is None or not np.all(np.isfinite(x)):
            self.z_prev = None  # the next tick linearizes about a hold, not about this iterate
            raise MpcInfeasible(
                f"MPC: OSQP did not solve the tick's QP ({status}{self._why(z0)}); no command "
                "(the caller's fallback applies)"
            )
        z_pred = x[: n * _NZ].reshape(n, _NZ).copy()
        z_pred[:, :3] += origin
        z_pred[:, 9] += yaw0
        w_pred = x[n * _NZ : n * (_NZ + _NW)].reshape(n, _NW)
        slack = np.maximum(x[self._is(0) :], 0.0) if self.n_soft else np.zeros(0)
        slack_m = float(slack.max()) if self.mode == "fixed" and slack.size else 0.0
        slack_inliers = float((slack * unit).max()) if self.mode == "perception" and slack.size else 0.0
        self.z_prev = z_pred
        plan_low = False
        if self.mode == "perception" and c.governor_check == "plan":
            assert self.field is not None and trunks is not None
            true = self.field.evaluate(
                z_pred[:, :3], z_pred[:, 9], trunk=trunks, gradient=False, **self.field_kwargs(n)
            )
            plan_low = bool(true.g.min() < 0.0)
        if plan_low or slack_inliers > c.perception_margin:  # the plan cannot keep the constraint at this speed
            self.reference_speed_mps *= c.speed_governor
        else:  # recover toward the desired speed at accel_max
            self.reference_speed_mps = min(c.speed_mps, self.reference_speed_mps + c.accel_max_mps2 / c.rate_hz)
        return MpcSolution(
            w_pred[0].copy(), z_pred, w_pred, slack_m, slack_inliers, status, int(res.info.iter), trunks, flags
        )


__all__ = ["MpcInfeasible", "MpcSolution", "PerceptionAwareMPC", "TaughtPathReference"]
