"""Compiled (numba) inner loops of the hot paths: bundle adjustment, descriptor matching, stereo
refinement. Each kernel works on plain arrays; the modules that call them (``estimation``,
``features``, ``stereo``) own the interfaces, units and frames.

Kernels are compiled on first use and cached next to their source (``cache=True``), so only the
first process after an install pays the compilation.
"""
