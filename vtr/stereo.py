"""Stereo processing of one rectified pair: left-right matching on epipolar rows, subpixel
disparity, triangulation into 3-D landmarks (left rectified camera frame) with covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import StereoCamera
from .config import FeatureConfig, StereoConfig
from .features import FeatureExtractor, Features, best_matches, hamming_pairs
from .io.base import StereoImages
from .timing import StageTimer


@dataclass(frozen=True)
class StereoFrame:
    """Features of the left image with their stereo measurements.

    ``u_right`` (N,) is the matched right-image column (NaN when unmatched); ``points`` (N, 3) the
    triangulated landmark in the left camera frame (NaN rows when unmatched), metres.
    """

    t_ns: int
    index: int
    features: Features
    u_right: np.ndarray
    points: np.ndarray

    @property
    def has_depth(self) -> np.ndarray:
        return np.isfinite(self.u_right)

    @property
    def stereo_measurements(self) -> np.ndarray:
        """(N, 3) measurements u_l, v, u_r (u_r NaN when unmatched)."""
        return np.column_stack([self.features.uv, self.u_right])


def row_band_pairs(uv_l: np.ndarray, oct_l: np.ndarray, uv_r: np.ndarray, scales: np.ndarray,
                   cfg: StereoConfig) -> tuple[np.ndarray, np.ndarray]:
    """Candidate left/right pairs on (nearly) the same row within the disparity limits."""
    if len(uv_l) == 0 or len(uv_r) == 0:
        e = np.zeros(0, int)
        return e, e
    order = np.argsort(uv_r[:, 1])
    v_sorted = uv_r[order, 1]
    tol = cfg.max_row_diff_px * scales[oct_l]
    lo = np.searchsorted(v_sorted, uv_l[:, 1] - tol, side="left")
    hi = np.searchsorted(v_sorted, uv_l[:, 1] + tol, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(len(uv_l)), counts)
    offs = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    jb = order[np.repeat(lo, counts) + offs]
    disp = uv_l[ia, 0] - uv_r[jb, 0]
    ok = (disp >= cfg.min_disparity_px - cfg.refine_search_px) & (disp <= cfg.max_disparity_px)
    return ia[ok], jb[ok]


def refine_disparity(left: np.ndarray, right: np.ndarray, u_l: np.ndarray, v_l: np.ndarray,
                     u_r: np.ndarray, half: int, search: int) -> tuple[np.ndarray, np.ndarray]:
    """Subpixel right-image columns by SAD block matching along the row around ``u_r``.

    Left patches are centred on the rounded left keypoints; the returned left columns are those
    rounded positions. Returns (u_left_px, u_right_px), with NaN right columns where the SAD
    minimum sits on the search border (no reliable match).
    """
    h, w = left.shape
    ul = np.rint(u_l).astype(int)
    vl = np.rint(v_l).astype(int)
    ur = np.rint(u_r).astype(int)
    pad = half + search + 1
    ok = (ul >= pad) & (ul < w - pad) & (ur >= pad) & (ur < w - pad) & (vl >= half) & (vl < h - half)
    out = np.full(len(u_l), np.nan)
    if not np.any(ok):
        return ul.astype(float), out
    ulo, vlo, uro = ul[ok], vl[ok], ur[ok]
    d = np.arange(-half, half + 1)
    rows = (vlo[:, None] + d[None, :])[:, :, None]                       # (n, P, 1)
    lp = left[rows, (ulo[:, None] + d[None, :])[:, None, :]].astype(np.int32)  # (n, P, P)
    lp -= lp.mean(axis=(1, 2), keepdims=True, dtype=np.int32)
    shifts = np.arange(-search, search + 1)
    cols = uro[:, None, None] + shifts[None, :, None] + d[None, None, :]   # (n, S, P)
    strip = right[rows[:, None, :, :], cols[:, :, None, :]].astype(np.int32)  # (n, S, P, P)
    strip -= strip.mean(axis=(2, 3), keepdims=True, dtype=np.int32)
    sad = ((strip - lp[:, None]).astype(float) ** 2).sum(axis=(2, 3))     # (n, S)
    k = np.argmin(sad, axis=1)
    inner = (k > 0) & (k < 2 * search)
    kk = np.clip(k, 1, 2 * search - 1)
    idx = np.arange(len(k))
    c_m, c_0, c_p = sad[idx, kk - 1], sad[idx, kk], sad[idx, kk + 1]
    denom = c_m - 2 * c_0 + c_p
    delta = np.where(denom > 0, 0.5 * (c_m - c_p) / np.where(denom > 0, denom, 1), 0.0)
    refined = uro + shifts[kk] + np.clip(delta, -1, 1)
    out[np.flatnonzero(ok)[inner]] = refined[inner]
    return ul.astype(float), out


class StereoProcessor:
    """Turns a rectified stereo pair into a ``StereoFrame``."""

    def __init__(self, camera: StereoCamera, features: FeatureConfig, stereo: StereoConfig,
                 timer: StageTimer | None = None):
        self.camera = camera
        self.timer = timer or StageTimer()
        self.cfg = stereo
        self.extractor = FeatureExtractor(features, camera.size)
        self.scales = self.extractor.level_scales

    def match(self, left: Features, right: Features) -> tuple[np.ndarray, np.ndarray]:
        """Left/right matches on epipolar rows: (left indices, right indices)."""
        ia, jb = row_band_pairs(left.uv, left.octave, right.uv, self.scales, self.cfg)
        near_scale = np.abs(left.octave[ia] - right.octave[jb]) <= 1
        ia, jb = ia[near_scale], jb[near_scale]
        dist = hamming_pairs(left.descriptors, right.descriptors, ia, jb)
        qi, tj, _ = best_matches(dist, ia, jb, self.cfg.max_descriptor_distance, mutual=True)
        return qi, tj

    def process(self, images: StereoImages) -> StereoFrame:
        """Features on both images, stereo matches, subpixel disparity, triangulation."""
        with self.timer("features"):
            left = self.extractor.extract(images.left)
            right = self.extractor.extract(images.right)
        with self.timer("stereo"):
            return self._triangulate(images, left, right)

    def _triangulate(self, images: StereoImages, left: Features, right: Features) -> StereoFrame:
        qi, tj = self.match(left, right)
        c = self.cfg
        ul, ur = refine_disparity(images.left, images.right, left.uv[qi, 0], left.uv[qi, 1],
                                  right.uv[tj, 0], c.refine_half_window, c.refine_search_px)
        disp = ul - ur
        good = np.isfinite(ur) & (disp >= c.min_disparity_px) & (disp <= c.max_disparity_px)
        qi, ul, ur = qi[good], ul[good], ur[good]
        uv = left.uv.copy()
        uv[qi, 0] = ul
        uv[qi, 1] = np.rint(uv[qi, 1])
        feats = Features(uv, left.octave, left.response, left.descriptors)
        u_right = np.full(len(uv), np.nan)
        u_right[qi] = ur
        points = np.full((len(uv), 3), np.nan)
        points[qi] = self.camera.triangulate(uv[qi, 0], uv[qi, 1], ul - ur)
        return StereoFrame(images.t_ns, images.index, feats, u_right, points)
