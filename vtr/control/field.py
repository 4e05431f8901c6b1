"""The taught-path perception field: every taught vertex's landmarks in its own controller frame o, built once from a
taught map and a perception model, and a horizon's constraint evaluated against each step's trunk (trunk selection is
the localizer's rule, :mod:`vtr.navigation.trunk`). Validity per step (distance to the trunk and the path, off the
route past its ends) and the gradient guard where the constraint's gradient points away from the landmarks; errors of
``perception_model`` raised through the field are :class:`PerceptionFieldError`. Frames, mount and rules:
docs/perception_aware_mpc/README.md."""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, TypeVar, cast

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from perception_model import frames
from perception_model.errors import PerceptionModelError
from perception_model.horizon import OFF_ROUTE, HorizonEvaluation, HorizonEvaluator, TrunkLandmarks
from perception_model.model import PerceptionModel
from perception_model.settings import THESIS_C_BAR, THESIS_L_MIN

from ..config import ControlConfig, LocalizationConfig
from ..errors import EstimationError, MapError
from ..geometry import inv_T
from ..map import Map
from ..navigation.trunk import BACKWARD, FORWARD, trunk_cost, trunk_window

F = TypeVar("F", bound=Callable[..., Any])

#: The chance constraint's two forms (thesis eqs. 7.7 and 7.8): ``mu - c_bar sigma`` and ``mu - c_bar sqrt(mu)``.
CONSTRAINT_FORMS = ("normal", "conservative")


class PerceptionFieldError(EstimationError, PerceptionModelError):
    """A ``perception_model`` error raised through the field: caught by ``except VtrError`` (and still by
    ``except PerceptionModelError``); the original is its ``__cause__``."""


@contextmanager
def perception_errors() -> Iterator[None]:
    """Re-raise ``perception_model`` errors as :class:`PerceptionFieldError` (the ``vtr.control`` boundary)."""
    try:
        yield
    except PerceptionFieldError:
        raise
    except PerceptionModelError as err:
        raise PerceptionFieldError(f"perception model: {err}") from err


def translating(method: F) -> F:
    """``method`` with :func:`perception_errors` around its body (the field's public methods)."""

    @functools.wraps(method)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with perception_errors():
            return method(*args, **kwargs)

    return cast(F, wrapper)


def check_direction(direction: object) -> int:
    """``direction`` as +1 (taught order) or -1 (the route flown backward); EstimationError otherwise."""
    if isinstance(direction, bool) or direction not in (FORWARD, BACKWARD):
        raise EstimationError(
            f"direction: expected {FORWARD} (taught order) or {BACKWARD} (reversed), got {direction!r}"
        )
    return int(direction)


@dataclass(frozen=True)
class CameraMount:
    """Camera on the vehicle: axis yaw from the vehicle's x axis (rad) and lever arm (m, vehicle FLU)."""

    mount_yaw_rad: float = 0.0
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class TaughtVertex:
    """A privileged vertex read from a map: camera pose and finite landmarks, both in the map frame."""

    vertex_id: int
    T_map_camera: np.ndarray
    points_map: np.ndarray


def read_taught_vertices(vtr_map: Map) -> list[TaughtVertex]:
    """Every privileged vertex with its landmarks in the map frame, in path order (MapError without a teach)."""
    path = vtr_map.taught_path()
    out = []
    for vid, T_mv in zip(path.ids, path.T_world_vertex, strict=True):
        rec = vtr_map.vertex(int(vid))
        pts = np.asarray(rec.frame.points, float)[rec.landmark_mask]
        out.append(TaughtVertex(int(vid), np.asarray(T_mv, float), pts @ T_mv[:3, :3].T + T_mv[:3, 3]))
    return out


