"""Compiled (numba) inner loops of place recognition's queries (:mod:`vtr.navigation.place`): the first pass
over the inverted file and the exact scores of the shortlisted vertices. Plain arrays in, plain arrays out;
compiled on first use and cached next to this file, as ``vtr.vo.kernels`` are."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def coarse_scores(indptr, vertex, weight, words, query_weight, n_vertices):
    """Sum over the query's ``words`` (with ``query_weight``) of each vertex's weight in the inverted file
    (``indptr`` (W+1,), ``vertex``, ``weight``): (n_vertices,) float64."""
    acc = np.zeros(n_vertices)
    for k in range(len(words)):
        w = words[k]
        qw = query_weight[k]
        for e in range(indptr[w], indptr[w + 1]):
            acc[vertex[e]] += qw * weight[e]
    return acc


@njit(cache=True, nogil=True)
def row_scores(indptr, word, weight, rows, q):
    """Dot product of CSR rows ``rows`` (``indptr``, ``word``, ``weight``) with the dense vector ``q``."""
    out = np.zeros(len(rows))
    for k in range(len(rows)):
        r = rows[k]
        s = 0.0
        for e in range(indptr[r], indptr[r + 1]):
            s += weight[e] * q[word[e]]
        out[k] = s
    return out
