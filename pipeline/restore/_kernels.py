"""numba kernels of the restorer (the hot ops). Each has a slow numpy twin next to its caller; tests compare.

Imported at the top of the modules that always run them (``lens``, ``sample``, ``frame``) and lazily by ``dewater``
and ``guided``, whose numpy twins and constants are read without numba (the report, ``medium``,
``consistency_truth``). Kernels compile on first call or load from numba's on-disk cache (``cache=True``, keyed
on this file). Parallel loops run on numba's OpenMP/workqueue pool, never TBB
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


@njit(parallel=True, cache=True)
def sample_bilinear(maps, xn, yn, fx, fy, cx, cy):  # pragma: no cover - numba
    """Sample maps [h, w, C] float32 at the render-camera positions of rays xn, yn [n, W] (u = fx·xn + cx,
    pixel-centre convention, edge-clamped). Returns (out [n, W, C] float32, inside [n, W] bool: 0 ≤ u ≤ w and
    0 ≤ v ≤ h)."""
    h, w, C = maps.shape
    n, W = xn.shape
    out = np.empty((n, W, C), np.float32)
    inside = np.empty((n, W), np.bool_)
    for i in prange(n):
        for j in range(W):
            u = fx * np.float64(xn[i, j]) + cx
            v = fy * np.float64(yn[i, j]) + cy
            inside[i, j] = (u >= 0.0) and (u <= w) and (v >= 0.0) and (v <= h)
            x = min(max(u - 0.5, 0.0), w - 1.0)
            y = min(max(v - 0.5, 0.0), h - 1.0)
            x0 = min(int(x), w - 2) if w > 1 else 0
            y0 = min(int(y), h - 2) if h > 1 else 0
            x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
            s, t = x - x0, y - y0
            for c in range(C):
                top = maps[y0, x0, c] * (1 - s) + maps[y0, x1, c] * s
                bot = maps[y1, x0, c] * (1 - s) + maps[y1, x1, c] * s
                out[i, j, c] = top * (1 - t) + bot * t
    return out, inside


@njit(parallel=True, cache=True)
def box_mean(x, r):  # pragma: no cover - numba
    """Mean over the (2r+1)² window clipped to the image, per channel: x [C, H, W] float32 → [C, H, W] float32.
    Separable running sums with float64 accumulators; O(1) per pixel whatever r."""
    C, H, W = x.shape
    tmp = np.empty((C, H, W), np.float32)
    out = np.empty((C, H, W), np.float32)
    for ci in prange(C * H):
        c, i = ci // H, ci % H
        s = 0.0
        for k in range(min(r, W - 1) + 1):
            s += x[c, i, k]
        for j in range(W):
            tmp[c, i, j] = s / (min(j + r, W - 1) - max(j - r, 0) + 1)
            if j + r + 1 < W:
                s += x[c, i, j + r + 1]
            if j - r >= 0:
                s -= x[c, i, j - r]
    BLK = 256
    nb = (W + BLK - 1) // BLK
    for cb in prange(C * nb):
        c, b = cb // nb, cb % nb
        j0, j1 = b * BLK, min(W, b * BLK + BLK)
        acc = np.zeros(j1 - j0, np.float64)
        for k in range(min(r, H - 1) + 1):
            for j in range(j0, j1):
                acc[j - j0] += tmp[c, k, j]
        for i in range(H):
            inv = 1.0 / (min(i + r, H - 1) - max(i - r, 0) + 1)
            for j in range(j0, j1):
                out[c, i, j] = acc[j - j0] * inv
            if i + r + 1 < H:
                for j in range(j0, j1):
                    acc[j - j0] += tmp[c, i + r + 1, j]
            if i - r >= 0:
                for j in range(j0, j1):
                    acc[j - j0] -= tmp[c, i - r, j]
    return out


@njit(parallel=True, cache=True)
def guided_stats(I, p):  # pragma: no cover - numba
    """Stack [I, p, I·p, I·I] of guide I and source p [H, W] float32 → [4, H, W] float32."""
    H, W = I.shape
    out = np.empty((4, H, W), np.float32)
    for i in prange(H):
        for j in range(W):
            a, b = I[i, j], p[i, j]
            out[0, i, j] = a
            out[1, i, j] = b
            out[2, i, j] = a * b
            out[3, i, j] = a * a
    return out


@njit(parallel=True, cache=True)
def guided_coeffs(m, eps):  # pragma: no cover - numba
    """He's per-window linear coefficients from the box means m [4, H, W] (of I, p, I·p, I·I): a = cov(I, p) /
    (var(I) + eps), b = mean(p) − a·mean(I). Returns [2, H, W] float32."""
    _, H, W = m.shape
    out = np.empty((2, H, W), np.float32)
    for i in prange(H):
        for j in range(W):
            mi, mp = np.float64(m[0, i, j]), np.float64(m[1, i, j])
            var = max(m[3, i, j] - mi * mi, 0.0)
            a = (m[2, i, j] - mi * mp) / (var + eps)
            out[0, i, j] = a
            out[1, i, j] = mp - a * mi
    return out


@njit(parallel=True, cache=True)
def guided_apply(mab, I):  # pragma: no cover - numba
    """q = mean(a)·I + mean(b): mab [2, H, W], I [H, W] → [H, W] float32."""
    _, H, W = mab.shape
    out = np.empty((H, W), np.float32)
    for i in prange(H):
        for j in range(W):
            out[i, j] = mab[0, i, j] * I[i, j] + mab[1, i, j]
    return out


@njit(parallel=True, cache=True)
def luminance(img, scale):  # pragma: no cover - numba
    """Rec. 709 luma of img [H, W, 3] (any numeric dtype) times ``scale`` (e.g. 1/255) → [H, W] float32."""
    H, W, _ = img.shape
    out = np.empty((H, W), np.float32)
    for i in prange(H):
        for j in range(W):
            out[i, j] = scale * (0.2126 * img[i, j, 0] + 0.7152 * img[i, j, 1] + 0.0722 * img[i, j, 2])
    return out


@njit(inline="always")
def _srgb_to_linear(x):  # pragma: no cover - numba
    return x / 12.92 if x <= 0.04045 else ((x + 0.055) / 1.055) ** 2.4


@njit(inline="always")
def _linear_to_srgb(x):  # pragma: no cover - numba
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1.0 / 2.4) - 0.055


@njit(inline="always")
def _optical_depths(kA, kB, rr):  # pragma: no cover - numba
    """(k_A·r, k_B·r) of one channel, each coefficient clamped to [0, 1e30] and each depth to 80 (e^-80 ≈ 0)."""
    kA = min(max(np.float64(kA), 0.0), 1e30)
    kB = min(max(np.float64(kB), 0.0), 1e30)
    return min(kA * rr, 80.0), min(kB * rr, 80.0)


@njit(parallel=True, cache=True)
def dewater(img, scale, r, surface, k_A, k_B, B_inf, max_gain, linear, J, out_max, prior, has_prior, lam2,
            sigma, noise2, cov, dcov, misfit, tau):  # pragma: no cover - numba
    """The physics per pixel (twin: ``pipeline.restore.dewater.dewater_reference``).

    img [n, W, 3] any dtype (× ``scale`` → [0, 1]); r [n, W] float32 range; surface [n, W] bool; k_A, k_B
    [n, W, 3] or [1, 1, 3] float32; B_inf [3]; max_gain > 1; prior [n, W, 3] float32 (the model's J, in the
    physics' space) read when ``has_prior``, with weights lam2 [3] (each ≥ (0.5 / max_gain)²) and cov [3, 3]
    the prior's covariance across channels (the photo's effective noise is lam2·diag(cov)): J = P + G·e,
    e = I − B − A·P, G from :func:`_gain_matrix`; sigma [3, 3] the water's
    uncertainty (rows: log k_A, log k_B, logit B∞; columns: channels), noise2 [3] the photo's noise variance,
    dcov [3, 3] what the model lacks (a covariance of J), misfit [n, W, 3] or [1, 1, 3] float32 the mean of
    e² around each pixel (:func:`misfit_terms`, tent-filtered, :func:`misfit_upsample`; read when
    ``has_prior``: the photo's local disagreement with the model, max(misfit − noise2, 0) / A_eff² of J), tau
    the expected error at confidence 1/2 (``pipeline.restore.dewater.expected_error``). Writes J [n, W, 3]
    (uint8 or uint16) quantised to 0..out_max; returns (confidence [n, W] float32, clipped count)."""
    n, W, _ = img.shape
    conf = np.zeros((n, W), np.float32)
    clipped = np.zeros(n, np.int64)
    a_min = 1.0 / max_gain
    tau2 = tau * tau
    full_A = 1 if k_A.shape[0] > 1 else 0  # index multipliers: 0 reads the [1, 1, 3] constant
    full_B = 1 if k_B.shape[0] > 1 else 0
    full_M = 1 if misfit.shape[0] > 1 else 0
    for i in prange(n):
        t = np.empty((9, 3))  # per channel: A, B, x, oA, oB, e^(-oB), e = x - B - A·P, the value, 1 - e^(-oB)
        G = np.empty((3, 3))
        M = np.empty((3, 3))
        kv = np.empty(3)  # a row of I − G·diag(A)
        for j in range(W):
            if not surface[i, j]:
                for c in range(3):
                    J[i, j, c] = int(min(max(scale * img[i, j, c], 0.0), 1.0) * out_max + 0.5)
                continue
            rr = np.float64(r[i, j])
            if not rr >= 0.0:  # also NaN
                rr = 0.0
            ia, ja, ib, jb = i * full_A, j * full_A, i * full_B, j * full_B
            for c in range(3):
                t[3, c], t[4, c] = _optical_depths(k_A[ia, ja, c], k_B[ib, jb, c], rr)
                t[0, c] = np.exp(-t[3, c])
                t[8, c] = -np.expm1(-t[4, c])  # 1 − e^(-oB) once: the veil and its error both need it
                t[5, c] = 1.0 - t[8, c]  # and e^(-oB) from it (an exp fewer; equal to within 1 ulp)
                t[1, c] = B_inf[c] * t[8, c]
                x = scale * np.float64(img[i, j, c])
                t[2, c] = _srgb_to_linear(x) if linear else x
            if has_prior:
                for c in range(3):
                    t[6, c] = t[2, c] - t[1, c] - t[0, c] * np.float64(prior[i, j, c])
                    for k in range(3):
                        M[c, k] = t[0, c] * cov[c, k] * t[0, k]
                    M[c, c] += lam2[c] * cov[c, c]
                _gain_matrix(M, cov, t, lam2, G, max_gain)
                for c in range(3):
                    t[7, c] = np.float64(prior[i, j, c]) + G[c, 0] * t[6, 0] + G[c, 1] * t[6, 1] + G[c, 2] * t[6, 2]
            else:
                for c in range(3):
                    t[7, c] = (t[2, c] - t[1, c]) / max(t[0, c], a_min)
            err2 = 0.0
            clip = False
            for c in range(3):
                A, oA, oB, v = t[0, c], t[3, c], t[4, c], t[7, c]
                Ae = max(A, a_min)
                if has_prior:
                    # the photo's noise through the gains, and what the model lacks through I − G·A
                    noise = G[c, 0] ** 2 * noise2[0] + G[c, 1] ** 2 * noise2[1] + G[c, 2] ** 2 * noise2[2]
                    for a in range(3):
                        kv[a] = (1.0 if a == c else 0.0) - G[c, a] * t[0, a]
                    model2 = 0.0
                    for a in range(3):
                        for b in range(3):
                            model2 += kv[a] * dcov[a, b] * kv[b]
                    model2 = max(model2, 0.0)
                    # where the photo disagrees with the model beyond its noise, the model's depth, water or J is
                    # wrong there, and so is what the restoration took from it (a NaN misfit counts as 0; ±inf
                    # needs no care: the error is capped at 1 below)
                    mf = np.float64(misfit[i * full_M, j * full_M, c])
                    if mf != mf:
                        mf = 0.0
                    model2 += max(mf - noise2[c], 0.0) / (Ae * Ae)
                else:
                    noise = noise2[c] / (Ae * Ae)
                    model2 = 0.0
                if v < 0.0 or v > 1.0:
                    clip = True
                    v = min(max(v, 0.0), 1.0)
                # expected error of v (the twin: pipeline.restore.dewater.expected_error)
                dA = v * oA * sigma[0, c]
                dB = ((B_inf[c] * oB * t[5, c] * sigma[1, c]) ** 2
                      + (B_inf[c] * (1.0 - B_inf[c]) * t[8, c] * sigma[2, c]) ** 2)
                e = np.sqrt(dA * dA + dB / (Ae * Ae) + noise + model2)
                if linear:
                    s0 = _linear_to_srgb(v)
                    e = max(_linear_to_srgb(min(v + e, 1.0)) - s0, s0 - _linear_to_srgb(max(v - e, 0.0)))
                    v = s0
                else:
                    e = min(e, 1.0)
                err2 += e * e
                J[i, j, c] = int(v * out_max + 0.5)
            conf[i, j] = tau2 / (tau2 + err2 / 3.0)
            if clip:
                clipped[i] += 1
    return conf, clipped.sum()


@njit(parallel=True, cache=True)
def misfit_terms(img, scale, r, surface, k_A, k_B, B_inf, linear, prior, first, q):  # pragma: no cover - numba
    """The photo's residual against the model, e = I − B − A·P per channel (physics space, as :func:`dewater`;
    twin: ``pipeline.restore.dewater.local_misfit_reference``), on every q-th pixel: rows first, first + q, …
    and columns 0, q, …: [4, nc, wc] float32 of e_c² on surface pixels (0 elsewhere) and the surface
    indicator, ready for :func:`box_mean`."""
    n, W, _ = img.shape
    nc, wc = (n - first + q - 1) // q, (W + q - 1) // q
    out = np.zeros((4, nc, wc), np.float32)
    full_A = 1 if k_A.shape[0] > 1 else 0
    full_B = 1 if k_B.shape[0] > 1 else 0
    for ci in prange(nc):
        i = first + ci * q
        for cj in range(wc):
            j = cj * q
            if not surface[i, j]:
                continue
            rr = np.float64(r[i, j])
            if not rr >= 0.0:
                rr = 0.0
            ia, ja, ib, jb = i * full_A, j * full_A, i * full_B, j * full_B
            for c in range(3):
                oA, oB = _optical_depths(k_A[ia, ja, c], k_B[ib, jb, c], rr)
                x = scale * np.float64(img[i, j, c])
                x = _srgb_to_linear(x) if linear else x
                e = x - B_inf[c] * -np.expm1(-oB) - np.exp(-oA) * np.float64(prior[i, j, c])
                out[c, ci, cj] = e * e
            out[3, ci, cj] = 1.0
    return out


@njit(parallel=True, cache=True)
def misfit_upsample(m, first, q, i0, n, W):  # pragma: no cover - numba
    """The window means m [4, nc, wc] (:func:`misfit_terms`' grid, box-filtered) as ratios m[:3] / m[3],
    interpolated bilinearly (edge-clamped) to rows i0 … i0 + n − 1 (of the rows the grid was taken from: coarse
    row k sits at row first + k·q) and every column: [n, W, 3] float32."""
    _, nc, wc = m.shape
    out = np.zeros((n, W, 3), np.float32)
    for ii in prange(n):
        y = min(max((i0 + ii - first) / q, 0.0), nc - 1.0)
        y0 = min(int(y), max(nc - 2, 0))
        y1 = min(y0 + 1, nc - 1)
        t = y - y0
        for j in range(W):
            x = min(j / q, wc - 1.0)
            x0 = min(int(x), max(wc - 2, 0))
            x1 = min(x0 + 1, wc - 1)
            u = x - x0
            w00, w01, w10, w11 = (1 - t) * (1 - u), (1 - t) * u, t * (1 - u), t * u
            den = w00 * m[3, y0, x0] + w01 * m[3, y0, x1] + w10 * m[3, y1, x0] + w11 * m[3, y1, x1]
            if den <= 1e-12:
                continue
            for c in range(3):
                out[ii, j, c] = (w00 * m[c, y0, x0] + w01 * m[c, y0, x1] + w10 * m[c, y1, x0]
                                 + w11 * m[c, y1, x1]) / den
    return out


@njit(inline="always")
def _gain_matrix(M, cov, t, lam2, G, max_gain):  # pragma: no cover - numba
    """The gains of J = P + G·e (twin: ``pipeline.restore.dewater.gain_matrix``): the joint posterior's
    cov·diag(A)·M⁻¹ (M symmetric positive definite, inverted by cofactors; A = t[0]), each row scaled so that
    Σ_k |G_ck| ≤ max_gain, then taking only the model's share m_c = λ_c²/(A_c² + λ_c²) of channel c: the photo's
    share keeps the per-channel gain A_c/(A_c² + λ_c²). Written into G [3, 3]."""
    a, b, c, d, e, f = M[0, 0], M[0, 1], M[0, 2], M[1, 1], M[1, 2], M[2, 2]
    i00, i01, i02 = d * f - e * e, c * e - b * f, b * e - c * d
    i11, i12, i22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * i00 + b * i01 + c * i02
    inv = 1.0 / det
    for r in range(3):
        w0, w1, w2 = cov[r, 0] * t[0, 0], cov[r, 1] * t[0, 1], cov[r, 2] * t[0, 2]
        G[r, 0] = (w0 * i00 + w1 * i01 + w2 * i02) * inv
        G[r, 1] = (w0 * i01 + w1 * i11 + w2 * i12) * inv
        G[r, 2] = (w0 * i02 + w1 * i12 + w2 * i22) * inv
        total = abs(G[r, 0]) + abs(G[r, 1]) + abs(G[r, 2])
        k = max_gain / total if total > max_gain else 1.0
        A, l2 = t[0, r], lam2[r]
        m = l2 / (A * A + l2)
        G[r, 0] *= k * m
        G[r, 1] *= k * m
        G[r, 2] *= k * m
        G[r, r] += (1.0 - m) * A / (A * A + l2)


@njit(parallel=True, cache=True)
def block_mean(x, s):  # pragma: no cover - numba
    """Mean of each s×s block of x [H, W] (partial blocks at the right/bottom: mean of what is there) →
    [ceil(H/s), ceil(W/s)] float32."""
    H, W = x.shape
    h, w = (H + s - 1) // s, (W + s - 1) // s
    out = np.empty((h, w), np.float32)
    for bi in prange(h):
        i0, i1 = bi * s, min(H, bi * s + s)
        for bj in range(w):
            j0, j1 = bj * s, min(W, bj * s + s)
            acc = 0.0
            for i in range(i0, i1):
                for j in range(j0, j1):
                    acc += x[i, j]
            out[bi, bj] = acc / ((i1 - i0) * (j1 - j0))
    return out


@njit(parallel=True, cache=True)
def upsample_apply(mab, I, s, off):  # pragma: no cover - numba
    """Fast guided filter's last step: q = a·I + b + off with a, b = mab [2, h, w] (one value per s×s block,
    sitting at the block centre) interpolated bilinearly (edge-clamped) to every pixel of I [H, W]."""
    _, h, w = mab.shape
    H, W = I.shape
    out = np.empty((H, W), np.float32)
    for i in prange(H):
        y = min(max((i + 0.5) / s - 0.5, 0.0), h - 1.0)
        y0 = min(int(y), max(h - 2, 0))
        y1 = min(y0 + 1, h - 1)
        t = y - y0
        for j in range(W):
            x = min(max((j + 0.5) / s - 0.5, 0.0), w - 1.0)
            x0 = min(int(x), max(w - 2, 0))
            x1 = min(x0 + 1, w - 1)
            u = x - x0
            a = (mab[0, y0, x0] * (1 - u) + mab[0, y0, x1] * u) * (1 - t) + \
                (mab[0, y1, x0] * (1 - u) + mab[0, y1, x1] * u) * t
            b = (mab[1, y0, x0] * (1 - u) + mab[1, y0, x1] * u) * (1 - t) + \
                (mab[1, y1, x0] * (1 - u) + mab[1, y1, x1] * u) * t
            out[i, j] = a * I[i, j] + b + off
    return out


@njit(parallel=True, cache=True)
def calibration_sums(img, scale, r, surface, k_A, k_B, B_inf, linear, prior, st):  # pragma: no cover - numba
    """The sums :meth:`pipeline.restore.frame.FrameRestorer.calibrate` measures the prior's weight from, over
    every ``st``-th row of a band (twin: ``pipeline.restore.frame.calibration_sums_reference``): the residual
    e = x − (P·A + B) of surface pixels, x = ``scale``·img (sRGB decoded after clipping to [0, 1] when
    ``linear``). img [n, W, 3] any dtype, r [n, W] float32, surface [n, W] bool, k_A, k_B [n, W, 3] or [1, 1, 3]
    float32, B_inf [3], prior [n, W, 3] float32. Returns (Σ e_c² [3], Σ e_c,x·e_k,x+1 over horizontal surface pairs
    [3, 3], Σ A_c·A_k [3, 3], surface count, pair count), float64, summed per row then over rows in order (the
    same bits on any thread count)."""
    n, W, _ = img.shape
    rows = (n + st - 1) // st
    acc = np.zeros((rows, 23))  # per sampled row: sq[3], lag[9], aa[9], n_sq, n_lag
    full_A = 1 if k_A.shape[0] > 1 else 0
    full_B = 1 if k_B.shape[0] > 1 else 0
    for ri in prange(rows):
        i = ri * st
        e = np.empty(3)
        A = np.empty(3)
        prev = np.empty(3)
        have_prev = False
        for j in range(W):
            if not surface[i, j]:
                have_prev = False
                continue
            rr = np.float64(r[i, j])
            for c in range(3):
                oA = min(max(np.float64(k_A[i * full_A, j * full_A, c]) * rr, 0.0), 80.0)
                oB = min(max(np.float64(k_B[i * full_B, j * full_B, c]) * rr, 0.0), 80.0)
                A[c] = np.exp(-oA)
                x = np.float64(img[i, j, c]) * scale
                if linear:
                    x = _srgb_to_linear(min(max(x, 0.0), 1.0))
                e[c] = x - (np.float64(prior[i, j, c]) * A[c] + B_inf[c] * -np.expm1(-oB))
            for c in range(3):
                acc[ri, c] += e[c] * e[c]
                for k in range(3):
                    acc[ri, 12 + 3 * c + k] += A[c] * A[k]
                    if have_prev:
                        acc[ri, 3 + 3 * c + k] += prev[c] * e[k]
            acc[ri, 21] += 1.0
            if have_prev:
                acc[ri, 22] += 1.0
            for c in range(3):
                prev[c] = e[c]
            have_prev = True
    total = np.zeros(23)
    for ri in range(rows):
        for q in range(23):
            total[q] += acc[ri, q]
    return (total[:3].copy(), total[3:12].copy().reshape(3, 3), total[12:21].copy().reshape(3, 3), int(total[21]),
            int(total[22]))


@njit(parallel=True, cache=True)
def surface_range(z, xn, yn, inside, vals):  # pragma: no cover - numba
    """One pass over a band's rows (twin: ``pipeline.restore.frame.surface_range_reference``): z [n, W] float32 the
    filtered depth, xn, yn [n, W] float32 the rays, inside [n, W] bool, vals [n, W, C ≥ 3] float32 the sampled maps
    (alpha in channel 1, the reach weight in 2). Returns (range r = z·√(1 + xn² + yn²) [n, W] float32 (float32
    arithmetic, as numpy's), surface [n, W] bool = inside & alpha ≥ 0.5 & z > 0, near [n, W] float32 = the reach
    weight off the surface where z > 0, else 0)."""
    n, W = z.shape
    r = np.empty((n, W), np.float32)
    surface = np.empty((n, W), np.bool_)
    near = np.empty((n, W), np.float32)
    one = np.float32(1.0)
    for i in prange(n):
        for j in range(W):
            zz, x, y = z[i, j], xn[i, j], yn[i, j]
            s = inside[i, j] and vals[i, j, 1] >= 0.5 and zz > 0
            surface[i, j] = s
            r[i, j] = zz * np.sqrt(one + x * x + y * y)
            near[i, j] = np.float32(0.0) if (s or zz <= 0) else vals[i, j, 2]
    return r, surface, near
