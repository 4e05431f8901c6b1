"""Stereo camera presets (:func:`zed_camera`, :func:`kitti_like_camera`) and the rig's right-in-left pose
(:func:`T_left_right`)."""

from __future__ import annotations

import numpy as np

from ...camera import StereoCamera
from ...geometry import make_T


def zed_camera() -> StereoCamera:
    """ZED-like rectified stereo camera at VGA (672x376, fx = fy = 350 px, 0.12 m baseline)."""
    return StereoCamera(fx=350.0, fy=350.0, cx=335.5, cy=187.5, baseline=0.12, width=672, height=376)


def kitti_like_camera() -> StereoCamera:
    """KITTI-odometry-like rectified stereo camera (1226x370, fx = 707.09 px, 0.537 m baseline)."""
    return StereoCamera(fx=707.0912, fy=707.0912, cx=601.8873, cy=183.1104, baseline=0.537, width=1226, height=370)


def T_left_right(camera: StereoCamera) -> np.ndarray:
    """Pose of the right rectified camera in the left one (``baseline`` m along +x)."""
    return make_T(np.eye(3), np.array([camera.baseline, 0.0, 0.0]))
