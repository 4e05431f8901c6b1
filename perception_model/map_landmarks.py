"""The chance constraint on a taught ``vtr`` map (``perception-model constraint --map``).

For each query position the **trunk** is the nearest privileged (teach) vertex
(``vtr.map.Map.nearest_vertices``), its landmarks are the vertex's triangulated points taken to
the map frame through ``T_world_vertex``, and ``mu``, ``sigma`` and the constraint margins come
from ``PerceptionConstraint`` (origin at the trunk camera, explicit optical axes).

Frames (``vtr`` conventions, README "Frames"): the **map frame** is the world frame of the teach
run, i.e. the teach run's first left camera frame: x right, y down, z forward (OpenCV), metres.
Query positions are camera centres in that frame. Parallax and view angles are angles between
vectors, so they do not depend on the frame they are computed in; no gravity alignment is needed
for ``mu`` and ``sigma``.

Camera orientation at a query position:

- **no yaw**: the trunk's orientation (its optical axis is the third column of the trunk's
  rotation ``T_world_vertex[:3, :3]``), i.e. the vehicle flies the taught attitude;
- **yaw ``psi``** (radians; ``yaw_deg`` in degrees in a positions file): a heading about the map
  frame's up axis ``-y`` in the FLU sense of ``perception_model.angles``: ``psi = 0`` looks along
  the map's ``+z`` (the first teach camera's forward direction), positive turns counter-clockwise
  seen from above, so ``psi = +90 deg`` looks along ``-x`` (left). The optical axis is pitched
  ``pitch_down`` below the map's horizontal plane (x-z) with no roll::

      h(psi)  = cos(psi) e_z - sin(psi) e_x              heading
      z_cam   = cos(b) h(psi) + sin(b) e_y               optical axis (e_y points down)
      x_cam   = cos(psi) e_x + sin(psi) e_z              image right, horizontal
      y_cam   = z_cam x x_cam

  ``pitch_down`` defaults to the trunk's own pitch below that plane. The map's ``-y`` is gravity
  up only when the first teach camera was level (a car camera, KITTI); for a camera pitched down at
  the start of the teach (the synthetic aerial runs) ``-y`` is that camera's up axis and yaw/pitch
  are relative to its tilted horizon: prefer positions without yaw there.

Landmarks counted: with ``in_view=True`` (default) only trunk landmarks in front of the camera
(depth > ``MIN_DEPTH_M``) that project inside the image of the map's camera at the query pose
count, which is the population the repeat pipeline writes to ``landmarks.csv`` (so a model fitted
on those files applies); with ``in_view=False`` every trunk landmark counts (the model's view cut
is then the only field of view).

``vtr`` (OpenCV, SciPy, the map store) is imported inside the functions, so
``perception_model`` stays importable without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .constraint import PerceptionConstraint, inlier_moments, normal_tail, poisson_binomial_tail
from .errors import GeometryError, InputDataError
from .model import PerceptionModel

#: Landmarks closer than this (metres, along the optical axis) are not in view (as in vtr's repeat).
MIN_DEPTH_M = 0.1
_E_X = np.array([1.0, 0.0, 0.0])
_E_Y = np.array([0.0, 1.0, 0.0])
_E_Z = np.array([0.0, 0.0, 1.0])


def camera_rotation_from_yaw(yaw: ArrayLike, pitch_down: ArrayLike) -> NDArray[np.float64]:
    """``R_map_cam`` ``(N, 3, 3)`` for headings ``yaw`` ``(N,)`` and pitches below the horizon (radians).

    Map frame x right, y down, z forward (see the module docstring for the convention).
    """
    psi = np.atleast_1d(np.asarray(yaw, dtype=np.float64))
    beta = np.broadcast_to(np.asarray(pitch_down, dtype=np.float64), psi.shape)
    cpsi, spsi = np.cos(psi)[:, None], np.sin(psi)[:, None]
    heading = cpsi * _E_Z - spsi * _E_X
    z = np.cos(beta)[:, None] * heading + np.sin(beta)[:, None] * _E_Y
    x = cpsi * _E_X + spsi * _E_Z
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def yaw_pitch_of_axis(z: ArrayLike) -> tuple[float, float]:
    """``(yaw, pitch_down)`` (radians) of an optical axis in the map frame (inverse of the convention)."""
    zz = np.asarray(z, dtype=np.float64)
    zz = zz / np.linalg.norm(zz)
    pitch = math.asin(float(np.clip(zz[1], -1.0, 1.0)))
    yaw = math.atan2(-float(zz[0]), float(zz[2]))
    return yaw, pitch


@dataclass(frozen=True)
class Trunk:
    """A privileged vertex and its landmarks in the map frame."""

    vertex_id: int
    T_map_vertex: NDArray[np.float64]
    points_map: NDArray[np.float64]  # (M, 3)

    @property
    def centre(self) -> NDArray[np.float64]:
        """Camera centre (3,) in the map frame."""
        return self.T_map_vertex[:3, 3]

    @property
    def optical_axis(self) -> NDArray[np.float64]:
        """Optical axis (3,): third column of the trunk rotation."""
        return self.T_map_vertex[:3, 2]


@dataclass(frozen=True)
class MapConstraintTable:
    """Per-position results of the constraint on a map (arrays of length N)."""

    positions: NDArray[np.float64]
    yaw: NDArray[np.float64]  # heading used (radians, map convention; the trunk's when none given)
    pitch_down: NDArray[np.float64]
    yaw_given: bool
    trunk_id: NDArray[np.int64]
    trunk_distance_m: NDArray[np.float64]
    n_landmarks: NDArray[np.int64]  # landmarks of the trunk
    n_in_view: NDArray[np.int64]  # of them counted (in view, or all with in_view=False)
    mu: NDArray[np.float64]
    sigma: NDArray[np.float64]
    g: NDArray[np.float64]
    g_conservative: NDArray[np.float64]
    p_fail_normal: NDArray[np.float64]
    p_fail_exact: NDArray[np.float64] | None
    n_map_landmarks: int  # distinct landmarks over the trunks used

    def __len__(self) -> int:
        return int(self.positions.shape[0])


def _open_map(path: Path) -> tuple[Any, type[Exception]]:
    """``(vtr.map.Map opened read-only, vtr's root error class)``; ``InputDataError`` if it cannot be opened."""
    try:
        from vtr.errors import VtrError
        from vtr.map import Map
    except ImportError as err:  # pragma: no cover - vtr ships with this package
        raise InputDataError(f"--map needs the vtr package ({err})") from None
    try:
        return Map.open(path, "r"), VtrError
    except VtrError as err:
        raise InputDataError(str(err)) from None


def trunk_landmarks(vtr_map: Any, vertex_id: int) -> Trunk:
    """Landmarks (finite triangulated points) of vertex ``vertex_id`` of an open ``vtr.map.Map``, map frame."""
    rec = vtr_map.vertex(int(vertex_id))
    T = np.asarray(rec.T_world_vertex, dtype=np.float64)
    pts = np.asarray(rec.frame.points, dtype=np.float64)[rec.landmark_mask]
    return Trunk(int(vertex_id), T, pts @ T[:3, :3].T + T[:3, 3])


def _in_view(points: NDArray[np.float64], position: NDArray[np.float64], R: NDArray[np.float64], camera: Any) -> Any:
    p_cam = (points - position) @ R  # rows: R^T (p - c)
    z = p_cam[:, 2]
    ok = z > MIN_DEPTH_M
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.fx * p_cam[:, 0] / z + camera.cx
        v = camera.fy * p_cam[:, 1] / z + camera.cy
    return ok & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


def evaluate_on_map(
    model: PerceptionModel,
    map_path: str | Path,
    positions: ArrayLike,
    yaw: ArrayLike | None = None,
    *,
    pitch_down: float | None = None,
    l_min: float,
    c_bar: float,
    in_view: bool = True,
    exact: bool = True,
) -> MapConstraintTable:
    """``mu``, ``sigma``, margins and failure probabilities at ``positions`` ``(N, 3)`` on a taught map.

    ``positions`` are camera centres in the map frame; ``yaw`` ``(N,)`` radians or ``None``
    (trunk orientation); ``pitch_down`` (radians) for yaw-defined axes, default the trunk's pitch.
    Raises ``InputDataError`` for an unreadable map or a map without a taught run.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] == 0:
        raise InputDataError(f"positions must have shape (N, 3) with N >= 1, got {pos.shape}")
    n = pos.shape[0]
    psi_in = None if yaw is None else np.broadcast_to(np.asarray(yaw, dtype=np.float64), (n,))
    vtr_map, VtrError = _open_map(Path(map_path))  # noqa: N806 - a class
    with vtr_map:
        try:
            trunk_ids = np.array([int(vtr_map.nearest_vertices(p, 1)[0]) for p in pos], dtype=np.int64)
            trunks = {int(t): trunk_landmarks(vtr_map, int(t)) for t in np.unique(trunk_ids)}
        except VtrError as err:
            raise InputDataError(str(err)) from None
        camera = vtr_map.camera
    yaw_used = np.empty(n)
    pitch_used = np.empty(n)
    R = np.empty((n, 3, 3))
    for i, t in enumerate(trunk_ids):
        trunk = trunks[int(t)]
        t_yaw, t_pitch = yaw_pitch_of_axis(trunk.optical_axis)
        if psi_in is None:
            R[i] = trunk.T_map_vertex[:3, :3]
            yaw_used[i], pitch_used[i] = t_yaw, t_pitch
        else:
            pitch_used[i] = t_pitch if pitch_down is None else pitch_down
            yaw_used[i] = psi_in[i]
            R[i] = camera_rotation_from_yaw(psi_in[i], pitch_used[i])[0]
    p_rows: list[NDArray[np.float64]] = [np.empty(0)] * n
    n_in = np.zeros(n, dtype=np.int64)
    for t, trunk in trunks.items():
        sel = np.flatnonzero(trunk_ids == t)
        if trunk.points_map.shape[0] == 0:
            for i in sel.tolist():
                p_rows[i] = np.zeros(0)
            continue
        try:
            con = PerceptionConstraint(model, trunk.points_map - trunk.centre, l_min=l_min, c_bar=c_bar)
            ev = con.evaluate(pos[sel] - trunk.centre, axes=R[sel, :, 2], gradient=False)
        except GeometryError as err:
            raise InputDataError(f"trunk {t}: {err}") from None
        for k, i in enumerate(sel.tolist()):
            p = ev.p[k]
            if in_view:
                p = p[_in_view(trunk.points_map, pos[i], R[i], camera)]
            p_rows[i] = p
            n_in[i] = p.size
    mu = np.empty(n)
    var = np.empty(n)
    for i, p in enumerate(p_rows):
        m, v = inlier_moments(p)
        mu[i], var[i] = float(m), float(v)
    sigma = np.sqrt(var)
    g = mu - c_bar * sigma - l_min
    gc = mu - c_bar * np.sqrt(mu) - l_min
    fail_n = np.array([normal_tail(float(m), float(s), l_min, lower=True) for m, s in zip(mu, sigma, strict=True)])
    fail_x = np.array([poisson_binomial_tail(p, l_min, lower=True) for p in p_rows]) if exact else None
    centres = np.stack([trunks[int(t)].centre for t in trunk_ids])
    return MapConstraintTable(
        positions=pos,
        yaw=yaw_used,
        pitch_down=pitch_used,
        yaw_given=psi_in is not None,
        trunk_id=trunk_ids,
        trunk_distance_m=np.linalg.norm(pos - centres, axis=1),
        n_landmarks=np.array([trunks[int(t)].points_map.shape[0] for t in trunk_ids], dtype=np.int64),
        n_in_view=n_in,
        mu=mu,
        sigma=sigma,
        g=g,
        g_conservative=gc,
        p_fail_normal=fail_n,
        p_fail_exact=fail_x,
        n_map_landmarks=int(sum(t.points_map.shape[0] for t in trunks.values())),
    )
