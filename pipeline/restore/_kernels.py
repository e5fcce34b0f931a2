"""numba kernels of the restorer (the hot ops). Each has a slow numpy twin next to its caller; tests compare.

Imported lazily by the modules that use them; kernels compile on first call or load from numba's on-disk cache
(``cache=True``, keyed on this file). Parallel loops run on numba's OpenMP/workqueue pool, never TBB
(``pipeline.splat._cpu_backend.pin_threading_layer``).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from pipeline.splat._cpu_backend import pin_threading_layer

pin_threading_layer()


@njit(parallel=True, cache=True)
def interp_grid_rows(gx, gy, row_cell, row_t, col_cell, col_t):  # pragma: no cover - numba
    """Bilinear interpolation of two grid maps gx, gy [Kr, Kc] float64 at rows (cell, t) [n] and columns
    (cell, t) [W]. Returns two float32 [n, W]."""
    n, W = row_cell.shape[0], col_cell.shape[0]
    ox = np.empty((n, W), np.float32)
    oy = np.empty((n, W), np.float32)
    for r in prange(n):
        i, t = row_cell[r], row_t[r]
        for c in range(W):
            j, s = col_cell[c], col_t[c]
            w00, w01, w10, w11 = (1 - t) * (1 - s), (1 - t) * s, t * (1 - s), t * s
            ox[r, c] = w00 * gx[i, j] + w01 * gx[i, j + 1] + w10 * gx[i + 1, j] + w11 * gx[i + 1, j + 1]
            oy[r, c] = w00 * gy[i, j] + w01 * gy[i, j + 1] + w10 * gy[i + 1, j] + w11 * gy[i + 1, j + 1]
    return ox, oy
