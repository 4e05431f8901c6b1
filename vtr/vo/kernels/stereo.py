"""Kernel of the subpixel disparity refinement (``vtr.vo.stereo.refine_disparity``)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def refine_rows(left, right, ul, vl, ur, half, search):
    """Subpixel right columns by mean-removed SSD block matching along row ``vl`` around ``ur``.

    ``ul``/``vl``/``ur`` are integer pixel positions; patches are (2 half + 1)^2, shifts
    -search..search, the minimum refined by a parabola. NaN where a patch leaves the image or the
    minimum sits on the search border.
    """
    h, w = left.shape
    n = len(ul)
    out = np.full(n, np.nan)
    size = 2 * half + 1
    count = size * size
    n_shift = 2 * search + 1
    pad = half + search + 1
    lp = np.empty((size, size), np.int64)
    ssd = np.empty(n_shift)
    for i in range(n):
        u, v, r = ul[i], vl[i], ur[i]
        if u < pad or u >= w - pad or r < pad or r >= w - pad or v < half or v >= h - half:
            continue
        total = 0
        for a in range(size):
            for b in range(size):
                lp[a, b] = left[v - half + a, u - half + b]
                total += lp[a, b]
        mean_l = total // count
        for s in range(n_shift):
            c0 = r - search + s - half
            total = 0
            for a in range(size):
                for b in range(size):
                    total += right[v - half + a, c0 + b]
            mean_r = total // count
            acc = 0.0
            for a in range(size):
                for b in range(size):
                    diff = (right[v - half + a, c0 + b] - mean_r) - (lp[a, b] - mean_l)
                    acc += diff * diff
            ssd[s] = acc
        k = 0
        for s in range(1, n_shift):
            if ssd[s] < ssd[k]:
                k = s
        if k == 0 or k == n_shift - 1:
            continue
        denom = ssd[k - 1] - 2.0 * ssd[k] + ssd[k + 1]
        delta = 0.5 * (ssd[k - 1] - ssd[k + 1]) / denom if denom > 0 else 0.0
        out[i] = r + (k - search) + min(max(delta, -1.0), 1.0)
    return out
