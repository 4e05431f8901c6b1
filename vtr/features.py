"""Feature detection and description on a grid (ORB from OpenCV).

Features are detected over the whole pyramid, then bucketed on a ``grid_rows x grid_cols`` grid
so landmarks cover the image (VT&R3 uses a grid for the same reason), then described.
Pixel coordinates are level-0 (full resolution) left-image pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .config import FeatureConfig


@dataclass(frozen=True)
class Features:
    """Keypoints of one image: ``uv`` (N, 2) px, ``octave`` (N,), ``response`` (N,), ``descriptors`` (N, 32)."""

    uv: np.ndarray
    octave: np.ndarray
    response: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, idx: np.ndarray) -> Features:
        return Features(self.uv[idx], self.octave[idx], self.response[idx], self.descriptors[idx])


def bucket(uv: np.ndarray, response: np.ndarray, size: tuple[int, int], rows: int, cols: int,
           n_keep: int) -> np.ndarray:
    """Indices of at most ``n_keep`` features spread over a rows x cols grid.

    Each cell keeps its strongest features up to an equal quota; the quota left unused by
    sparse cells goes to the globally strongest remaining features.
    """
    w, h = size
    if len(uv) <= n_keep:
        return np.arange(len(uv))
    col = np.minimum((uv[:, 0] * cols / w).astype(int), cols - 1)
    row = np.minimum((uv[:, 1] * rows / h).astype(int), rows - 1)
    cell = row * cols + col
    order = np.lexsort((-response, cell))           # by cell, strongest first
    sorted_cell = cell[order]
    first = np.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = np.empty(len(uv), int)
    rank[order] = np.arange(len(uv)) - first          # rank within its cell
    quota = max(1, n_keep // (rows * cols))
    keep = rank < quota
    n_extra = n_keep - int(keep.sum())
    if n_extra > 0:
        rest = np.flatnonzero(~keep)
        keep[rest[np.argsort(-response[rest])[:n_extra]]] = True
    elif n_extra < 0:
        kept = np.flatnonzero(keep)
        keep[:] = False
        keep[kept[np.argsort(-response[kept])[:n_keep]]] = True
    return np.flatnonzero(keep)


class FeatureExtractor:
    """ORB detector/descriptor with grid bucketing, built from ``FeatureConfig``."""

    def __init__(self, config: FeatureConfig, image_size: tuple[int, int]):
        self.config = config
        self.image_size = image_size
        self._orb = cv2.ORB_create(
            nfeatures=int(config.n_features * config.detect_factor),
            scaleFactor=config.scale_factor,
            nlevels=config.n_levels,
            edgeThreshold=config.edge_threshold,
            patchSize=config.edge_threshold + 12,
            fastThreshold=config.fast_threshold,
        )

    @property
    def level_scales(self) -> np.ndarray:
        """Scale of each pyramid level relative to level 0."""
        return self.config.scale_factor ** np.arange(self.config.n_levels)

    def extract(self, image: np.ndarray) -> Features:
        """Detect, bucket and describe features of one greyscale image."""
        kps = self._orb.detect(image, None)
        if not kps:
            return _empty()
        uv = cv2.KeyPoint_convert(kps).astype(np.float64)
        response = np.fromiter((k.response for k in kps), np.float64, len(kps))
        c = self.config
        keep = bucket(uv, response, self.image_size, c.grid_rows, c.grid_cols, c.n_features)
        kps = [kps[i] for i in keep]
        kps, desc = self._orb.compute(image, kps)
        if desc is None or not kps:
            return _empty()
        return Features(
            uv=cv2.KeyPoint_convert(kps).astype(np.float64),
            octave=np.fromiter((k.octave for k in kps), np.int32, len(kps)),
            response=np.fromiter((k.response for k in kps), np.float64, len(kps)),
            descriptors=desc,
        )


def _empty() -> Features:
    return Features(np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0), np.zeros((0, 32), np.uint8))


def hamming_pairs(a: np.ndarray, b: np.ndarray, ia: np.ndarray, jb: np.ndarray) -> np.ndarray:
    """Hamming distances between descriptors ``a[ia]`` and ``b[jb]`` (binary, 32 bytes each)."""
    if len(ia) == 0:
        return np.zeros(0, np.int32)
    a64 = np.ascontiguousarray(a).view(np.uint64)
    b64 = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(a64[ia] ^ b64[jb]).sum(axis=1, dtype=np.int32)


def best_matches(dist: np.ndarray, ia: np.ndarray, jb: np.ndarray, max_distance: int,
                 ratio: float = 1.0, mutual: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pick one match per query among candidate pairs (ia[k], jb[k]) with distances dist[k].

    Keeps the best candidate of each query when it is within ``max_distance``, passes the ratio
    test against the query's second-best candidate (``best < ratio * second``) and, with
    ``mutual``, is also the best query for its train feature. Returns (ia, jb, dist) of matches.
    """
    if len(ia) == 0:
        e = np.zeros(0, int)
        return e, e, np.zeros(0, np.int32)
    big = np.int64(np.max(dist)) + 1
    order = np.argsort(ia.astype(np.int64) * big + dist, kind="stable")   # by query, closest first
    ia_s, jb_s, d_s = ia[order], jb[order], dist[order]
    first = np.r_[True, ia_s[1:] != ia_s[:-1]]
    best = np.flatnonzero(first)
    ok = d_s[best] <= max_distance
    if ratio < 1.0:
        has_second = np.r_[best[1:] - best[:-1] > 1, len(ia_s) - best[-1] > 1]
        second = np.where(has_second, d_s[np.minimum(best + 1, len(d_s) - 1)], np.iinfo(np.int32).max)
        ok &= d_s[best] < ratio * second
    best = best[ok]
    qi, tj, dd = ia_s[best], jb_s[best], d_s[best]
    if mutual and len(qi):
        # for every train feature keep the closest query
        o = np.argsort(tj.astype(np.int64) * big + dd, kind="stable")
        keep_first = np.r_[True, tj[o][1:] != tj[o][:-1]]
        sel = o[keep_first]
        qi, tj, dd = qi[sel], tj[sel], dd[sel]
    return qi, tj, dd


def radius_pairs(pred_uv: np.ndarray, uv: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (i, j) with ``|pred_uv[i] - uv[j]| <= radius`` (px), via KD-trees."""
    from scipy.spatial import cKDTree

    if len(pred_uv) == 0 or len(uv) == 0:
        e = np.zeros(0, int)
        return e, e
    sdm = cKDTree(pred_uv).sparse_distance_matrix(cKDTree(uv), radius, output_type="ndarray")
    return sdm["i"].astype(int), sdm["j"].astype(int)
