"""How much of a trajectory's scale error the data itself owes: stereo disparities against ground truth.

Two checks on a source with ground truth, independent of the odometry:

* :func:`disparity_offset` matches features between frames ``k`` and ``k + step``, triangulates each
  from the two left views with the *ground-truth* motion (no disparity involved), and compares the
  disparity that depth implies with the disparity the stereo pair measured. A robust line
  ``measured = slope * implied + offset`` separates a systematic disparity error (``offset``, e.g.
  a rectification error) from a scale error of the ground truth (``slope``).
* :func:`near_point_scale` holds the stereo-triangulated landmarks of frame ``k`` with disparity
  above a threshold fixed and fits the one factor ``s`` on the ground-truth translation that best
  explains where they are seen in frame ``k + 1``: the path-length factor an estimator that trusted
  those depths would report, even with perfect matching and rotation.

See docs/far_structure.md for the figures on the shipped clips.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..camera import StereoCamera
from ..config import Config
from ..errors import DataError
from ..geometry import inv_T
from ..io.base import FrameSource
from ..types import StereoFrame
from ..vo.matching import match_to_landmarks
from ..vo.stereo import StereoProcessor

MATCH_RADIUS_PX = 8.0  # matching around the ground-truth prediction
MATCH_RATIO = 0.8
MIN_PARALLAX_DEG = 1.0  # two-view triangulation needs this much angle between the rays
MAX_REPROJECTION_PX = 0.5  # ... and rays that (nearly) meet
MAX_IMPLIED_DISPARITY_PX = 60.0  # the line is fitted where disparities are small enough to show an offset
HUBER_K = 1.5  # robust fits: Huber weights at this many robust sigmas
ROBUST_ITERATIONS = 10
SCALE_THRESHOLDS_PX = (30.0, 15.0, 5.0, 1.0)


@dataclass(frozen=True)
class DisparityOffset:
    """``measured = slope * implied + offset_px`` over ``points`` features; ``sigma_px`` the robust spread."""

    slope: float
    offset_px: float
    sigma_px: float
    points: int

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class DisparitySamples:
    """Per matched feature: measured disparity, disparity implied by the ground-truth motion, ray angle."""

    measured_px: np.ndarray
    implied_px: np.ndarray
    parallax_deg: np.ndarray


def _frames(source: FrameSource, config: Config) -> tuple[list[StereoFrame], np.ndarray]:
    gt = source.ground_truth()
    if gt is None:
        raise DataError(f"{source.path}: the scale check needs ground truth")
    processor = StereoProcessor(source.camera, config.features, config.stereo)
    frames = [processor.process(images) for images in source]
    times = np.array([f.t_ns for f in frames], np.int64)
    idx = np.searchsorted(gt.t_ns, times).clip(0, len(gt.t_ns) - 1)
    if not np.array_equal(gt.t_ns[idx], times):
        raise DataError(f"{source.path}: ground truth does not cover every frame time")
    return frames, gt.T_world_cam[idx]


def _rays(camera: StereoCamera, uv: np.ndarray) -> np.ndarray:
    return np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))])


def disparity_samples(source: FrameSource, config: Config, steps: tuple[int, ...] = (1, 2, 3)) -> DisparitySamples:
    """Measured against motion-implied disparities of features matched between frames ``k`` and ``k + step``."""
    camera = source.camera
    frames, T_world_cam = _frames(source, config)
    out: list[np.ndarray] = []
    for step in steps:
        for k in range(len(frames) - step):
            a, b = frames[k], frames[k + step]
            T_b_a = inv_T(T_world_cam[k + step]) @ T_world_cam[k]
            ia, ib = match_to_landmarks(
                a, b, T_b_a, camera, MATCH_RADIUS_PX, config.odometry.max_descriptor_distance, MATCH_RATIO
            )
            if len(ia) == 0:
                continue
            ra = _rays(camera, a.features.uv[ia]) @ T_b_a[:3, :3].T  # ray of a, in b
            rb = _rays(camera, b.features.uv[ib])
            t = T_b_a[:3, 3]
            # depths (za, zb) with za * ra + t = zb * rb, least squares per feature (2x2 normal equations)
            a11, a12, a22 = (ra * ra).sum(1), -(ra * rb).sum(1), (rb * rb).sum(1)
            b1, b2 = -(ra @ t), rb @ t
            det = a11 * a22 - a12 * a12
            with np.errstate(divide="ignore", invalid="ignore"):  # parallel rays: no depth (dropped below)
                za = (a22 * b1 - a12 * b2) / det
            P = za[:, None] * ra + t
            reproj = np.hypot(
                camera.fx * P[:, 0] / P[:, 2] + camera.cx - b.features.uv[ib, 0],
                camera.fy * P[:, 1] / P[:, 2] + camera.cy - b.features.uv[ib, 1],
            )
            cos = (ra * rb).sum(1) / np.linalg.norm(ra, axis=1) / np.linalg.norm(rb, axis=1)
            parallax = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
            measured = a.features.uv[ia, 0] - a.u_right[ia]
            ok = (za > 0) & (reproj < MAX_REPROJECTION_PX) & np.isfinite(measured)
            out.append(np.column_stack([measured[ok], camera.fb / za[ok], parallax[ok]]))
    if not out:
        raise DataError(f"{source.path}: no feature could be matched between frames")
    s = np.concatenate(out)
    return DisparitySamples(s[:, 0], s[:, 1], s[:, 2])


def _robust_line(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Huber-weighted least squares of ``y = a x + b``: ((a, b), robust sigma)."""
    A = np.column_stack([x, np.ones(len(x))])
    w: np.ndarray = np.ones(len(x))
    coef, sigma = np.zeros(2), float("nan")
    for _ in range(ROBUST_ITERATIONS):
        coef = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)[0]
        r = y - A @ coef
        sigma = float(1.4826 * np.median(np.abs(r))) + 1e-12
        w = 1.0 / np.sqrt(np.maximum(1.0, np.abs(r) / (HUBER_K * sigma)))
    return coef, sigma


