"""Online self-calibration of a stereo pair's disparity offset (a rectification error the calibration does not know).

A right camera whose principal point sits a fraction of a pixel off the one the calibration states shifts every
disparity by the same amount ``c``: ``measured = true + c``. Depth from one disparity cannot show it (it is as
plausible as a scale), but motion can: the depth a landmark's *left-image rays* across the window give (parallax, no
disparity involved) implies a disparity ``fb / z`` that is the true one times the window's scale ``s`` (whatever the
motion's scale error), so ``measured = (1 / s) * implied + c`` over the window's landmarks: the slope takes the
scale, which motion cannot observe, and the intercept is the offset, which it can. Near and far points disagree with
any single scale when ``c`` is not 0, which is what the fit sees.

:class:`DisparityOffsetEstimator` collects those samples at each keyframe (the newest keyframe's observations of
landmarks its window triangulates from parallax), fits the robust line over every sample so far and hands out the
offset to remove, shrunk towards 0 by its uncertainty (weak evidence leaves it at 0; the estimate moves smoothly,
never switches). docs/odometry_stability.md has the figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import StereoCamera
from ..config import OdometryConfig
from ..types import StereoFrame
from .estimation import triangulate_bearings
from .matching import MIN_DEPTH_M

HUBER_K = 1.5  # robust line: Huber weights beyond this many robust sigmas (as tools/scale_check.py)
ROBUST_ITERATIONS = 10
MAD_TO_SIGMA = 1.4826  # median absolute deviation -> standard deviation of a normal distribution


@dataclass(frozen=True)
class OffsetFit:
    """``measured = slope * implied + offset_px`` over ``samples``; ``offset_se_px`` the offset's standard error."""

    offset_px: float
    offset_se_px: float
    slope: float
    sigma_px: float
    samples: int


def robust_line(implied: np.ndarray, measured: np.ndarray) -> OffsetFit:
    """Huber-weighted least squares of ``measured = slope * implied + offset`` with the offset's standard error.

    Each reweighting solves the 2x2 normal equations from weighted sums (no design matrix is formed): the cost per
    keyframe stays a few vector passes over the samples however many the window keeps."""
    x = np.asarray(implied, float)
    y = np.asarray(measured, float)
    w = np.ones(len(x))
    slope, offset, sigma = 0.0, 0.0, 1.0
    for _ in range(ROBUST_ITERATIONS):
        N, b = _normal_equations(w, x, y)
        slope, offset = np.linalg.solve(N, b)
        r = y - (slope * x + offset)
        sigma = float(MAD_TO_SIGMA * np.median(np.abs(r))) + 1e-12
        w = 1.0 / np.maximum(1.0, np.abs(r) / (HUBER_K * sigma))
    cov = sigma**2 * np.linalg.inv(_normal_equations(w, x, y)[0])
    return OffsetFit(float(offset), float(np.sqrt(cov[1, 1])), float(slope), sigma, len(x))


def _normal_equations(w: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted line fit's 2x2 normal equations, summed without BLAS (whose threads stall a loaded machine on
    vectors of this length)."""
    wx = w * x
    sxx, sx, sw = np.einsum("i,i->", wx, x), wx.sum(), w.sum()
    return np.array([[sxx, sx], [sx, sw]]), np.array([np.einsum("i,i->", wx, y), np.einsum("i,i->", w, y)])


def window_samples(
    T_cam_world: np.ndarray,
    slot: np.ndarray,
    lm_local: np.ndarray,
    z: np.ndarray,
    camera: StereoCamera,
    n_points: int,
    min_parallax_rad: float,
    max_ray_error_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(implied, measured) disparities of the newest pose's observations (``slot`` = last) of the window's landmarks
    whose left-image rays span at least ``min_parallax_rad`` and meet within ``max_ray_error_px`` in every view:
    ``implied = fb / depth`` of the ray triangulation, ``measured`` the raw stereo disparity."""
    tri, parallax = triangulate_bearings(T_cam_world, slot, lm_local, z[:, :2], camera, n_points)
    ok_point = np.isfinite(tri).all(1) & (parallax >= min_parallax_rad)
    P = T_cam_world[slot, :3, :3] @ np.nan_to_num(tri[lm_local])[:, :, None]
    P = P[:, :, 0] + T_cam_world[slot, :3, 3]
    depth = P[:, 2]
    in_front = depth > MIN_DEPTH_M
    safe = np.where(in_front, depth, 1.0)
    err = np.hypot(camera.fx * P[:, 0] / safe + camera.cx - z[:, 0], camera.fy * P[:, 1] / safe + camera.cy - z[:, 1])
    fits = in_front & (err <= max_ray_error_px)
    ok_all = ok_point.copy()
    np.logical_and.at(ok_all, lm_local, fits)
    newest = slot == T_cam_world.shape[0] - 1
    measured = z[:, 0] - z[:, 2]
    use = newest & ok_all[lm_local] & np.isfinite(measured)
    return camera.fb / depth[use], measured[use]


