"""Rectified stereo camera model and rectification of raw (distorted) stereo pairs.

Frames: the *left rectified camera* frame (x right, y down, z forward) is the sensor frame of
every pose the package produces. ``StereoCamera.T_vehicle_sensor`` places it on the vehicle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .errors import CalibrationError
from .geometry import check_se3

MIN_BASELINE_M = 1e-6  # cameras closer than this on the body are the same camera
RIGID_TOLERANCE = 1e-4  # T_BS of a calibration file is rigid to this (printed with ~8 digits)

MIN_DEPTH_M = 0.1  # points closer than this in front of the camera are not in view (not predicted)


@dataclass(frozen=True)
class StereoCamera:
    """Rectified pinhole stereo pair: both cameras share K, the right one sits ``baseline`` m along +x.

    Pixel coordinates: ``u = fx x/z + cx``, ``v = fy y/z + cy``; right image ``u_r = u - fx b / z``.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    width: int
    height: int
    T_vehicle_sensor: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy", "baseline"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("width", "height"):
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "T_vehicle_sensor", np.asarray(self.T_vehicle_sensor, float))
        vals = np.array([self.fx, self.fy, self.cx, self.cy, self.baseline], float)
        if not np.all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0 or self.baseline <= 0:
            raise CalibrationError(f"invalid stereo calibration fx={self.fx} fy={self.fy} baseline={self.baseline}")
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"invalid image size {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix of the rectified left camera."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def fb(self) -> float:
        """Focal length times baseline (pixel metres): disparity = fb / depth."""
        return self.fx * self.baseline

    @property
    def size(self) -> tuple[int, int]:
        """Image size as (width, height)."""
        return (self.width, self.height)

    def project(self, p: np.ndarray) -> np.ndarray:
        """Project points (N, 3) in the left camera frame to stereo measurements (N, 3): u_l, v, u_r."""
        z = p[:, 2]
        u = self.fx * p[:, 0] / z + self.cx
        v = self.fy * p[:, 1] / z + self.cy
        return np.stack([u, v, u - self.fb / z], axis=1)

    def in_view(self, p: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(N,) bool: points (N, 3) in the left camera frame that lie more than ``MIN_DEPTH_M`` in front of
        the camera and project inside the image grown by ``margin_px`` on every side
        (``-margin <= u < width + margin``, likewise v)."""
        p = np.asarray(p, float)
        ok = p[:, 2] > MIN_DEPTH_M
        uv = self.project(p[ok])
        inside = (
            (uv[:, 0] >= -margin_px)
            & (uv[:, 0] < self.width + margin_px)
            & (uv[:, 1] >= -margin_px)
            & (uv[:, 1] < self.height + margin_px)
        )
        ok[np.flatnonzero(ok)[~inside]] = False
        return ok

    def triangulate(self, u: np.ndarray, v: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """Back-project left pixels with disparities (px) to points (N, 3) in the left camera frame."""
        z = self.fb / disparity
        return np.stack([(u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z], axis=1)

    def point_covariance(self, p: np.ndarray, sigma_px: float) -> np.ndarray:
        """First-order covariance (N, 3, 3) of triangulated points from isotropic pixel noise.

        Propagates sigma on (u_l, v, u_r) through the stereo back-projection; depth variance grows
        as z^4 sigma_d^2 / (f b)^2, which is why far points are weak in translation.
        """
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        d = self.fb / z
        # d p / d (u_l, v, u_r) with z = fb / (u_l - u_r)
        J = np.zeros((len(p), 3, 3))
        dz_dul = -z / d
        J[:, 2, 0], J[:, 2, 2] = dz_dul, z / d
        J[:, 0, 0] = z / self.fx + x / z * dz_dul
        J[:, 0, 2] = x / z * (z / d)
        J[:, 1, 0] = y / z * dz_dul
        J[:, 1, 1] = z / self.fy
        J[:, 1, 2] = y / z * (z / d)
        return sigma_px**2 * np.einsum("nij,nkj->nik", J, J)

    def to_dict(self) -> dict:
        """Plain-data form for JSON/maps."""
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "baseline": self.baseline,
            "width": self.width,
            "height": self.height,
            "T_vehicle_sensor": np.asarray(self.T_vehicle_sensor).tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> StereoCamera:
        return cls(
            fx=float(d["fx"]),
            fy=float(d["fy"]),
            cx=float(d["cx"]),
            cy=float(d["cy"]),
            baseline=float(d["baseline"]),
            width=int(d["width"]),
            height=int(d["height"]),
            T_vehicle_sensor=np.asarray(d.get("T_vehicle_sensor", np.eye(4)), float),
        )

    def matches(self, other: StereoCamera, rtol: float = 1e-4) -> bool:
        """True when two calibrations describe the same rectified pair (same size, K and baseline)."""
        a = np.array([self.fx, self.fy, self.cx, self.cy, self.baseline])
        b = np.array([other.fx, other.fy, other.cx, other.cy, other.baseline])
        return self.size == other.size and bool(np.allclose(a, b, rtol=rtol))


@dataclass(frozen=True)
class RawCamera:
    """One raw camera: pinhole intrinsics, radial-tangential distortion, pose on the body ``T_body_cam``."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    T_body_cam: np.ndarray


@dataclass(frozen=True)
class StereoRectifier:
    """Maps raw left/right images to a rectified pair described by ``camera``.

    ``T_rawleft_rect`` is the rotation from the rectified left frame to the raw left camera frame,
    so ``T_body_rect = T_body_rawleft @ T_rawleft_rect``.
    """

    camera: StereoCamera
    maps_left: tuple[np.ndarray, np.ndarray]
    maps_right: tuple[np.ndarray, np.ndarray]
    T_rawleft_rect: np.ndarray

    @classmethod
    def from_raw(
        cls, left: RawCamera, right: RawCamera, alpha: float = 0.0, where: str = "stereo calibration"
    ) -> StereoRectifier:
        """Rectify a raw pair (OpenCV ``stereoRectify``); alpha 0 keeps only valid pixels.

        ``CalibrationError`` naming ``where`` (the calibration files) for a pair OpenCV cannot rectify.
        """
        size = (left.width, left.height)
        if (right.width, right.height) != size:
            raise CalibrationError(
                f"{where}: left and right cameras differ in size: {size} vs {(right.width, right.height)}"
            )
        if min(size) <= 0:
            raise CalibrationError(f"{where}: image size {size[0]}x{size[1]} is empty")
        for side, raw in (("left", left), ("right", right)):
            if not (np.isfinite(raw.K).all() and np.isfinite(raw.dist).all() and np.isfinite(raw.T_body_cam).all()):
                raise CalibrationError(f"{where}: {side} camera has NaN or infinite calibration values")
            if raw.K[0, 0] <= 0 or raw.K[1, 1] <= 0:
                raise CalibrationError(f"{where}: {side} camera focal lengths must be positive")
            check_se3(raw.T_body_cam, f"{where}: {side} camera T_BS", tol=RIGID_TOLERANCE, error=CalibrationError)
        T_right_left = np.linalg.inv(right.T_body_cam) @ left.T_body_cam
        if np.linalg.norm(T_right_left[:3, 3]) < MIN_BASELINE_M:
            raise CalibrationError(
                f"{where}: left and right cameras are at the same place on the body "
                "(identical T_BS translations): no stereo baseline"
            )
        try:
            R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
                left.K,
                left.dist,
                right.K,
                right.dist,
                size,
                T_right_left[:3, :3].copy(),
                T_right_left[:3, 3].reshape(3, 1).copy(),
                flags=cv2.CALIB_ZERO_DISPARITY,
                alpha=alpha,
            )
        except cv2.error as err:
            raise CalibrationError(f"{where}: OpenCV cannot rectify this pair ({' '.join(str(err).split())})") from None
        fx = P1[0, 0]
        baseline = -P2[0, 3] / fx
        if not baseline > 0:
            raise CalibrationError(f"{where}: rectification gives a non-positive baseline: is left/right swapped?")
        T_rawleft_rect = np.eye(4)
        T_rawleft_rect[:3, :3] = R1.T
        cam = StereoCamera(
            fx=float(fx),
            fy=float(P1[1, 1]),
            cx=float(P1[0, 2]),
            cy=float(P1[1, 2]),
            baseline=float(baseline),
            width=size[0],
            height=size[1],
            T_vehicle_sensor=left.T_body_cam @ T_rawleft_rect,
        )
        ml = cv2.initUndistortRectifyMap(left.K, left.dist, R1, P1, size, cv2.CV_16SC2)
        mr = cv2.initUndistortRectifyMap(right.K, right.dist, R2, P2, size, cv2.CV_16SC2)
        return cls(cam, ml, mr, T_rawleft_rect)

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectify one raw greyscale pair."""
        l_img = cv2.remap(left, *self.maps_left, cv2.INTER_LINEAR)
        r_img = cv2.remap(right, *self.maps_right, cv2.INTER_LINEAR)
        return l_img, r_img
