"""The taught-path perception field: every taught vertex's landmarks, trunk selection, horizon evaluation.

Built once from a taught map and a perception model. Frames follow :mod:`perception_model.frames`:
the field works in the map's gravity-aligned frame g (z up; x the first teach camera's forward
direction on the horizontal plane; ``up_map`` gives gravity in the map frame); each vertex's
landmarks are cached in its own controller frame o (origin at the taught vehicle, x along its
heading) as ``perception_model.horizon.TrunkLandmarks``.

The vehicle is a level multirotor with flat outputs ``(p, psi)`` in g; its camera sits at
``CameraMount.lever_arm_m`` (vehicle FLU frame) with the optical axis yawed ``mount_yaw_rad`` from
the vehicle's x axis and the taught pitch below the horizon. The taught vehicle's yaw is the
taught optical axis' heading minus ``mount_yaw_rad`` (the map stores camera poses).

Trunk selection is the localizer's rule (``vtr.navigation.trunk``, as ``vtr.navigation.chain.LocalizationChain.prior``):
in a window of ``trunk_window_back``/``trunk_window_forward`` vertices around the previous trunk,
the vertex minimizing ``||rho|| + rotation_weight ||phi||`` of the relative camera pose
(``config.localization``). Along a horizon the previous trunk of step k is step k-1's.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from perception_model import frames
from perception_model.horizon import HorizonEvaluation, HorizonEvaluator, TrunkLandmarks
from perception_model.model import PerceptionModel
from perception_model.settings import THESIS_C_BAR, THESIS_L_MIN

from ..config import LocalizationConfig
from ..errors import EstimationError, MapError
from ..geometry import inv_T
from ..map import Map
from ..navigation.trunk import FORWARD, trunk_cost, trunk_window


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

    ``dg_dpos`` (N, 3), ``dg_dyaw`` (N,) (vehicle yaw: axis yaw and lever arm), ``dg_daxis`` (N, 3)
    (the optical axis, for a gimbal); ``vertex_id`` (N,) each step's trunk; ``flag`` as in
    ``perception_model.horizon``. ``raw`` is the evaluator's record (camera-centre gradients).
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


class TaughtPathField:
    """The perception chance constraint over the whole taught path (value and gradient for a horizon)."""

    def __init__(self, model: PerceptionModel, vertices: list[TaughtVertex], *,
                 T_g_map: np.ndarray, mount: CameraMount | None = None,
                 config: LocalizationConfig | None = None, l_min: float = THESIS_L_MIN,
                 c_bar: float = THESIS_C_BAR) -> None:
        if not vertices:
            raise MapError("the taught path is empty")
        _check_bounds(l_min, c_bar)
        self.mount = mount or CameraMount()
        self.config = config or LocalizationConfig()
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
            trunks.append(TrunkLandmarks(v.vertex_id, positions[i], float(yaw[i]), lever.copy(), p_is_o,
                                         float(pitch[i])))
        self.vertex_ids = np.array([v.vertex_id for v in vertices], dtype=np.int64)
        self.T_g_camera = T_g_cam
        self.vehicle_position_g = positions
        self.vehicle_yaw_g = np.asarray(yaw, float)
        self.pitch_down = np.asarray(pitch, float)
        self.evaluator = HorizonEvaluator(model, trunks, l_min=l_min, c_bar=c_bar)

    @classmethod
    def from_map(cls, vtr_map: Map, model: PerceptionModel, *, up_map=frames.LEVEL_CAMERA_UP,
                 mount: CameraMount | None = None, config: LocalizationConfig | None = None,
                 l_min: float = THESIS_L_MIN, c_bar: float = THESIS_C_BAR) -> TaughtPathField:
        """Read every taught vertex of ``vtr_map`` (open) once; ``up_map``: gravity up in the map frame."""
        return cls(model, read_taught_vertices(vtr_map), T_g_map=frames.T_g_map_from_up(up_map), mount=mount,
                   config=config, l_min=l_min, c_bar=c_bar)

    def __len__(self) -> int:
        return len(self.vertex_ids)

    @property
    def l_min(self) -> float:
        return self.evaluator.l_min

    @property
    def c_bar(self) -> float:
        return self.evaluator.c_bar

    def with_bounds(self, l_min: float, c_bar: float) -> TaughtPathField:
        """The same field (landmarks shared, not copied) with the constraint ``mu - c_bar sigma - l_min``;
        the MPC uses it so that its ``ControlConfig`` owns ``l_min`` and ``c_bar``."""
        _check_bounds(l_min, c_bar)
        out = copy.copy(self)
        out.evaluator = copy.copy(self.evaluator)
        out.evaluator.l_min, out.evaluator.c_bar = float(l_min), float(c_bar)
        return out

    def _index(self, value, what: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or not 0 <= int(value) < len(self):
            raise EstimationError(f"{what}: {value!r} is not a trunk index (0 to {len(self) - 1})")
        return int(value)

    def _horizon(self, positions, yaw, axes=None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
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
    def camera_centres(self, positions: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """Camera centres (N, 3) in g of vehicles at ``positions`` (N, 3) with yaw ``yaw`` (N,)."""
        return frames.camera_position(positions, yaw, self.mount.lever_arm_m)

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

    def select_trunks(self, positions: np.ndarray, yaw: np.ndarray, previous: int,
                      axes: np.ndarray | None = None, direction: int = FORWARD) -> np.ndarray:
        """Trunk index (N,) of each predicted vehicle pose by the localizer's rule (:mod:`vtr.navigation.trunk`),
        starting from ``previous``; ``direction`` -1 for a route flown backward (the window mirrors).

        The camera's attitude comes from the vehicle yaw and the mount, or from ``axes`` (N, 3) (gimbal).
        """
        pos, yaw, axes = self._horizon(positions, yaw, axes)
        previous = self._index(previous, "previous trunk")
        axes_pitch = None
        if axes is not None:
            heading, axes_pitch = frames.heading_of_axis(axes)
            yaw = heading - self.mount.mount_yaw_rad
        c = self.config
        n = len(pos)
        prev = int(previous)
        # every step's window lies in n windows' reach of prev: one batched cost for all steps
        reach = n * max(c.trunk_window_back, c.trunk_window_forward)
        lo_all, hi_all = trunk_window(prev, len(self), reach, reach)
        pitch = self.pitch_down[prev] if axes_pitch is None else np.asarray(axes_pitch, float)
        T_l_g = np.stack([inv_T(T) for T in self.camera_poses(pos, yaw, pitch)])
        cost = trunk_cost(T_l_g[:, None] @ self.T_g_camera[None, lo_all:hi_all], c.rotation_weight)
        out = np.empty(n, dtype=np.int64)
        for k in range(n):
            lo, hi = trunk_window(prev, len(self), c.trunk_window_back, c.trunk_window_forward, direction)
            prev = lo + int(np.argmin(cost[k, lo - lo_all:hi - lo_all]))
            out[k] = prev
        return out

    # ----------------------------------------------------------------- evaluation
    def evaluate(self, positions: np.ndarray, yaw: np.ndarray, *, trunk: np.ndarray | None = None,
                 previous: int | None = None, axes: np.ndarray | None = None,
                 gradient: bool = True) -> FieldEvaluation:
        """Constraint at vehicle outputs ``positions`` (N, 3), ``yaw`` (N,) in g.

        Each step's trunk is ``trunk`` (N,) when given, else selected from ``previous`` (default: the
        nearest vertex to the first position). ``axes`` (N, 3) overrides the mount's optical axes
        (gimbal: also for the trunk selection); the yaw gradient then covers the lever arm only.
        """
        pos, psi, axes = self._horizon(positions, yaw, axes)
        if trunk is None:
            start = self.nearest_trunk(pos[0]) if previous is None else self._index(previous, "previous trunk")
            trunk = self.select_trunks(pos, psi, start, axes=axes)
        t = np.asarray(trunk)
        if t.dtype.kind not in "iu" or t.shape not in ((), (len(pos),)) or t.size == 0 \
                or t.min() < 0 or t.max() >= len(self):
            raise EstimationError(f"trunk: expected {len(pos)} trunk indices from 0 to {len(self) - 1}")
        trunk = np.broadcast_to(t.astype(np.int64), (len(pos),))
        cam = self.camera_centres(pos, psi)
        if axes is None:
            ev = self.evaluator.evaluate(cam, trunk, frames.axis_yaw(psi, self.mount.mount_yaw_rad),
                                         gradient=gradient)
        else:
            ev = self.evaluator.evaluate(cam, trunk, axes_g=axes, gradient=gradient)
        dpos = dyaw = None
        if gradient:
            assert ev.dg_dpos is not None
            dpos = ev.dg_dpos
            lever = np.asarray(self.mount.lever_arm_m, float)
            s, c = np.sin(psi), np.cos(psi)
            dcam_dyaw = np.stack([-s * lever[0] - c * lever[1], c * lever[0] - s * lever[1], np.zeros_like(psi)],
                                 axis=1)
            dyaw = np.einsum("nk,nk->n", dpos, dcam_dyaw)
            if ev.dg_dyaw is not None:
                dyaw = dyaw + ev.dg_dyaw
        return FieldEvaluation(trunk=trunk, vertex_id=self.vertex_ids[trunk], mu=ev.mu, sigma=ev.sigma, g=ev.g,
                               flag=ev.flag, dg_dpos=dpos, dg_dyaw=dyaw, dg_daxis=ev.dg_daxis, raw=ev)


def _check_bounds(l_min: float, c_bar: float) -> None:
    for name, v in (("l_min", l_min), ("c_bar", c_bar)):
        if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating) \
                or not math.isfinite(float(v)) or v < 0:
            raise EstimationError(f"{name} must be a finite number >= 0, got {v!r}")


__all__ = ["CameraMount", "FieldEvaluation", "TaughtPathField", "TaughtVertex", "read_taught_vertices"]
