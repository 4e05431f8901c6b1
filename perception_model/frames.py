"""The controller frame ``o`` and its yaw convention: the one definition used by the whole project (``vtr`` imports this
module; this package imports nothing from ``vtr``). ``g`` is a gravity-aligned frame (on a map:
:func:`T_g_map_from_up`), ``o`` a trunk's controller frame (:func:`to_trunk_frame`), yaw the heading of the vehicle's x
axis counter-clockwise about z (:func:`yaw_of`); a camera on a fixed mount has the optical axis of
:func:`optical_axis` and the axis yaw of :func:`axis_yaw`. The definitions: docs/perception_model.md, "In code"
(Frames), and docs/frames.md."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError

#: ``T_vehicle_camera`` of a level, forward-looking camera (x right, y down, z forward) at the centre of a vehicle
#: whose frame is FLU (x forward, y left, z up): vehicle x = camera z, y = -camera x, z = -camera y. The one
#: statement of the "level camera" convention; the identity ``T_vehicle_sensor`` of a source (KITTI) means it.
T_VEHICLE_LEVEL_CAMERA = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
T_VEHICLE_LEVEL_CAMERA.flags.writeable = False
#: Gravity up in a level camera's coordinates (the vehicle's z seen from the camera: its -y); the map frame's up
#: when the first teach camera was level.
LEVEL_CAMERA_UP: tuple[float, float, float] = (
    float(T_VEHICLE_LEVEL_CAMERA[2, 0]),
    float(T_VEHICLE_LEVEL_CAMERA[2, 1]),
    float(T_VEHICLE_LEVEL_CAMERA[2, 2]),
)

UP = np.array([0.0, 0.0, 1.0])
#: A horizontal direction shorter than this (unit vectors) has no heading.
MIN_HORIZONTAL_NORM = 1e-9


def yaw_of(C: ArrayLike) -> NDArray[np.float64] | float:
    """Yaw (rad) of a frame's x axis in a gravity-aligned frame: ``atan2(C[1, 0], C[0, 0])``; (..., 3, 3) stacks."""
    R = np.asarray(C, dtype=np.float64)
    out = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return float(out) if out.ndim == 0 else out


def rot_z(psi: ArrayLike) -> NDArray[np.float64]:
    """Rotation(s) about z by ``psi`` (rad): (3, 3), or (N, 3, 3) for an (N,) input."""
    a = np.asarray(psi, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def wrap_angle(a: ArrayLike) -> NDArray[np.float64]:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + math.pi) % (2.0 * math.pi) - math.pi