@dataclass(frozen=True)
class FieldEvaluation:
    """Constraint along a horizon of vehicle outputs ``(p, psi)`` in g; gradients w.r.t. the vehicle outputs.

    ``g`` (N,) is the field's ``form`` (``"normal"``: mu - c_bar sigma - l_min; ``"conservative"``:
    mu - c_bar sqrt(mu) - l_min). ``dg_dpos`` (N, 3), ``dg_dyaw`` (N,) (vehicle yaw: axis yaw and lever arm),
    ``dg_daxis`` (N, 3) (the optical axis, for a gimbal): the gradient of ``g``, except on ``guarded`` steps
    (``mu < c_bar**2 / 4``, where ``g`` grows as ``mu`` falls), which carry the gradient of ``mu``.
    ``vertex_id`` (N,) each step's trunk; ``flag`` as in ``perception_model.horizon`` (``OFF_ROUTE`` first).
    ``trunk_distance_m`` (N,): vehicle to its trunk's taught vehicle; ``path_distance_m`` (N,): to the taught
    path (the polyline through the taught vehicles); ``past_end_m`` (N,): how far beyond the route's first or
    last vertex along its end segment (0 within). ``raw`` is the evaluator's record (camera-centre gradients).
    """

    trunk: np.ndarray
    vertex_id: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray
    g: np.ndarray
    flag: np.ndarray
    dg_dpos: np.ndarray | None
    dg_dyaw: np.ndarray | None
    dg_daxis: np.ndarray | None
    raw: HorizonEvaluation
    trunk_distance_m: np.ndarray
    path_distance_m: np.ndarray
    past_end_m: np.ndarray
    guarded: np.ndarray
    form: str = "normal"

    @property
    def off_route(self) -> np.ndarray:
        """(N,) bool: the steps flagged ``OFF_ROUTE``."""
        return self.flag == OFF_ROUTE


