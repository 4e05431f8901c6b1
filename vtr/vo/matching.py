"""Matching landmarks to a frame's features around their predicted projections (odometry's local map
and localization's trunk-to-leaf matching share it).
"""

from __future__ import annotations

import numpy as np

from ..camera import MIN_DEPTH_M, StereoCamera
from ..types import StereoFrame
from .features import match_within_radius

__all__ = ["MIN_DEPTH_M", "match_landmarks", "match_to_landmarks"]


def match_landmarks(
    points_world: np.ndarray,
    descriptors: np.ndarray,
    frame: StereoFrame,
    T_cam_world: np.ndarray,
    camera: StereoCamera,
    radius: float,
    max_distance: int,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match landmarks (world points with descriptors) to a frame's features near their predicted projection.

    Returns (landmark indices, feature indices).
    """
    P = points_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    idx = np.flatnonzero(camera.in_view(P, margin_px=radius))
    pred = camera.project(P[idx])[:, :2]
    qi, tj = match_within_radius(
        pred,
        descriptors[idx],
        frame.features.uv,
        frame.features.descriptors,
        radius,
        max_distance,
        ratio=ratio,
        mutual=True,
    )
    return idx[qi], tj


def match_to_landmarks(
    ref: StereoFrame,
    cur: StereoFrame,
    T_cur_ref: np.ndarray,
    camera: StereoCamera,
    radius: float,
    max_distance: int,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match a reference frame's landmarks (with depth) to a current frame: (ref indices, cur indices)."""
    ref_idx = np.flatnonzero(ref.has_depth)
    qi, tj = match_landmarks(
        ref.points[ref_idx], ref.features.descriptors[ref_idx], cur, T_cur_ref, camera, radius, max_distance, ratio
    )
    return ref_idx[qi], tj
