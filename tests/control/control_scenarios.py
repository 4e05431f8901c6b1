"""Helpers: a synthetic taught path with landmark arrays (no rendering): an L-shaped path 12 m above ground."""

from __future__ import annotations

import math

import numpy as np

from perception_model import frames
from vtr.control.field import TaughtVertex

PITCH_DOWN_RAD = math.radians(50.0)


def l_path(first_m: float = 14.0, second_m: float = 10.0) -> np.ndarray:
    a = [(s, 0.0) for s in np.arange(0.0, first_m, 1.0)]
    b = [(first_m, s) for s in np.arange(0.0, second_m + 0.5, 1.0)]
    return np.array(a + b, float)


def vertices(
    points_xy: np.ndarray, camera_heading: float | None, *, n_landmarks: int, seed: int = 0, mount_yaw: float = 0.0
) -> list[TaughtVertex]:
    """Camera poses along the path (fixed heading = gimbal, else path heading + mount) and ground landmarks
    inside a ZED-like field of view, as a map would hold them (map frame = g here)."""
    rng = np.random.default_rng(seed)
    lo, hi = points_xy.min(axis=0) - 30.0, points_xy.max(axis=0) + 30.0
    ground = np.column_stack(
        [rng.uniform(lo[0], hi[0], 40_000), rng.uniform(lo[1], hi[1], 40_000), rng.uniform(0.0, 2.0, 40_000)]
    )
    d = np.gradient(points_xy, axis=0)
    path_heading = np.arctan2(d[:, 1], d[:, 0])
    out = []
    for i, p in enumerate(points_xy):
        h = camera_heading if camera_heading is not None else path_heading[i] + mount_yaw
        T = np.eye(4)
        T[:3, :3] = frames.camera_rotation(h, PITCH_DOWN_RAD)
        T[:3, 3] = [p[0], p[1], 12.0]
        pc = (ground - T[:3, 3]) @ T[:3, :3]
        vis = (pc[:, 2] > 1.0) & (np.abs(pc[:, 0] / pc[:, 2]) < 0.95) & (np.abs(pc[:, 1] / pc[:, 2]) < 0.53)
        out.append(TaughtVertex(i, T, ground[np.flatnonzero(vis)[:n_landmarks]]))
    return out