class DisparityOffsetEstimator:
    """The disparity offset of a stereo pair, from every keyframe's window so far (see the module docstring).

    ``offset_px`` is what to *remove* from measured disparities: the fitted intercept shrunk towards 0 by
    ``odometry.disparity_offset_shrink_sigmas`` of its standard error; 0 until ``disparity_offset_min_samples``
    samples are in and while the shrunk offset is below ``disparity_offset_min_px``. The fit keeps the latest
    keyframes' samples, at least ``disparity_offset_max_samples`` of them (a long route's cost stays flat, and an
    offset that drifts, e.g. with temperature, is followed). Samples: landmarks whose rays
    span ``disparity_offset_min_parallax_deg`` and meet within ``pixel_sigma`` in every view.
    """

    def __init__(self, camera: StereoCamera, config: OdometryConfig, pixel_sigma: float):
        self.camera = camera
        self.config = config
        self.pixel_sigma = pixel_sigma
        self._implied: list[np.ndarray] = []
        self._measured: list[np.ndarray] = []
        self.fit: OffsetFit | None = None
        self.offset_px = 0.0

    @property
    def samples(self) -> int:
        return sum(len(m) for m in self._measured)

    def add_window(
        self, T_cam_world: np.ndarray, slot: np.ndarray, lm_local: np.ndarray, z: np.ndarray, n_points: int
    ) -> float:
        """Add the newest keyframe's samples from the window (poses ``T_cam_world``, observations ``slot``,
        ``lm_local`` and raw measurements ``z`` (M, 3)); returns the offset to remove now."""
        cfg = self.config
        implied, measured = window_samples(
            T_cam_world,
            slot,
            lm_local,
            z,
            self.camera,
            n_points,
            np.radians(cfg.disparity_offset_min_parallax_deg),
            self.pixel_sigma,
        )
        self._implied.append(implied)
        self._measured.append(measured)
        while len(self._measured) > 1 and self.samples - len(self._measured[0]) >= cfg.disparity_offset_max_samples:
            del self._implied[0], self._measured[0]  # the oldest keyframe's samples: memory and cost stay bounded
        if self.samples < cfg.disparity_offset_min_samples:
            return self.offset_px
        self.fit = robust_line(np.concatenate(self._implied), np.concatenate(self._measured))
        margin = cfg.disparity_offset_shrink_sigmas * self.fit.offset_se_px
        shrunk = max(0.0, abs(self.fit.offset_px) - margin)
        self.offset_px = float(np.sign(self.fit.offset_px) * shrunk) if shrunk >= cfg.disparity_offset_min_px else 0.0
        return self.offset_px


def corrected(frame: StereoFrame, camera: StereoCamera, offset_px: float, min_disparity_px: float) -> StereoFrame:
    """``frame`` with ``offset_px`` removed from every disparity (the right column moved by it) and its points
    triangulated again; a disparity left below ``min_disparity_px`` becomes unmatched, as stereo matching treats it."""
    if offset_px == 0.0:
        return frame
    u_right = frame.u_right + offset_px
    disparity = frame.features.uv[:, 0] - u_right
    keep = np.isfinite(disparity) & (disparity >= min_disparity_px)
    u_right = np.where(keep, u_right, np.nan)
    points = np.full_like(frame.points, np.nan)
    points[keep] = camera.triangulate(frame.features.uv[keep, 0], frame.features.uv[keep, 1], disparity[keep])
    return StereoFrame(frame.t_ns, frame.index, frame.features, u_right, points)
