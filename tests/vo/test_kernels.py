"""Compiled kernels against plain-Python statements of what they compute."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.vo.features import match_all, match_within_radius
from vtr.vo.kernels import matching as km
from vtr.vo.stereo import refine_disparity


def _hamming(a: np.ndarray, b: np.ndarray) -> int:
    return int(np.unpackbits(np.bitwise_xor(a, b)).sum())


def _reference_match(candidates, n_query, n_train, dist, gap, max_distance, ratio, mutual):
    """The documented rule, one query at a time: closest (ties: smaller gap, lower index), ratio, mutual."""
    best = {}
    for q in range(n_query):
        cands = sorted((dist(q, j), gap(q, j), j) for j in candidates(q))
        if not cands or cands[0][0] > max_distance:
            continue
        if ratio < 1.0 and not cands[0][0] < ratio * (cands[1][0] if len(cands) > 1 else np.inf):
            continue
        best[q] = cands[0]
    if mutual:
        owner = {}
        for q, (d, g, j) in sorted(best.items()):
            if j not in owner or (d, g) < owner[j][1:]:
                owner[j] = (q, d, g)
        best = {q: v for q, v in best.items() if owner[v[2]][0] == q}
    return sorted((q, v[2]) for q, v in best.items())


def _descriptors(rng, n, pool):
    """Descriptors drawn from a small pool plus bit noise, so equal and near distances are common."""
    base = rng.integers(0, 256, (pool, 32), dtype=np.uint8)
    out = base[rng.integers(0, pool, n)].copy()
    flips = rng.random((n, 32)) < 0.05
    out[flips] ^= rng.integers(1, 256, flips.sum(), dtype=np.uint8)
    return out


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_q=st.integers(0, 40),
    n_t=st.integers(0, 40),
    radius=st.sampled_from([3.0, 10.0, 40.0]),
    ratio=st.sampled_from([0.8, 1.0]),
    mutual=st.booleans(),
)
def test_radius_match_follows_the_documented_rule(seed, n_q, n_t, radius, ratio, mutual):
    rng = np.random.default_rng(seed)
    pred = rng.uniform(0, 60, (n_q, 2)).round()  # integer positions: equal gaps happen too
    uv = rng.uniform(0, 60, (n_t, 2)).round()
    dq, dt = _descriptors(rng, n_q, 6), _descriptors(rng, n_t, 6)
    qi, tj = match_within_radius(pred, dq, uv, dt, radius, 40, ratio=ratio, mutual=mutual)
    gap2 = lambda q, j: float(((pred[q] - uv[j]) ** 2).sum())  # noqa: E731
    expected = _reference_match(
        lambda q: [j for j in range(n_t) if gap2(q, j) <= radius**2],
        n_q,
        n_t,
        lambda q, j: _hamming(dq[q], dt[j]),
        gap2,
        40,
        ratio,
        mutual,
    )
    assert sorted(zip(qi.tolist(), tj.tolist(), strict=True)) == expected


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_q=st.integers(0, 30), n_t=st.integers(0, 30))
def test_all_pairs_match_follows_the_documented_rule(seed, n_q, n_t):
    rng = np.random.default_rng(seed)
    dq, dt = _descriptors(rng, n_q, 5), _descriptors(rng, n_t, 5)
    qi, tj = match_all(dq, dt, 50, ratio=0.9)
    expected = _reference_match(
        lambda q: range(n_t), n_q, n_t, lambda q, j: _hamming(dq[q], dt[j]), lambda q, j: 0.0, 50, 0.9, True
    )
    assert sorted(zip(qi.tolist(), tj.tolist(), strict=True)) == expected


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_l=st.integers(0, 40), n_r=st.integers(0, 40))
def test_row_band_match_follows_the_documented_rule(seed, n_l, n_r):
    rng = np.random.default_rng(seed)
    uv_l = np.column_stack([rng.uniform(0, 100, n_l), rng.integers(0, 12, n_l)]).astype(float)
    uv_r = np.column_stack([rng.uniform(0, 100, n_r), rng.integers(0, 12, n_r)]).astype(float)
    oct_l, oct_r = rng.integers(0, 4, n_l), rng.integers(0, 4, n_r)
    dl, dr = _descriptors(rng, n_l, 6), _descriptors(rng, n_r, 6)
    row_tol = 1.5 * 1.2 ** np.arange(4)

    def candidates(i):
        return [
            j
            for j in range(n_r)
            if abs(uv_l[i, 1] - uv_r[j, 1]) <= row_tol[oct_l[i]]
            and 0.0 <= uv_l[i, 0] - uv_r[j, 0] <= 60.0
            and abs(oct_l[i] - oct_r[j]) <= 1
        ]

    qi, tj, _ = km.row_band_match(uv_l, oct_l, km_words(dl), uv_r, oct_r, km_words(dr), row_tol, 0.0, 60.0, 1, 64)
    expected = _reference_match(
        candidates,
        n_l,
        n_r,
        lambda i, j: _hamming(dl[i], dr[j]),
        lambda i, j: abs(uv_l[i, 1] - uv_r[j, 1]) + abs(oct_l[i] - oct_r[j]),
        64,
        1.0,
        True,
    )
    assert sorted(zip(qi.tolist(), tj.tolist(), strict=True)) == expected


def km_words(d: np.ndarray) -> np.ndarray:
    from vtr.vo.features import descriptor_words

    return descriptor_words(d)


def test_refine_disparity_recovers_known_subpixel_shifts(kitti_clip):
    """A real KITTI image shifted by a known disparity: the SSD parabola recovers it to ~0.05 px."""
    left = cv2.imread(str(kitti_clip / "image_0" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    corners = cv2.goodFeaturesToTrack(left, 400, 0.01, 10).reshape(-1, 2)
    for d in (7.0, 12.25, 20.5, 31.75):
        right = cv2.warpAffine(left, np.float32([[1, 0, -d], [0, 1, 0]]), left.shape[::-1], flags=cv2.INTER_CUBIC)
        guess = corners[:, 0] - d + np.random.default_rng(1).integers(-1, 2, len(corners))
        ul, ur = refine_disparity(left, right, corners[:, 0], corners[:, 1], guess, 5, 3)
        err = (ul - ur) - d
        ok = np.isfinite(err)
        assert ok.mean() > 0.8
        assert abs(np.mean(err[ok])) < 0.03
        assert np.percentile(np.abs(err[ok]), 90) < 0.1


def test_refine_disparity_marks_border_minima_and_image_edges_unmatched():
    rng = np.random.default_rng(0)
    smooth = cv2.GaussianBlur(rng.uniform(0, 255, (40, 80)), (0, 0), 4)  # SSD falls steadily toward the match
    left = cv2.normalize(smooth, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    right = np.roll(left, -5, axis=1)  # true disparity 5 px
    u = np.array([30.0, 30.0, 2.0])
    ul, ur = refine_disparity(left, right, u, np.array([20.0, 20.0, 20.0]), np.array([25.0, 29.0, 0.0]), 3, 2)
    assert abs((ul - ur)[0] - 5.0) < 0.25  # found inside the search window
    assert np.isnan(ur[1])  # true match 4 px away: beyond +-2 px
    assert np.isnan(ur[2])  # patch leaves the image