def heading_of_axis(z: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(heading, pitch_down)`` (rad) of optical axes ``z`` (..., 3) in a gravity-aligned frame."""
    v = np.asarray(z, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1)
    if np.any(n == 0.0) or not np.all(np.isfinite(n)):
        raise GeometryError("optical axes must be finite and non-zero")
    v = v / n[..., None]
    horiz = np.hypot(v[..., 0], v[..., 1])
    if np.any(horiz < MIN_HORIZONTAL_NORM):
        raise GeometryError("a vertical optical axis has no heading")
    return np.arctan2(v[..., 1], v[..., 0]), np.arcsin(np.clip(-v[..., 2], -1.0, 1.0))


def optical_axis(yaw: ArrayLike, pitch_down: ArrayLike, mount_yaw: ArrayLike = 0.0) -> NDArray[np.float64]:
    """Unit optical axis (..., 3) of a camera on a level vehicle with yaw ``yaw`` (see the module docstring)."""
    h = np.asarray(yaw, dtype=np.float64) + np.asarray(mount_yaw, dtype=np.float64)
    b = np.broadcast_to(np.asarray(pitch_down, dtype=np.float64), h.shape)
    return np.stack([np.cos(h) * np.cos(b), np.sin(h) * np.cos(b), -np.sin(b)], axis=-1)


def axis_yaw(vehicle_yaw: ArrayLike, mount_yaw: ArrayLike = 0.0) -> NDArray[np.float64]:
    """Heading of the optical axis (the ``yaw`` of ``PerceptionConstraint``) for a vehicle yaw and mount yaw."""
    return np.asarray(vehicle_yaw, dtype=np.float64) + np.asarray(mount_yaw, dtype=np.float64)


def camera_rotation(yaw: ArrayLike, pitch_down: ArrayLike, mount_yaw: ArrayLike = 0.0) -> NDArray[np.float64]:
    """``C_g_cam`` (..., 3, 3) of the camera (x right, y down, z forward; no roll) in a gravity-aligned frame."""
    h = np.asarray(yaw, dtype=np.float64) + np.asarray(mount_yaw, dtype=np.float64)
    z = optical_axis(h, pitch_down)
    x = np.stack([np.sin(h), -np.cos(h), np.zeros_like(h)], axis=-1)  # image right, horizontal
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def camera_position(position: ArrayLike, yaw: ArrayLike, lever_arm_m: ArrayLike | None = None) -> NDArray[np.float64]:
    """Camera centre(s) (..., 3) of a level vehicle at ``position`` with yaw ``yaw`` and camera lever arm."""
    p = np.asarray(position, dtype=np.float64)
    if lever_arm_m is None:
        return p.copy()
    return p + np.einsum("...ij,j->...i", rot_z(yaw), np.asarray(lever_arm_m, dtype=np.float64))


def to_trunk_frame(
    position_g: ArrayLike, yaw_g: ArrayLike, trunk_position_g: ArrayLike, trunk_yaw_g: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Positions and yaws from a gravity-aligned frame g into trunk frames o (broadcast over (..., 3)/(...))."""
    psi_t = np.asarray(trunk_yaw_g, dtype=np.float64)
    d = np.asarray(position_g, dtype=np.float64) - np.asarray(trunk_position_g, dtype=np.float64)
    p_o = np.einsum("...ji,...j->...i", rot_z(psi_t), d)
    return p_o, np.asarray(yaw_g, dtype=np.float64) - psi_t


def from_trunk_frame(
    position_o: ArrayLike, yaw_o: ArrayLike, trunk_position_g: ArrayLike, trunk_yaw_g: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Inverse of :func:`to_trunk_frame`; also rotates gradients when given ``trunk_position_g = 0``."""
    psi_t = np.asarray(trunk_yaw_g, dtype=np.float64)
    p_g = np.einsum("...ij,...j->...i", rot_z(psi_t), np.asarray(position_o, dtype=np.float64))
    return p_g + np.asarray(trunk_position_g, dtype=np.float64), np.asarray(yaw_o, dtype=np.float64) + psi_t


def gravity_aligned(C_g_x: ArrayLike) -> NDArray[np.float64]:
    """``C_o_x``: the attitude of frame x in the gravity-aligned frame o that shares x's yaw (``Rz(psi)^T C``)."""
    C = np.asarray(C_g_x, dtype=np.float64)
    if C.shape != (3, 3) or not np.all(np.isfinite(C)):
        raise GeometryError("expected a finite 3x3 rotation")
    return rot_z(yaw_of(C)).T @ C


def T_g_map_from_up(up_map: ArrayLike, forward_map: ArrayLike = (0.0, 0.0, 1.0)) -> NDArray[np.float64]:
    """``T_g_map`` (4x4, pure rotation): the map's gravity-aligned frame g from the up direction in the map.

    g: z = ``up_map``; x = ``forward_map`` (default the first teach camera's optical axis, the map's +z)
    projected on the horizontal plane; origin the map origin. For a level first camera (a car, KITTI)
    the up direction is the map's ``-y`` (:data:`LEVEL_CAMERA_UP`).
    """
    up = np.asarray(up_map, dtype=np.float64)
    n = np.linalg.norm(up)
    if up.shape != (3,) or not math.isfinite(float(n)) or n == 0.0:
        raise GeometryError(f"up direction must be a finite non-zero 3-vector, got {up_map!r}")
    up = up / n
    f = np.asarray(forward_map, dtype=np.float64)
    x = f - (f @ up) * up
    if np.linalg.norm(x) < MIN_HORIZONTAL_NORM:
        raise GeometryError("the forward direction is vertical: no heading")
    x = x / np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(up, x), up])  # rows: g axes in map coordinates
    return T


def T_vehicle_camera_from_up(up_camera: ArrayLike) -> NDArray[np.float64]:
    """``T_vehicle_camera`` (4x4, pure rotation) of a camera rigidly mounted on a *level* vehicle, from the up
    direction seen from the camera (``up_camera``, camera coordinates: x right, y down, z forward).

    The vehicle frame (FLU) sits at the camera centre: z = up, x = the optical axis projected on the horizontal
    plane, y = z x x. A camera pitched 50 degrees down has ``up_camera = (0, -cos 50, -sin 50)``; a level camera
    has :data:`LEVEL_CAMERA_UP`, for which this is :data:`T_VEHICLE_LEVEL_CAMERA`. It is :func:`T_g_map_from_up`
    of the camera's own frame: at the first teach camera, the vehicle frame is the map's g.
    """
    return T_g_map_from_up(up_camera)


__all__ = [
    "LEVEL_CAMERA_UP",
    "T_vehicle_camera_from_up",
    "T_VEHICLE_LEVEL_CAMERA",
    "UP",
    "T_g_map_from_up",
    "axis_yaw",
    "camera_position",
    "camera_rotation",
    "from_trunk_frame",
    "gravity_aligned",
    "heading_of_axis",
    "optical_axis",
    "rot_z",
    "to_trunk_frame",
    "wrap_angle",
    "yaw_of",
]
