"""Compiled (numba) inner loops of the hot paths: bundle adjustment, descriptor matching, stereo
refinement. Each kernel works on plain arrays; the modules that call them (``estimation``,
``features``, ``stereo``) own the interfaces, units and frames.

Kernels are compiled on first use and cached next to their source (``cache=True``), so only the
first process after an install pays the compilation.
"""

import numpy as np


def warm_up() -> None:
    """Run every kernel once on tiny inputs so that later calls (and processes) find them compiled."""
    from . import bundle, matching, stereo  # not at import: a caller of one kernel module loads only that one

    R, t = np.eye(3)[None], np.zeros((1, 3))
    X = np.array([[0.0, 0.0, 5.0]])
    obs = np.zeros(1, np.int64)
    z, ones = np.array([[100.0, 100.0, 90.0]]), np.ones((1, 3))
    Y, e, w, _, _ = bundle.residuals(R, t, X, obs, obs, z, ones, ones, 1.5, 500.0, 500.0, 100.0, 100.0, 50.0)
    free = np.ones(1, np.bool_)
    H, b, Hll, bl, W = bundle.normal_equations(R, Y, e, w, obs, obs, ones, 1, free, False, 500.0, 500.0, 50.0)
    start = np.array([0, 1], np.int64)
    _, _, Hinv = bundle.schur(H, b, Hll, bl, W, obs, start, obs, free, 1e-4)
    bundle.back_substitute(X, Hinv, bl, W, obs, start, obs, np.zeros(6))
    words = np.zeros((2, 4), np.uint64)
    uv = np.array([[1.0, 1.0], [5.0, 1.0]])
    octave = np.zeros(2, np.int64)
    matching.radius_match(uv, words, uv, words, 3.0, 64, 0.9, True)
    matching.radius_match(uv, words, uv, words, 3.0, 64, 1.0, False)
    matching.all_pairs_match(words, words, 64, 0.9, True)
    matching.row_band_match(uv, octave, words, uv, octave, words, np.ones(1), 0.0, 10.0, 1, 64)
    image = np.zeros((20, 40), np.uint8)
    stereo.refine_rows(image, image, np.array([20]), np.array([10]), np.array([15]), 3, 2)
