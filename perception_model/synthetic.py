"""Synthetic data for tests, benchmarks and demos: labelled angle samples and landmark scenes.

Frame ``o`` is ENU-like (x east, y north, z up) with its origin at the taught camera; lengths in
metres, angles in radians. Nothing here is used by the fitting or constraint code itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .angles import optical_axis
from .fit import simulate_labels
from .landmarks_file import Observations, SourceSpan
from .model import DEFAULT_ALPHA_MAX_RAD, DEFAULT_THETA_MAX_RAD, PerceptionModel
from .settings import THESIS_PITCH_DOWN_RAD

#: Default scene: camera altitude above the ground plane and height of raised structure (m).
DEFAULT_ALTITUDE_M = 15.0
DEFAULT_STRUCTURE_HEIGHT_M = 3.0
#: Default camera field of view (ZED-like, VGA): horizontal and vertical, radians.
DEFAULT_HFOV_RAD = math.radians(87.0)
DEFAULT_VFOV_RAD = math.radians(56.0)
#: Landmarks per simulated localization in ``simulate_observations``.
LANDMARKS_PER_FRAME = 500
_NS_PER_FRAME = 100_000_000
#: Rays must descend at least this steeply (z component of the unnormalized ray) to be kept.
_MIN_RAY_DESCENT = 1e-3


def sample_angles(
    n: int,
    rng: np.random.Generator,
    *,
    alpha_max: float = DEFAULT_ALPHA_MAX_RAD,
    theta_max: float = DEFAULT_THETA_MAX_RAD,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``n`` (alpha, theta) pairs uniform on ``[0, alpha_max] x [0, theta_max]`` (radians)."""
    return rng.uniform(0.0, alpha_max, n), rng.uniform(0.0, theta_max, n)


def simulate_observations(
    model: PerceptionModel,
    n: int,
    rng: np.random.Generator,
    *,
    alpha_max: float = DEFAULT_ALPHA_MAX_RAD,
    theta_max: float = DEFAULT_THETA_MAX_RAD,
    name: str = "<synthetic>",
) -> Observations:
    """Uniform angles with Bernoulli labels from ``model``, grouped into fake localizations."""
    a, t = sample_angles(n, rng, alpha_max=alpha_max, theta_max=theta_max)
    y = simulate_labels(model, a, t, rng)
    frame = np.arange(n, dtype=np.int64) // LANDMARKS_PER_FRAME
    return Observations(
        alpha=a,
        theta=t,
        inlier=y,
        t_ns=frame * _NS_PER_FRAME,
        leaf_id=frame,
        trunk_id=frame,
        landmark_id=np.arange(n, dtype=np.int64) % LANDMARKS_PER_FRAME,
        range_m=np.full(n, np.nan),
        sources=(SourceSpan(name, 0, n),),
    )


@dataclass(frozen=True)
class Scene:
    """Landmarks ``p_is`` ``(M, 3)`` seen by a taught camera at the origin of frame ``o``."""

    landmarks: NDArray[np.float64]
    yaw: float
    pitch_down: float
    altitude: float


def ground_scene(
    n_landmarks: int,
    rng: np.random.Generator,
    *,
    altitude: float = DEFAULT_ALTITUDE_M,
    structure_height: float = DEFAULT_STRUCTURE_HEIGHT_M,
    yaw: float = 0.0,
    pitch_down: float = THESIS_PITCH_DOWN_RAD,
    hfov: float = DEFAULT_HFOV_RAD,
    vfov: float = DEFAULT_VFOV_RAD,
) -> Scene:
    """Landmarks where rays through random pixels of the taught camera hit the ground or structure.

    The camera (yaw, pitched ``pitch_down`` below the horizon) is ``altitude`` metres above a
    ground plane; each landmark sits at a random height in ``[0, structure_height]`` above it.
    Rays that would not hit the ground in front of the camera are redrawn.
    """
    if not 0.0 <= structure_height < altitude:
        raise ValueError("structure_height must be in [0, altitude)")
    fwd = optical_axis(yaw, pitch_down)
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    tan_h, tan_v = math.tan(0.5 * hfov), math.tan(0.5 * vfov)
    out = np.empty((0, 3))
    while out.shape[0] < n_landmarks:
        k = 2 * (n_landmarks - out.shape[0]) + 8
        u = rng.uniform(-tan_h, tan_h, k)
        v = rng.uniform(-tan_v, tan_v, k)
        rays = fwd[None, :] + u[:, None] * right[None, :] + v[:, None] * down[None, :]
        height = rng.uniform(0.0, structure_height, k)
        plane = -altitude + height  # z of the hit point
        ok = rays[:, 2] < -_MIN_RAY_DESCENT
        scale = plane[ok] / rays[ok, 2]
        out = np.vstack([out, rays[ok] * scale[:, None]])
    return Scene(out[:n_landmarks], yaw, pitch_down, altitude)
