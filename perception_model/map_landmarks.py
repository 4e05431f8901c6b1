"""Map-frame conventions and records of the chance constraint on a taught map (``constraint --map``). Pure: the
reading of a ``vtr`` map and the evaluation are ``vtr.app.perception.evaluate_on_map``'s. Each query position takes
its trunk by the localizer's rule, the trunk's landmarks in the map frame (the teach run's first left camera frame),
and a camera orientation that is the trunk's or a yaw about the map's ``-y`` at a pitch below its horizontal plane;
landmarks count when in view (``in_view=True``). The conventions: docs/perception_model.md, "In code" (On a taught
map)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .records import short_repr

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

    __repr__ = short_repr  # arrays by shape: print(record) stays short

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

    __repr__ = short_repr  # arrays by shape: print(record) stays short

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
