"""Kernels of binary-descriptor matching (``vtr.vo.features``, ``vtr.vo.stereo``).

Descriptors are 256-bit ORB strings viewed as four uint64 words (N, 4). A query keeps its closest
candidate when it is within ``max_distance``, passes the ratio test against its second-closest
candidate (``best < ratio * second``; ratio >= 1 disables it) and, after all queries, is the
closest query of its train feature. Equal descriptor distances go to the candidate nearer in the
image (nearer the prediction; on stereo rows, the closer row and pyramid level), then the lower index.
"""

from __future__ import annotations

import numpy as np
from numba import njit

NO_MATCH = -1
_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


@njit(cache=True, nogil=True)
def _popcount(x):
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return int((x * _H01) >> np.uint64(56))


@njit(cache=True, nogil=True)
def hamming(a, i, b, j):
    """Hamming distance between descriptor a[i] and b[j] (uint64 words)."""
    d = 0
    for w in range(a.shape[1]):
        d += _popcount(a[i, w] ^ b[j, w])
    return d


@njit(cache=True, nogil=True)
def _no_matches(n):
    """Per-query best train index (NO_MATCH), its descriptor distance and image gap, for n queries."""
    return np.full(n, NO_MATCH, np.int64), np.zeros(n, np.int64), np.zeros(n)


@njit(cache=True, nogil=True)
def _pack(best_j, best_d, keep):
    """(query indices, train indices, distances) of the queries marked in ``keep``."""
    q = np.nonzero(keep)[0].astype(np.int64)
    return q, best_j[q], best_d[q]


@njit(cache=True, nogil=True)
def _finish(best_j, best_d, best_gap, n_train, mutual):
    """Each query's best match; with ``mutual`` only if it is also the closest query of its train feature."""
    matched = best_j != NO_MATCH
    if not mutual:
        return _pack(best_j, best_d, matched)
    owner = np.full(n_train, NO_MATCH, np.int64)
    owner_d = np.full(n_train, np.iinfo(np.int64).max, np.int64)
    owner_gap = np.full(n_train, np.inf)
    for q in range(len(best_j)):
        j = best_j[q]
        if matched[q] and (best_d[q] < owner_d[j] or (best_d[q] == owner_d[j] and best_gap[q] < owner_gap[j])):
            owner[j], owner_d[j], owner_gap[j] = q, best_d[q], best_gap[q]
    for q in range(len(best_j)):
        matched[q] = matched[q] and owner[best_j[q]] == q
    return _pack(best_j, best_d, matched)


@njit(cache=True, nogil=True)
def _consider(d, gap, j, best, second, best_j, best_gap):
    """Update (best, second, best_j, best_gap) with candidate j at descriptor distance d and image
    distance ``gap``; equal descriptors prefer the smaller gap, then the lower index."""
    if d < best or (d == best and (gap < best_gap or (gap == best_gap and j < best_j))):
        return d, best, j, gap
    if d < second:
        return best, d, best_j, best_gap
    return best, second, best_j, best_gap


@njit(cache=True, nogil=True)
def radius_match(pred_uv, q_desc, uv, t_desc, radius, max_distance, ratio, mutual):
    """Match queries predicted at ``pred_uv`` (N, 2) to features at ``uv`` (M, 2) within ``radius`` px.

    Features are bucketed on a grid of ``radius``-sized cells, so each query scans only the cells
    its search disc touches. Returns (query indices, train indices, distances).
    """
    n_q, n_t = len(pred_uv), len(uv)
    best_j, best_d, best_gap = _no_matches(n_q)
    if n_q == 0 or n_t == 0:
        return _finish(best_j, best_d, best_gap, n_t, mutual)
    cell = max(radius, 1.0)
    u0, v0 = uv[:, 0].min(), uv[:, 1].min()
    n_cu = int((uv[:, 0].max() - u0) / cell) + 1
    n_cv = int((uv[:, 1].max() - v0) / cell) + 1
    cell_of = np.empty(n_t, np.int64)
    for j in range(n_t):
        cell_of[j] = int((uv[j, 1] - v0) / cell) * n_cu + int((uv[j, 0] - u0) / cell)
    order = np.argsort(cell_of, kind="mergesort")
    start = np.searchsorted(cell_of[order], np.arange(n_cu * n_cv + 1))
    r2 = radius * radius
    big = np.iinfo(np.int64).max
    for q in range(n_q):
        pu, pv = pred_uv[q, 0], pred_uv[q, 1]
        cu_lo = max(int(np.floor((pu - radius - u0) / cell)), 0)
        cu_hi = min(int(np.floor((pu + radius - u0) / cell)), n_cu - 1)
        cv_lo = max(int(np.floor((pv - radius - v0) / cell)), 0)
        cv_hi = min(int(np.floor((pv + radius - v0) / cell)), n_cv - 1)
        best, second, bj, bgap = big, big, NO_MATCH, np.inf
        for cv in range(cv_lo, cv_hi + 1):
            for cu in range(cu_lo, cu_hi + 1):
                c = cv * n_cu + cu
                for k in range(start[c], start[c + 1]):
                    j = order[k]
                    du, dv = uv[j, 0] - pu, uv[j, 1] - pv
                    gap = du * du + dv * dv
                    if gap > r2:
                        continue
                    best, second, bj, bgap = _consider(hamming(q_desc, q, t_desc, j), gap, j, best, second, bj, bgap)
        if bj != NO_MATCH and best <= max_distance and (ratio >= 1.0 or best < ratio * second):
            best_j[q], best_d[q], best_gap[q] = bj, best, bgap
    return _finish(best_j, best_d, best_gap, n_t, mutual)