class TaughtPathField:
    """The perception chance constraint over the whole taught path (value and gradient for a horizon)."""

    @translating
    def __init__(
        self,
        model: PerceptionModel,
        vertices: list[TaughtVertex],
        *,
        T_g_map: np.ndarray,
        mount: CameraMount | None = None,
        config: LocalizationConfig | None = None,
        l_min: float = THESIS_L_MIN,
        c_bar: float = THESIS_C_BAR,
        control: ControlConfig | None = None,
        form: str = "normal",
    ) -> None:
        if not vertices:
            raise MapError("the taught path is empty")
        _check_bounds(l_min, c_bar)
        self.form = _check_form(form)
        self.mount = mount or CameraMount()
        self.config = config or LocalizationConfig()
        control = control or ControlConfig()
        self.off_route_distance_m = float(control.off_route_distance_m)
        self.off_route_past_end_m = float(control.off_route_past_end_m)
        self.T_g_map = np.asarray(T_g_map, float)
        lever = np.asarray(self.mount.lever_arm_m, float)
        T_g_cam = self.T_g_map[None] @ np.stack([v.T_map_camera for v in vertices])
        heading, pitch = frames.heading_of_axis(T_g_cam[:, :3, 2])
        yaw = frames.wrap_angle(heading - self.mount.mount_yaw_rad)
        centres = T_g_cam[:, :3, 3]
        positions = centres - np.einsum("kij,j->ki", frames.rot_z(yaw), lever)
        trunks = []
        for i, v in enumerate(vertices):
            pts_g = v.points_map @ self.T_g_map[:3, :3].T + self.T_g_map[:3, 3]
            p_is_o, _ = frames.to_trunk_frame(pts_g, 0.0, centres[i], yaw[i])
            trunks.append(
                TrunkLandmarks(v.vertex_id, positions[i], float(yaw[i]), lever.copy(), p_is_o, float(pitch[i]))
            )
        self.vertex_ids = np.array([v.vertex_id for v in vertices], dtype=np.int64)
        self.T_g_camera = T_g_cam
        self.vehicle_position_g = positions
        self.vehicle_yaw_g = np.asarray(yaw, float)
        self.pitch_down = np.asarray(pitch, float)
        self.evaluator = HorizonEvaluator(model, trunks, l_min=l_min, c_bar=c_bar)
        self._path = _TaughtPolyline(positions)

    @classmethod
    @translating
    def from_map(
        cls,
        vtr_map: Map,
        model: PerceptionModel,
        *,
        up_map: ArrayLike | None = None,
        mount: CameraMount | None = None,
        config: LocalizationConfig | None = None,
        l_min: float = THESIS_L_MIN,
        c_bar: float = THESIS_C_BAR,
        control: ControlConfig | None = None,
        form: str = "normal",
    ) -> TaughtPathField:
        """Read every taught vertex of ``vtr_map`` (open) once. g is the map's gravity frame: up is ``up_map`` when
        given (an override), else the map's stored gravity (``Map.gravity_up``), else a level first camera's."""
        if up_map is None:
            stored = vtr_map.gravity_up
            up_map = frames.LEVEL_CAMERA_UP if stored is None else stored
        T_g_map = frames.T_g_map_from_up(up_map)
        return cls(
            model,
            read_taught_vertices(vtr_map),
            T_g_map=T_g_map,
            mount=mount,
            config=config,
            l_min=l_min,
            c_bar=c_bar,
            control=control,
            form=form,
        )

    def __len__(self) -> int:
        return len(self.vertex_ids)

    @property
    def l_min(self) -> float:
        return self.evaluator.l_min

    @property
    def c_bar(self) -> float:
        return self.evaluator.c_bar

    def with_bounds(
        self, l_min: float, c_bar: float, form: str | None = None, control: ControlConfig | None = None
    ) -> TaughtPathField:
        """The same field (landmarks shared, not copied) with the constraint ``mu - c_bar sigma - l_min``
        (or ``form``, and the off-route limits of ``control`` when given); the MPC uses it so that its
        ``ControlConfig`` owns ``l_min``, ``c_bar``, the form and the limits."""
        _check_bounds(l_min, c_bar)
        out = copy.copy(self)
        out.evaluator = copy.copy(self.evaluator)
        out.evaluator.l_min, out.evaluator.c_bar = float(l_min), float(c_bar)
        if form is not None:
            out.form = _check_form(form)
        if control is not None:
            out.off_route_distance_m = float(control.off_route_distance_m)
            out.off_route_past_end_m = float(control.off_route_past_end_m)
        return out

    def _index(self, value: object, what: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or not 0 <= int(value) < len(self):
            raise EstimationError(f"{what}: {value!r} is not a trunk index (0 to {len(self) - 1})")
        return int(value)

    def _horizon(
        self, positions: ArrayLike, yaw: ArrayLike, axes: ArrayLike | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Positions (N, 3), yaw (N,) and axes (N, 3) checked: finite, shapes that fit, N >= 1."""
        pos = np.asarray(positions, float) if not isinstance(positions, str) else np.array(np.nan)
        if pos.ndim == 1:
            pos = pos[None]
        if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) == 0:
            raise EstimationError(f"positions: expected shape (N, 3) with N >= 1, got {np.shape(positions)}")
        n = len(pos)
        psi = np.asarray(yaw, float)
        if psi.shape not in ((), (n,)):
            raise EstimationError(f"yaw: expected shape ({n},) to match the positions, got {psi.shape}")
        psi = np.broadcast_to(psi, (n,))
        ax = None
        if axes is not None:
            ax = np.asarray(axes, float)
            if ax.shape not in ((3,), (n, 3)):
                raise EstimationError(f"axes: expected shape ({n}, 3), got {ax.shape}")
            ax = np.broadcast_to(ax, (n, 3))
            if not np.all(np.isfinite(ax)) or np.any(np.linalg.norm(ax, axis=1) == 0.0):
                raise EstimationError("axes: must be finite and non-zero")
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(psi))):
            raise EstimationError("positions and yaw must be finite (got NaN or inf)")
        return pos, psi, ax

    # ----------------------------------------------------------------- vehicle <-> camera
    @translating
    def camera_centres(self, positions: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """Camera centres (N, 3) in g of vehicles at ``positions`` (N, 3) with yaw ``yaw`` (N,)."""
        return frames.camera_position(positions, yaw, self.mount.lever_arm_m)

    @translating
    def camera_poses(self, positions: np.ndarray, yaw: np.ndarray, pitch_down: float | np.ndarray) -> np.ndarray:
        """``T_g_camera`` (N, 4, 4) of level vehicles (camera pitched ``pitch_down`` below the horizon)."""
        yaw = np.asarray(yaw, float)
        T = np.tile(np.eye(4), (len(yaw), 1, 1))
        T[:, :3, :3] = frames.camera_rotation(yaw, pitch_down, self.mount.mount_yaw_rad)
        T[:, :3, 3] = self.camera_centres(positions, yaw)
        return T

    # ----------------------------------------------------------------- trunk selection
    def nearest_trunk(self, position: np.ndarray) -> int:
        """Index of the taught vertex whose vehicle position is nearest (to start a chain)."""
        p = np.asarray(position, float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise EstimationError(f"position: expected 3 finite numbers, got shape {p.shape}")
        return int(np.argmin(np.linalg.norm(self.vehicle_position_g - p, axis=1)))

    @translating
    def select_trunks(
        self,
        positions: np.ndarray,
        yaw: np.ndarray,
        previous: int,
        axes: np.ndarray | None = None,
        direction: int = FORWARD,
        *,
        taught_axes: bool = False,
    ) -> np.ndarray:
        """Trunk index (N,) of each predicted vehicle pose by the localizer's rule (:mod:`vtr.navigation.trunk`),
        starting from ``previous``; ``direction`` -1 for a route flown backward (the window mirrors).

        The camera's attitude comes from the vehicle yaw and the mount, or from ``axes`` (N, 3) (gimbal), or,
        with ``taught_axes``, from a gimbal holding each candidate's taught axis (the relative rotation is then
        the identity and the rule compares camera centres).
        """
        pos, yaw, axes = self._horizon(positions, yaw, axes)
        previous = self._index(previous, "previous trunk")
        direction = check_direction(direction)
        if taught_axes and axes is not None:
            raise EstimationError("axes: give explicit axes or taught_axes, not both")
        c = self.config
        n = len(pos)
        prev = int(previous)
        if taught_axes:
            cam = self.camera_centres(pos, yaw)
        else:
            axes_pitch = None
            if axes is not None:
                heading, axes_pitch = frames.heading_of_axis(axes)
                yaw = heading - self.mount.mount_yaw_rad
            pitch = self.pitch_down[prev] if axes_pitch is None else np.asarray(axes_pitch, float)
            T_l_g = inv_T(self.camera_poses(pos, yaw, pitch))

        def window(previous: int) -> tuple[int, int]:
            return trunk_window(previous, len(self), c.trunk_window_back, c.trunk_window_forward, direction)

        def costs(lo: int, hi: int, first: int) -> np.ndarray:
            """Every step's cost from ``first`` on (rows) against candidates ``lo..hi-1`` (columns), in one batch."""
            if taught_axes:
                return np.linalg.norm(cam[first:, None] - self.T_g_camera[None, lo:hi, :3, 3], axis=2)
            return trunk_cost(T_l_g[first:, None] @ self.T_g_camera[None, lo:hi], c.rotation_weight)

        # Each step's trunk is the argmin over its own window (the window follows the previous step's trunk), so the
        # cost of a horizon does not grow with the route's length. The costs themselves do not depend on the chain:
        # they are computed in batches over a block of candidates (first the start's window widened by one forward
        # reach in the direction of travel), the block widened by a reach only when a step's window leaves it.
        reach = c.trunk_window_forward
        lo, hi = window(prev)
        blo, bhi = (lo, min(len(self), hi + reach)) if direction >= 0 else (max(0, lo - reach), hi)
        block, first = costs(blo, bhi, 0), 0
        out = np.empty(n, dtype=np.int64)
        for k in range(n):
            lo, hi = window(prev)
            if lo < blo or hi > bhi:
                nlo = max(0, lo - reach) if lo < blo else blo
                nhi = min(len(self), hi + reach) if hi > bhi else bhi
                parts = [costs(nlo, blo, k)] if nlo < blo else []
                parts.append(block[k - first :])
                if nhi > bhi:
                    parts.append(costs(bhi, nhi, k))
                block, first, blo, bhi = np.hstack(parts), k, nlo, nhi
            prev = lo + int(np.argmin(block[k - first, lo - blo : hi - blo]))
            out[k] = prev
        return out

    @translating
    def route_distances(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(path_distance_m, past_end_m)`` (N,) of vehicle positions (N, 3): distance to the taught path (the
        polyline through the taught vehicles) and how far past its first or last vertex (0 within)."""
        return self._path.distances(np.atleast_2d(np.asarray(positions, float)))

    # ----------------------------------------------------------------- evaluation
    @translating
    def evaluate(
        self,
        positions: np.ndarray,
        yaw: np.ndarray,
        *,
        trunk: np.ndarray | None = None,
        previous: int | None = None,
        axes: np.ndarray | None = None,
        taught_axes: bool = False,
        direction: int = FORWARD,
        gradient: bool = True,
    ) -> FieldEvaluation:
        """Constraint at vehicle outputs ``positions`` (N, 3), ``yaw`` (N,) in g.

        Each step's trunk is ``trunk`` (N,) when given, else selected from ``previous`` (default: the
        nearest vertex to the first position) in the travel ``direction`` (+1 taught order, -1 reversed).
        ``axes`` (N, 3) overrides the mount's optical axes (gimbal: also for the trunk selection);
        ``taught_axes``: a gimbal holding each step's trunk's taught axis. With a gimbal the yaw gradient
        covers the lever arm only.
        """
        pos, psi, axes = self._horizon(positions, yaw, axes)
        direction = check_direction(direction)
        if taught_axes and axes is not None:
            raise EstimationError("axes: give explicit axes or taught_axes, not both")
        if trunk is None:
            start = self.nearest_trunk(pos[0]) if previous is None else self._index(previous, "previous trunk")
            trunk = self.select_trunks(pos, psi, start, axes=axes, direction=direction, taught_axes=taught_axes)
        t = np.asarray(trunk)
        if (
            t.dtype.kind not in "iu"
            or t.shape not in ((), (len(pos),))
            or t.size == 0
            or t.min() < 0
            or t.max() >= len(self)
        ):
            raise EstimationError(f"trunk: expected {len(pos)} trunk indices from 0 to {len(self) - 1}")
        trunk = np.broadcast_to(t.astype(np.int64), (len(pos),))
        if taught_axes:
            axes = self.T_g_camera[trunk, :3, 2]
        cam = self.camera_centres(pos, psi)
        if axes is None:
            ev = self.evaluator.evaluate(cam, trunk, frames.axis_yaw(psi, self.mount.mount_yaw_rad), gradient=gradient)
        else:
            ev = self.evaluator.evaluate(cam, trunk, axes_g=axes, gradient=gradient)
        conservative = self.form == "conservative"
        g = ev.g_conservative if conservative else ev.g
        guarded = ev.mu < 0.25 * self.c_bar**2
        dpos = dyaw = dax = None
        if gradient:
            assert ev.dg_dpos is not None and ev.dgc_dpos is not None and ev.dmu_dpos is not None
            assert ev.dg_daxis is not None and ev.dgc_daxis is not None and ev.dmu_daxis is not None
            dpos = np.where(guarded[:, None], ev.dmu_dpos, ev.dgc_dpos if conservative else ev.dg_dpos)
            dax = np.where(guarded[:, None], ev.dmu_daxis, ev.dgc_daxis if conservative else ev.dg_daxis)
            lever = np.asarray(self.mount.lever_arm_m, float)
            s, c = np.sin(psi), np.cos(psi)
            dcam_dyaw = np.stack(
                [-s * lever[0] - c * lever[1], c * lever[0] - s * lever[1], np.zeros_like(psi)], axis=1
            )
            dyaw = np.einsum("nk,nk->n", dpos, dcam_dyaw)
            if ev.dg_dyaw is not None:
                assert ev.dgc_dyaw is not None and ev.dmu_dyaw is not None
                dyaw = dyaw + np.where(guarded, ev.dmu_dyaw, ev.dgc_dyaw if conservative else ev.dg_dyaw)
        path_distance, past_end = self.route_distances(pos)
        flag = ev.flag.copy()
        flag[(path_distance > self.off_route_distance_m) | (past_end > self.off_route_past_end_m)] = OFF_ROUTE
        return FieldEvaluation(
            trunk=trunk,
            vertex_id=self.vertex_ids[trunk],
            mu=ev.mu,
            sigma=ev.sigma,
            g=g,
            flag=flag,
            dg_dpos=dpos,
            dg_dyaw=dyaw,
            dg_daxis=dax,
            raw=ev,
            trunk_distance_m=np.linalg.norm(pos - self.vehicle_position_g[trunk], axis=1),
            path_distance_m=path_distance,
            past_end_m=past_end,
            guarded=guarded,
            form=self.form,
        )


class _TaughtPolyline:
    """The taught path as a polyline, for the distance of points to it without visiting every segment: a segment can
    hold a point's nearest point only if its midpoint lies within (distance to the nearest vertex + half the longest
    segment) of the point, so only those are measured (k-d trees over vertices and midpoints; the same answers as
    measuring every segment, at a cost that does not grow with the route's length)."""

    def __init__(self, vertices: np.ndarray) -> None:
        self.pts = np.asarray(vertices, float)
        self.a, seg = self.pts[:-1], np.diff(self.pts, axis=0)
        self.length = np.linalg.norm(seg, axis=1)
        self.d = np.divide(seg, self.length[:, None], out=np.zeros_like(seg), where=self.length[:, None] > 0.0)
        self.vertex_tree = cKDTree(self.pts)
        if len(seg):
            self.mid_tree = cKDTree(self.a + 0.5 * seg)
            # the ball's radius is widened by a relative hair so that rounding in the trees never drops a segment
            self.reach = 0.5 * float(self.length.max()) * (1 + 1e-9) + 1e-9

    def distances(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(self.pts) == 1:
            return np.linalg.norm(p - self.pts[0], axis=1), np.zeros(len(p))
        upper, _ = self.vertex_tree.query(p)
        near = self.mid_tree.query_ball_point(p, upper * (1 + 1e-9) + self.reach)
        rows = np.repeat(np.arange(len(p)), [len(c) for c in near])
        cols = np.concatenate([np.asarray(c, np.int64) for c in near])
        rel = p[rows] - self.a[cols]
        s_rc = np.einsum("kj,kj->k", rel, self.d[cols])
        closest = self.a[cols] + np.clip(s_rc, 0.0, self.length[cols])[:, None] * self.d[cols]
        dist = np.full((len(p), len(self.a)), np.inf)
        dist[rows, cols] = np.linalg.norm(p[rows] - closest, axis=1)
        along = np.zeros_like(dist)
        along[rows, cols] = s_rc
        nearest = np.argmin(dist, axis=1)  # the first of equally near segments, as over all of them
        idx = np.arange(len(p))
        s_n = along[idx, nearest]
        past = np.zeros(len(p))
        first, last = nearest == 0, nearest == len(self.a) - 1
        past[first] = np.maximum(past[first], -s_n[first])
        past[last] = np.maximum(past[last], s_n[last] - self.length[-1])
        return dist[idx, nearest], past


def _check_form(form: str) -> str:
    if form not in CONSTRAINT_FORMS:
        raise EstimationError(f"constraint form: expected one of {', '.join(CONSTRAINT_FORMS)}, got {form!r}")
    return form


def _check_bounds(l_min: float, c_bar: float) -> None:
    for name, v in (("l_min", l_min), ("c_bar", c_bar)):
        if (
            isinstance(v, bool)
            or not isinstance(v, int | float | np.integer | np.floating)
            or not math.isfinite(float(v))
            or v < 0
        ):
            raise EstimationError(f"{name} must be a finite number >= 0, got {v!r}")


__all__ = [
    "CONSTRAINT_FORMS",
    "CameraMount",
    "FieldEvaluation",
    "PerceptionFieldError",
    "TaughtPathField",
    "TaughtVertex",
    "check_direction",
    "perception_errors",
    "read_taught_vertices",
]
