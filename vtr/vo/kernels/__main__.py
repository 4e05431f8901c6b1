"""``python -m vtr.vo.kernels``: compile every kernel once (fills numba's on-disk cache) and say how long it took."""

from __future__ import annotations

import time

from . import warm_up

if __name__ == "__main__":
    t0 = time.perf_counter()
    warm_up()
    print(f"vtr kernels ready ({time.perf_counter() - t0:.1f} s)")
