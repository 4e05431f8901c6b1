"""Map-frame conventions and records of the chance constraint on a taught map (``constraint --map``).

This module is pure (it imports nothing from ``vtr``): the reading of a ``vtr`` map and the
evaluation live on the ``vtr`` side (``vtr.app.perception.evaluate_on_map``; the ``perception-model``
console script installed with ``vtr`` is ``vtr.cli.perception_model``, which adds the map-aware
commands). For each query position the **trunk** is chosen by the localizer's rule (a window
around the previous trunk minimizing ``||rho|| + 7 ||phi||``, starting at the vertex nearest to the
first position); its landmarks are the vertex's triangulated points in the map frame, and ``mu``,
``sigma`` and the margins come from ``PerceptionConstraint`` (explicit optical axes).

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
  seen from above, so ``psi = +90 deg`` looks along ``-x`` (left). This is the yaw of
  ``perception_model.frames`` in the map's gravity-aligned frame g with up = the map's ``-y``
  (``frames.T_g_map_from_up((0, -1, 0))``: x_g = map +z, y_g = map -x). The optical axis is pitched
  ``pitch_down`` below the map's horizontal plane (x-z) with no roll::

      h(psi)  = cos(psi) e_z - sin(psi) e_x              heading
      z_cam   = cos(b) h(psi) + sin(b) e_y               optical axis (e_y points down)
      x_cam   = cos(psi) e_x + sin(psi) e_z              image right, horizontal
      y_cam   = z_cam x x_cam

  ``pitch_down`` defaults to the trunk's own pitch below that plane. The map's ``-y`` is gravity
  up only when the first teach camera was level (a car camera, KITTI); for a camera pitched down at
  the start of the teach (the synthetic aerial runs) ``-y`` is that camera's up axis and yaw/pitch
  are relative to its tilted horizon: prefer positions without yaw there.

Landmarks counted: with ``in_view=True`` (default) only trunk landmarks in view of the map's camera
at the query pose (``vtr.camera.StereoCamera.in_view``: in front by more than its minimum depth and
inside the image) count, which is the population the repeat pipeline writes to ``landmarks.csv`` (so a model fitted
on those files applies); with ``in_view=False`` every trunk landmark counts (the model's view cut
is then the only field of view).

"""

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

    __repr__ = short_repr        # arrays by shape: print(record) stays short

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

    __repr__ = short_repr        # arrays by shape: print(record) stays short

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
