"""numba kernels: SSIM's five Gaussian blurs, its map and its mean, and the closed-form backward (row-parallel).

Planes [P, H, W] (every channel of every image is one plane), a 1-D window g [S] (S = 2R + 1, symmetric), zero
padding outside the image, exactly as :func:`pipeline.ops.image_losses.ssim_map` (the torch twin).

1. ``ssim_fwd``: the vertical pass of the five blurs (x, y, x², y², xy) for every image row in one sweep over the
   rows of x and y, then per row the horizontal pass, the SSIM value s and its three partial derivatives
   ``m1 = ∂s/∂μx``, ``m2 = ∂s/∂E[x²]``, ``m3 = ∂s/∂E[xy]`` (σ² = E[x²] − μx², σxy = E[xy] − μxμy), and the
   row's sum of s (float64).
2. ``ssim_bwd``: dL/dx = scale · (G∗m1 + 2x·G∗m2 + y·G∗m3): a 'same' blur with a symmetric window and zero padding
   is its own transpose, so the backward is three more blurs and one element-wise pass.

Every row is one thread's work and written by it alone, so the results never depend on the schedule. Loop
indices into the rows are unsigned (numba then adds no negative-index wraparound and the inner loops vectorise, as
in the rasterizer), and every constant is float32 (a literal 2 would make the arithmetic float64): a first version
with neither took 6.9 against 1.5 ms forward at 320x240 (docs/DECISIONS.md, "Numbers behind code comments").
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(inline="always")
def _hblur(src, g, out):
    """out[j] = Σ_k g[k] · src[j + k − R], zero outside the row. src, out [W]; g [2R + 1]."""
    W = src.shape[0]
    R = g.shape[0] // 2
    out[:] = 0
    for k in range(g.shape[0]):
        lo = max(0, R - k)
        hi = min(W, W + R - k)
        if hi <= lo:
            continue
        s0 = np.uint64(lo + k - R)
        o = out[lo:hi]
        gk = g[k]
        for q in range(np.uint64(hi - lo)):
            o[q] += gk * src[s0 + q]


@njit(inline="always")
def _vblur(planes, p, r, g, out):
    """out[m] = Σ_k g[k] · planes[m][p, r + k − R] for every map m (rows outside the image are zero).
    planes: a tuple of M arrays [P, H, W]; out [M, W]."""
    H, W = planes[0].shape[1], planes[0].shape[2]
    R = g.shape[0] // 2
    out[:] = 0
    for k in range(g.shape[0]):
        rr = r + k - R
        if rr < 0 or rr >= H:
            continue
        gk = g[k]
        for m in range(len(planes)):
            src, o = planes[m][p, rr], out[m]
            for j in range(np.uint64(W)):
                o[j] += gk * src[j]


@njit(parallel=True, cache=True)
def ssim_fwd(x, y, g, c1, c2, m1, m2, m3, rowsum):
    """x, y [P, H, W]; g [S]; c1, c2 the stabilisers (of x's dtype) -> m1, m2, m3 [P, H, W] (s's partial
    derivatives, step 1 of the module docstring), rowsum [P, H] float64 (the sum of s over each row)."""
    P, H, W = x.shape
    R = g.shape[0] // 2
    two = np.float32(2.0)  # a literal 2 (an int64) would promote float32 arithmetic to float64
    for pr in prange(P * H):
        p, r = pr // H, pr % H
        v = np.zeros((5, W), x.dtype)  # the vertical pass of the five blurs at this row
        v0, v1, v2, v3, v4 = v[0], v[1], v[2], v[3], v[4]
        for k in range(g.shape[0]):
            rr = r + k - R
            if rr < 0 or rr >= H:
                continue
            xr, yr, gk = x[p, rr], y[p, rr], g[k]
            for j in range(np.uint64(W)):
                xv, yv = xr[j], yr[j]
                v0[j] += gk * xv
                v1[j] += gk * yv
                v2[j] += gk * (xv * xv)
                v3[j] += gk * (yv * yv)
                v4[j] += gk * (xv * yv)
        h = np.empty((5, W), x.dtype)
        for m in range(5):
            _hblur(v[m], g, h[m])
        h0, h1, h2, h3, h4 = h[0], h[1], h[2], h[3], h[4]
        o1, o2, o3 = m1[p, r], m2[p, r], m3[p, r]
        s = np.empty(W, x.dtype)
        for j in range(np.uint64(W)):
            mx, my = h0[j], h1[j]
            sxx = h2[j] - mx * mx
            syy = h3[j] - my * my
            sxy = h4[j] - mx * my
            a1 = two * mx * my + c1
            a2 = two * sxy + c2
            b1 = mx * mx + my * my + c1
            b2 = sxx + syy + c2
            val = a1 * a2 / (b1 * b2)
            s[j] = val
            o1[j] = val * (two * my / a1 - two * my / a2 - two * mx / b1 + two * mx / b2)
            o2[j] = -val / b2
            o3[j] = two * val / a2
        total = 0.0
        for j in range(W):
            total += s[j]
        rowsum[p, r] = total


@njit(parallel=True, cache=True)
def ssim_bwd(x, y, g, m1, m2, m3, scale, dx):
    """dx [P, H, W] = scale · (G∗m1 + 2x·G∗m2 + y·G∗m3) (step 2 of the module docstring); scale = dL/d(mean s)
    divided by the number of values, in x's dtype."""
    P, H, W = x.shape
    two = np.float32(2.0)
    for pr in prange(P * H):
        p, r = pr // H, pr % H
        v = np.empty((3, W), x.dtype)
        _vblur((m1, m2, m3), p, r, g, v)
        h = np.empty((3, W), x.dtype)
        for m in range(3):
            _hblur(v[m], g, h[m])
        h0, h1, h2 = h[0], h[1], h[2]
        xr, yr, o = x[p, r], y[p, r], dx[p, r]
        for j in range(np.uint64(W)):
            o[j] = scale * (h0[j] + two * xr[j] * h1[j] + yr[j] * h2[j])