def disparity_offset(samples: DisparitySamples) -> DisparityOffset:
    """The robust line through (implied, measured) disparities of well-triangulated features."""
    ok = (
        (samples.parallax_deg >= MIN_PARALLAX_DEG)
        & (samples.implied_px > 0)
        & (samples.implied_px < MAX_IMPLIED_DISPARITY_PX)
    )
    if ok.sum() < 10:
        raise DataError(f"only {int(ok.sum())} features triangulate well enough from the motion")
    (slope, offset), sigma = _robust_line(samples.implied_px[ok], samples.measured_px[ok])
    return DisparityOffset(float(slope), float(offset), sigma, int(ok.sum()))


def near_point_scale(
    source: FrameSource, config: Config, thresholds_px: tuple[float, ...] = SCALE_THRESHOLDS_PX
) -> dict[float, float]:
    """For each disparity threshold, the ground-truth translation factor ``s`` that best explains frame
    ``k + 1``'s view of frame ``k``'s stereo landmarks with at least that disparity, held fixed."""
    camera = source.camera
    frames, T_world_cam = _frames(source, config)
    rows = []
    for k in range(len(frames) - 1):
        a, b = frames[k], frames[k + 1]
        T_b_a = inv_T(T_world_cam[k + 1]) @ T_world_cam[k]
        ia, ib = match_to_landmarks(
            a, b, T_b_a, camera, MATCH_RADIUS_PX, config.odometry.max_descriptor_distance, MATCH_RATIO
        )
        Y = a.points[ia] @ T_b_a[:3, :3].T  # rotated landmark, before the translation
        d = a.features.uv[ia, 0] - a.u_right[ia]
        rows.append(np.column_stack([Y, np.repeat(T_b_a[None, :3, 3], len(ia), 0), b.features.uv[ib], d]))
    R = np.concatenate(rows)
    out = {}
    for thr in thresholds_px:
        m = R[R[:, 8] >= thr]
        if len(m) < 10:
            out[thr] = float("nan")
            continue
        Y, t, uv = m[:, 0:3], m[:, 3:6], m[:, 6:8]
        s = 1.0
        for _ in range(ROBUST_ITERATIONS):  # Gauss-Newton on s with Huber weights
            P = Y + s * t
            u = camera.fx * P[:, 0] / P[:, 2] + camera.cx
            v = camera.fy * P[:, 1] / P[:, 2] + camera.cy
            du = camera.fx * (t[:, 0] * P[:, 2] - P[:, 0] * t[:, 2]) / P[:, 2] ** 2
            dv = camera.fy * (t[:, 1] * P[:, 2] - P[:, 1] * t[:, 2]) / P[:, 2] ** 2
            r = np.concatenate([uv[:, 0] - u, uv[:, 1] - v])
            J = np.concatenate([du, dv])
            sigma = 1.4826 * np.median(np.abs(r)) + 1e-12
            w = 1.0 / np.maximum(1.0, np.abs(r) / (HUBER_K * sigma))
            s += float((w * J * r).sum() / (w * J * J).sum())
        out[thr] = s
    return out