@njit(cache=True, nogil=True)
def row_band_match(
    uv_l, oct_l, desc_l, uv_r, oct_r, desc_r, row_tol, min_disparity, max_disparity, max_octave_gap, max_distance
):
    """Stereo matches on epipolar rows: right features within ``row_tol[oct_l]`` rows of the left
    one, disparity in [min_disparity, max_disparity] and pyramid levels at most ``max_octave_gap``
    apart; closest descriptor, mutual. Returns (left indices, right indices, distances)."""
    n_l, n_r = len(uv_l), len(uv_r)
    best_j, best_d, best_gap = _no_matches(n_l)
    if n_l == 0 or n_r == 0:
        return _finish(best_j, best_d, best_gap, n_r, True)
    order = np.argsort(uv_r[:, 1], kind="mergesort")
    v_sorted = uv_r[order, 1]
    big = np.iinfo(np.int64).max
    for i in range(n_l):
        tol = row_tol[oct_l[i]]
        lo = np.searchsorted(v_sorted, uv_l[i, 1] - tol, side="left")
        hi = np.searchsorted(v_sorted, uv_l[i, 1] + tol, side="right")
        best, second, bj, bgap = big, big, NO_MATCH, np.inf
        for k in range(lo, hi):
            j = order[k]
            disparity = uv_l[i, 0] - uv_r[j, 0]
            if disparity < min_disparity or disparity > max_disparity or abs(oct_l[i] - oct_r[j]) > max_octave_gap:
                continue
            gap = abs(uv_l[i, 1] - uv_r[j, 1]) + abs(oct_l[i] - oct_r[j])
            best, second, bj, bgap = _consider(hamming(desc_l, i, desc_r, j), gap, j, best, second, bj, bgap)
        if bj != NO_MATCH and best <= max_distance:
            best_j[i], best_d[i], best_gap[i] = bj, best, bgap
    return _finish(best_j, best_d, best_gap, n_r, True)


@njit(cache=True, nogil=True)
def all_pairs_match(q_desc, t_desc, max_distance, ratio, mutual):
    """Match every query against every train descriptor (no geometric gate)."""
    n_q, n_t = len(q_desc), len(t_desc)
    best_j, best_d, best_gap = _no_matches(n_q)
    big = np.iinfo(np.int64).max
    for q in range(n_q):
        best, second, bj, bgap = big, big, NO_MATCH, 0.0
        for j in range(n_t):
            best, second, bj, bgap = _consider(hamming(q_desc, q, t_desc, j), 0.0, j, best, second, bj, bgap)
        if bj != NO_MATCH and best <= max_distance and (ratio >= 1.0 or best < ratio * second):
            best_j[q], best_d[q] = bj, best
    return _finish(best_j, best_d, best_gap, n_t, mutual)


@njit(cache=True, nogil=True)
def _nearest_row(a, i, b, lo, hi):
    """Index in ``lo .. hi-1`` of the row of ``b`` nearest to ``a[i]`` (Hamming; ties: lower index)."""
    best, best_d = lo, 1 << 30
    for j in range(lo, hi):
        d = hamming(a, i, b, j)
        if d < best_d:
            best, best_d = j, d
    return best


@njit(cache=True, nogil=True)
def nearest(a, b):
    """Index (N,) of the nearest row of ``b`` (K, 4) to each row of ``a`` (N, 4) (Hamming; ties: lower index)."""
    out = np.empty(a.shape[0], np.int64)
    for i in range(a.shape[0]):
        out[i] = _nearest_row(a, i, b, 0, b.shape[0])
    return out


@njit(cache=True, nogil=True)
def nearest_in_tree(a, top, leaves, branching):
    """Leaf word (N,) of each descriptor of ``a`` (N, 4) in a two-level tree: the nearest of the ``top`` nodes
    (T, 4), then the nearest of that node's ``branching`` leaves (``leaves`` (T * branching, 4), node t's at
    ``t * branching ...``)."""
    out = np.empty(a.shape[0], np.int64)
    for i in range(a.shape[0]):
        t = _nearest_row(a, i, top, 0, top.shape[0])
        out[i] = _nearest_row(a, i, leaves, t * branching, (t + 1) * branching)
    return out
