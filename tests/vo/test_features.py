"""ORB features on a grid: the bucketing rule, and extraction on a real KITTI image."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.config import FeatureConfig
from vtr.vo.features import FeatureExtractor, bucket


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 400), n_keep=st.integers(1, 300))
def test_bucket_keeps_each_cells_strongest_and_at_most_n_keep(seed, n, n_keep):
    rng = np.random.default_rng(seed)
    # clustered positions: some cells crowded, others empty
    uv = np.clip(rng.normal([60, 30], [40, 15], (n, 2)), 0, [119.9, 59.9])
    response = rng.random(n)
    keep = bucket(uv, response, (120, 60), 4, 8, n_keep)
    assert len(keep) == min(n, n_keep) and len(np.unique(keep)) == len(keep)
    cell = (uv[:, 1] * 4 / 60).astype(int) * 8 + (uv[:, 0] * 8 / 120).astype(int)
    kept = np.zeros(n, bool)
    kept[keep] = True
    for c in np.unique(cell):
        here = cell == c
        if kept[here].any() and (~kept[here]).any():
            assert response[here & kept].min() >= response[here & ~kept].max()


def _cells_used(uv: np.ndarray, cfg: FeatureConfig, shape: tuple[int, ...]) -> int:
    cells = (uv[:, 1] * cfg.grid_rows / shape[0]).astype(int) * cfg.grid_cols + (
        uv[:, 0] * cfg.grid_cols / shape[1]
    ).astype(int)
    return len(np.unique(cells))


@pytest.mark.parametrize("score", ["fast", "harris"])
def test_extraction_on_kitti_spreads_features_over_the_grid(kitti_clip, score):
    image = cv2.imread(str(kitti_clip / "image_0" / "000010.png"), cv2.IMREAD_GRAYSCALE)
    size = (image.shape[1], image.shape[0])
    cfg = FeatureConfig(corner_score=score)
    f = FeatureExtractor(cfg, size).extract(image)
    assert 0.9 * cfg.n_features <= len(f) <= cfg.n_features
    assert f.descriptors.shape == (len(f), 32) and f.descriptors.dtype == np.uint8
    assert f.octave.min() >= 0 and f.octave.max() < cfg.n_levels
    # the same number of features taken by strength alone (no bucketing) crowd into fewer cells
    unbucketed = FeatureExtractor(FeatureConfig(corner_score=score, detect_factor=1.0), size).extract(image)
    assert _cells_used(f.uv, cfg, image.shape) >= _cells_used(unbucketed.uv, cfg, image.shape) + 5


def test_corner_scores_rank_differently(kitti_clip):
    image = cv2.imread(str(kitti_clip / "image_0" / "000010.png"), cv2.IMREAD_GRAYSCALE)
    size = (image.shape[1], image.shape[0])
    fast, harris = (FeatureExtractor(FeatureConfig(corner_score=s), size).extract(image) for s in ("fast", "harris"))
    shared = {tuple(p) for p in np.round(fast.uv, 1)} & {tuple(p) for p in np.round(harris.uv, 1)}
    assert len(shared) < 0.95 * min(len(fast), len(harris))
