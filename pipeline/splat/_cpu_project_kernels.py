"""numba kernels: EWA projection + SH colour, forward and hand-written backward (one Gaussian per iteration).

Same maths and conventions as ``project.py`` and ``sh.py`` (their torch code is the slow twin these are tested
against). Everything is computed in float64 and rounded to float32 at the end, as the torch reference does, so
both produce the same float32 means2d / conics / colours.

Backward (matrix-calculus form, G_X = dL/dX as a full matrix):
  conic P = Sigma2^-1:           G_Sigma2 = -P G_P P, with G_P = [[g0, g1/2], [g1/2, g2]] for conic (a, b, c)
  Sigma2 = J Sigma_c J^T + eps:  G_Sigma_c = J^T G_Sigma2 J,  G_J = 2 G_Sigma2 J Sigma_c
  Sigma_c = W Sigma W^T:         G_Sigma = W^T G_Sigma_c W
  Sigma = M M^T, M = R S:        G_M = 2 G_Sigma M,  G_R = G_M S,  g_s_j = sum_i G_M[i, j] R[i, j]
  q_n = q / |q|:                 g_q = (g_qn - (g_qn . q_n) q_n) / |q|
  colour = max(sum_k c_k Y_k(d/|d|) + 0.5, 0), d = mean - campos: g_d = (I - n n^T) g_n / |d|

Importing this module imports numba; the cpu backend imports it on first use.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pipeline.splat._constants import ALPHA_MIN, MAX_EXTENT_SIGMAS
from pipeline.splat.sh import C0, C1, C2, C3

_C20, _C21, _C22, _C23, _C24 = C2
_C30, _C31, _C32, _C33, _C34, _C35, _C36 = C3


@njit(inline="always")
def _sh_basis(deg, x, y, z, out):
    """Real SH basis (sh.py's sh_basis) at a unit direction into out[:(deg+1)^2]."""
    out[0] = C0
    if deg >= 1:
        out[1] = -C1 * y
        out[2] = C1 * z
        out[3] = -C1 * x
    if deg >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = _C20 * x * y
        out[5] = _C21 * y * z
        out[6] = _C22 * (2.0 * zz - xx - yy)
        out[7] = _C23 * x * z
        out[8] = _C24 * (xx - yy)
    if deg >= 3:
        xx, yy, zz = x * x, y * y, z * z
        out[9] = _C30 * y * (3.0 * xx - yy)
        out[10] = _C31 * x * y * z
        out[11] = _C32 * y * (4.0 * zz - xx - yy)
        out[12] = _C33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        out[13] = _C34 * x * (4.0 * zz - xx - yy)
        out[14] = _C35 * z * (xx - yy)
        out[15] = _C36 * x * (xx - 3.0 * yy)


@njit(inline="always")
def _sh_basis_grad(deg, x, y, z, w, out):
    """out[:] += sum_k w[k] dY_k/d(x, y, z) (the polynomial's gradient; only its tangential part matters)."""
    if deg >= 1:
        out[0] += -C1 * w[3]
        out[1] += -C1 * w[1]
        out[2] += C1 * w[2]
    if deg >= 2:
        out[0] += _C20 * y * w[4] + _C23 * z * w[7] - 2.0 * _C22 * x * w[6] + 2.0 * _C24 * x * w[8]
        out[1] += _C20 * x * w[4] + _C21 * z * w[5] - 2.0 * _C22 * y * w[6] - 2.0 * _C24 * y * w[8]
        out[2] += _C21 * y * w[5] + 4.0 * _C22 * z * w[6] + _C23 * x * w[7]
    if deg >= 3:
        xx, yy, zz = x * x, y * y, z * z
        out[0] += (
            6.0 * _C30 * x * y * w[9]
            + _C31 * y * z * w[10]
            - 2.0 * _C32 * x * y * w[11]
            - 6.0 * _C33 * x * z * w[12]
            + _C34 * (4.0 * zz - 3.0 * xx - yy) * w[13]
            + 2.0 * _C35 * x * z * w[14]
            + 3.0 * _C36 * (xx - yy) * w[15]
        )
        out[1] += (
            3.0 * _C30 * (xx - yy) * w[9]
            + _C31 * x * z * w[10]
            + _C32 * (4.0 * zz - xx - 3.0 * yy) * w[11]
            - 6.0 * _C33 * y * z * w[12]
            - 2.0 * _C34 * x * y * w[13]
            - 2.0 * _C35 * y * z * w[14]
            - 6.0 * _C36 * x * y * w[15]
        )
        out[2] += (
            _C31 * x * y * w[10]
            + 8.0 * _C32 * y * z * w[11]
            + _C33 * (6.0 * zz - 3.0 * xx - 3.0 * yy) * w[12]
            + 8.0 * _C34 * x * z * w[13]
            + _C35 * (xx - yy) * w[14]
        )


@njit(inline="always")
def _camera_rot(Wall, c, W):
    """Copy camera c's rotation into the 3x3 scratch W."""
    for i in range(3):
        for j in range(3):
            W[i, j] = Wall[c, i, j]


@njit(inline="always")
def _mm(A, B, out):
    """out = A @ B for 3x3 arrays."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(inline="always")
def _mm_bt(A, B, out):
    """out = A @ B^T for 3x3 arrays."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[j, 0] + A[i, 1] * B[j, 1] + A[i, 2] * B[j, 2]


@njit(inline="always")
def _mm_at(A, B, out):
    """out = A^T @ B for 3x3 arrays."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[0, i] * B[0, j] + A[1, i] * B[1, j] + A[2, i] * B[2, j]


@njit(cache=True)
def _cameras(viewmats, Ks, width, height):
    """Per-camera constants in float64: W [C, 3, 3] world->camera rotation, t [C, 3], intrinsics [C, 4]
    (fx, fy, cx, cy) and the Jacobian clamp limits lim [C, 4] (x+, x-, y+, y-: 1.3x the field of view)."""
    C = viewmats.shape[0]
    W, t = np.empty((C, 3, 3)), np.empty((C, 3))
    intr, lim = np.empty((C, 4)), np.empty((C, 4))
    for c in range(C):
        for i in range(3):
            for j in range(3):
                W[c, i, j] = viewmats[c, i, j]
            t[c, i] = viewmats[c, i, 3]
        fx, fy = float(Ks[c, 0, 0]), float(Ks[c, 1, 1])
        cx, cy = float(Ks[c, 0, 2]), float(Ks[c, 1, 2])
        intr[c, 0], intr[c, 1], intr[c, 2], intr[c, 3] = fx, fy, cx, cy
        lim[c, 0] = (width - cx) / fx + 0.3 * width / (2 * fx)
        lim[c, 1] = cx / fx + 0.3 * width / (2 * fx)
        lim[c, 2] = (height - cy) / fy + 0.3 * height / (2 * fy)
        lim[c, 3] = cy / fy + 0.3 * height / (2 * fy)
    return W, t, intr, lim


@njit(inline="always")
def _covariance(quats, scales, n, q, R, M, S):
    """Fill normalised quaternion q [4], R [3, 3], M = R S, Sigma = M M^T of Gaussian n (float64); return |q|."""
    for i in range(4):
        q[i] = quats[n, i]
    qn = max(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), 1e-12)
    for i in range(4):
        q[i] /= qn
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)
    for i in range(3):
        for j in range(3):
            M[i, j] = R[i, j] * scales[n, j]
    _mm_bt(M, M, S)
    return qn


@njit(inline="always")
def _to_camera(means, n, W, t, c, mc):
    """Camera-space mean of Gaussian n in camera c into mc [3]."""
    for i in range(3):
        mc[i] = W[c, i, 0] * means[n, 0] + W[c, i, 1] * means[n, 1] + W[c, i, 2] * means[n, 2] + t[c, i]


@njit(inline="always")
def _view_dir(means, n, W, t, c, d):
    """Unit direction camera centre (-W^T t) -> mean into d [3]; return its length."""
    for i in range(3):
        d[i] = means[n, i] + (W[c, 0, i] * t[c, 0] + W[c, 1, i] * t[c, 1] + W[c, 2, i] * t[c, 2])
    dl = max(math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]), 1e-12)
    for i in range(3):
        d[i] /= dl
    return dl


@njit(inline="always")
def _jacobian(mc, fx, fy, lim, c):
    """J entries (j00, j02, j11, j12) at camera-space mean mc, clamped tx, ty, and whether x/z, y/z hit the clamp."""
    z = mc[2]
    u, v = mc[0] / z, mc[1] / z
    cu = min(max(u, -lim[c, 1]), lim[c, 0])
    cv = min(max(v, -lim[c, 3]), lim[c, 2])
    tx, ty = z * cu, z * cv
    return fx / z, -fx * tx / (z * z), fy / z, -fy * ty / (z * z), tx, ty, cu != u, cv != v


@njit(inline="always")
def _no_gradient(n, radii, v_colors):
    """Whether Gaussian n gets no gradient: culled in every camera (its means2d, conic and depth gradients are
    ignored) and no colour gradient (the compositing gives none to culled Gaussians)."""
    for c in range(radii.shape[0]):
        if radii[c, n, 0] > 0 or radii[c, n, 1] > 0:
            return False
        if v_colors.shape[1] > 0:  # [C, 0, 3] without SH
            for ch in range(v_colors.shape[2]):
                if v_colors[c, n, ch] != 0.0:
                    return False
    return True


@njit(inline="always")
def _zero_sh(n, v_sh0, v_shN):
    """Zero Gaussian n's SH gradient rows (v_sh0 [N, 1 or 0, 3], v_shN [N, K - 1, 3])."""
    for k in range(v_sh0.shape[1]):
        for ch in range(3):
            v_sh0[n, k, ch] = 0.0
    for k in range(v_shN.shape[1]):
        for ch in range(3):
            v_shN[n, k, ch] = 0.0


_CHUNK = 256  # Gaussians per parallel work item (scratch buffers are allocated once per chunk)


@njit(parallel=True, cache=True)
def project_fwd(
    means, quats, scales, opacities, sh0, shN, sh_degree, viewmats, Ks,
    width, height, eps2d, near_plane, far_plane,
    means2d, conics, depths, radii, depth_keys, colors,
):  # fmt: skip
    """Forward: fills means2d [C, N, 2], conics [C, N, 3], depths [C, N], radii [C, N, 2] int32,
    depth_keys [C, N] float64 (inf when culled), colors [C, N, 3] (only if sh_degree >= 0) from the SH DC band
    sh0 [N, 1, 3] and the higher bands shN [N, K - 1, 3] (K >= (sh_degree + 1)^2; separate arrays, as the
    Gaussians keep them, so a step never concatenates them nor splits their gradient)."""
    C, N = depths.shape
    nb = (sh_degree + 1) ** 2
    Wall, tall, intr, lim = _cameras(viewmats, Ks, width, height)
    for chunk in prange((N + _CHUNK - 1) // _CHUNK):
        q, mc, d = np.empty(4), np.empty(3), np.empty(3)
        R, M, S, W = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        T3, Sc, basis = np.empty((3, 3)), np.empty((3, 3)), np.empty(16)
        for n in range(chunk * _CHUNK, min(N, (chunk + 1) * _CHUNK)):
            op = float(opacities[n])
            ext = min(math.sqrt(2.0 * math.log(max(op / ALPHA_MIN, 1.0))), MAX_EXTENT_SIGMAS)
            smax2 = max(float(scales[n, 0]), float(scales[n, 1]), float(scales[n, 2])) ** 2
            have_cov = False  # the covariance is computed for the first camera that may see the Gaussian
            for c in range(C):
                means2d[c, n, 0] = 0.0
                means2d[c, n, 1] = 0.0
                conics[c, n, 0] = 0.0
                conics[c, n, 1] = 0.0
                conics[c, n, 2] = 0.0
                depths[c, n] = 0.0
                radii[c, n, 0] = 0
                radii[c, n, 1] = 0
                depth_keys[c, n] = np.inf
                fx, fy, cx, cy = intr[c, 0], intr[c, 1], intr[c, 2], intr[c, 3]
                _to_camera(means, n, Wall, tall, c, mc)
                if sh_degree >= 0:
                    _view_dir(means, n, Wall, tall, c, d)
                    _sh_basis(sh_degree, d[0], d[1], d[2], basis)
                    for ch in range(3):
                        acc = 0.0
                        acc += basis[0] * sh0[n, 0, ch]
                        for k in range(1, nb):
                            acc += basis[k] * shN[n, k - 1, ch]
                        colors[c, n, ch] = max(acc + 0.5, 0.0)
                z = mc[2]
                if not (z >= near_plane and z <= far_plane) or op < ALPHA_MIN:
                    continue
                j00, j02, j11, j12, tx, ty, clx, cly = _jacobian(mc, fx, fy, lim, c)
                mx = fx * (mc[0] / z) + cx
                my = fy * (mc[1] / z) + cy
                # Cull off-screen Gaussians before their covariance (most of a survey's Gaussians are outside a
                # given view): the conic's a = r0 Sc r0^T + eps2d <= |r0|^2 max(s)^2 + eps2d with r0 = J's first
                # row (Sc = W R S^2 R^T W^T), likewise c, so these bounds are >= the radii below and a Gaussian
                # they cull is culled by the exact test too (same outputs, the zeros written above).
                rbx = ext * math.sqrt((j00 * j00 + j02 * j02) * smax2 + eps2d) * (1.0 + 1e-6) + 1.0
                rby = ext * math.sqrt((j11 * j11 + j12 * j12) * smax2 + eps2d) * (1.0 + 1e-6) + 1.0
                if mx + rbx <= 0 or mx - rbx >= width or my + rby <= 0 or my - rby >= height:
                    continue
                if not have_cov:
                    _covariance(quats, scales, n, q, R, M, S)
                    have_cov = True
                _camera_rot(Wall, c, W)
                _mm(W, S, T3)
                _mm_bt(T3, W, Sc)
                # T = J Sc (2x3), cov2d = T J^T
                t00 = j00 * Sc[0, 0] + j02 * Sc[2, 0]
                t01 = j00 * Sc[0, 1] + j02 * Sc[2, 1]
                t02 = j00 * Sc[0, 2] + j02 * Sc[2, 2]
                t11 = j11 * Sc[1, 1] + j12 * Sc[2, 1]
                t12 = j11 * Sc[1, 2] + j12 * Sc[2, 2]
                a = t00 * j00 + t02 * j02 + eps2d
                b = t01 * j11 + t02 * j12
                cc = t11 * j11 + t12 * j12 + eps2d
                det = a * cc - b * b
                if not det > 0:
                    continue
                rx = math.ceil(ext * math.sqrt(a))
                ry = math.ceil(ext * math.sqrt(cc))
                if rx <= 0 and ry <= 0:
                    continue
                if mx + rx <= 0 or mx - rx >= width or my + ry <= 0 or my - ry >= height:
                    continue
                inv = 1.0 / det
                means2d[c, n, 0] = mx
                means2d[c, n, 1] = my
                conics[c, n, 0] = cc * inv
                conics[c, n, 1] = -b * inv
                conics[c, n, 2] = a * inv
                depths[c, n] = z
                radii[c, n, 0] = rx
                radii[c, n, 1] = ry
                depth_keys[c, n] = z


@njit(parallel=True, cache=True)
def project_bwd(
    means, quats, scales, sh0, shN, sh_degree, viewmats, Ks, width, height, eps2d, radii,
    v_means2d, v_conics, v_depths, v_colors,
    v_means, v_quats, v_scales, v_sh0, v_shN,
):  # fmt: skip
    """Backward of ``project_fwd``: fills v_means [N, 3], v_quats [N, 4], v_scales [N, 3], v_sh0 [N, 1, 3] and
    v_shN [N, K - 1, 3] (zero beyond the rendered bands) from v_means2d [C, N, 2], v_conics [C, N, 3],
    v_depths [C, N], v_colors [C, N, 3] (culled entries ignored; colours count for every camera, as in the torch
    reference)."""
    C, N = v_depths.shape
    nb = (sh_degree + 1) ** 2
    Wall, tall, intr, lim = _cameras(viewmats, Ks, width, height)
    for chunk in prange((N + _CHUNK - 1) // _CHUNK):
        q, mc, d = np.empty(4), np.empty(3), np.empty(3)
        R, M, S, W = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        T3, Sc, gSc, gS = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        gM, gm, gdir = np.empty((3, 3)), np.empty(3), np.empty(3)
        basis, wk = np.empty(16), np.empty(16)
        for n in range(chunk * _CHUNK, min(N, (chunk + 1) * _CHUNK)):
            if _no_gradient(n, radii, v_colors):  # culled in every camera, no colour gradient: all zero
                for i in range(3):
                    v_means[n, i] = 0.0
                    v_scales[n, i] = 0.0
                for i in range(4):
                    v_quats[n, i] = 0.0
                _zero_sh(n, v_sh0, v_shN)
                continue
            qn = _covariance(quats, scales, n, q, R, M, S)
            gS[:] = 0.0  # dL/dSigma (world), summed over cameras
            gm[:] = 0.0  # dL/dmean
            _zero_sh(n, v_sh0, v_shN)
            for c in range(C):
                fx, fy = intr[c, 0], intr[c, 1]
                _to_camera(means, n, Wall, tall, c, mc)
                if sh_degree >= 0:
                    dl = _view_dir(means, n, Wall, tall, c, d)
                    x, y, z = d[0], d[1], d[2]
                    _sh_basis(sh_degree, x, y, z, basis)
                    wk[:] = 0.0
                    for ch in range(3):
                        acc = 0.0
                        acc += basis[0] * sh0[n, 0, ch]
                        for k in range(1, nb):
                            acc += basis[k] * shN[n, k - 1, ch]
                        g = float(v_colors[c, n, ch]) if acc + 0.5 >= 0.0 else 0.0
                        v_sh0[n, 0, ch] += basis[0] * g
                        wk[0] += sh0[n, 0, ch] * g
                        for k in range(1, nb):
                            v_shN[n, k - 1, ch] += basis[k] * g
                            wk[k] += shN[n, k - 1, ch] * g
                    gdir[:] = 0.0
                    _sh_basis_grad(sh_degree, x, y, z, wk, gdir)
                    dot = gdir[0] * x + gdir[1] * y + gdir[2] * z
                    gm[0] += (gdir[0] - dot * x) / dl
                    gm[1] += (gdir[1] - dot * y) / dl
                    gm[2] += (gdir[2] - dot * z) / dl
                if radii[c, n, 0] <= 0 and radii[c, n, 1] <= 0:
                    continue
                _camera_rot(Wall, c, W)
                _mm(W, S, T3)
                _mm_bt(T3, W, Sc)
                z = mc[2]
                j00, j02, j11, j12, tx, ty, clx, cly = _jacobian(mc, fx, fy, lim, c)
                t00 = j00 * Sc[0, 0] + j02 * Sc[2, 0]
                t01 = j00 * Sc[0, 1] + j02 * Sc[2, 1]
                t02 = j00 * Sc[0, 2] + j02 * Sc[2, 2]
                t10 = j11 * Sc[1, 0] + j12 * Sc[2, 0]
                t11 = j11 * Sc[1, 1] + j12 * Sc[2, 1]
                t12 = j11 * Sc[1, 2] + j12 * Sc[2, 2]
                a = t00 * j00 + t02 * j02 + eps2d
                b = t01 * j11 + t02 * j12
                cc = t11 * j11 + t12 * j12 + eps2d
                inv = 1.0 / (a * cc - b * b)
                p0, p1, p2 = cc * inv, -b * inv, a * inv
                g0, g1, g2 = float(v_conics[c, n, 0]), 0.5 * float(v_conics[c, n, 1]), float(v_conics[c, n, 2])
                # G_Sigma2 = -P G_P P (symmetric 2x2: ga, gb, gc)
                ga = -(p0 * (p0 * g0 + p1 * g1) + p1 * (p0 * g1 + p1 * g2))
                gb = -(p0 * (p1 * g0 + p2 * g1) + p1 * (p1 * g1 + p2 * g2))
                gc = -(p1 * (p1 * g0 + p2 * g1) + p2 * (p1 * g1 + p2 * g2))
                # G_J = 2 G_Sigma2 (J Sc); only the entries of J that vary are needed
                gj00 = 2.0 * (ga * t00 + gb * t10)
                gj02 = 2.0 * (ga * t02 + gb * t12)
                gj11 = 2.0 * (gb * t01 + gc * t11)
                gj12 = 2.0 * (gb * t02 + gc * t12)
                # G_Sc = J^T G_Sigma2 J with J = [[j00, 0, j02], [0, j11, j12]]
                u0, u1, u2 = j00 * ga, j11 * gb, j02 * ga + j12 * gb  # (J^T G2)[:, 0]
                w0, w1, w2 = j00 * gb, j11 * gc, j02 * gb + j12 * gc  # (J^T G2)[:, 1]
                gSc[0, 0], gSc[0, 1], gSc[0, 2] = u0 * j00, w0 * j11, u0 * j02 + w0 * j12
                gSc[1, 0], gSc[1, 1], gSc[1, 2] = u1 * j00, w1 * j11, u1 * j02 + w1 * j12
                gSc[2, 0], gSc[2, 1], gSc[2, 2] = u2 * j00, w2 * j11, u2 * j02 + w2 * j12
                _mm_at(W, gSc, T3)  # G_Sigma += W^T G_Sc W
                _mm(T3, W, Sc)
                for i in range(3):
                    for j in range(3):
                        gS[i, j] += Sc[i, j]
                # camera-space mean: means2d, depth, J
                vmx, vmy = float(v_means2d[c, n, 0]), float(v_means2d[c, n, 1])
                rz = 1.0 / z
                gx = fx * rz * vmx
                gy = fy * rz * vmy
                gz = -(fx * mc[0] * vmx + fy * mc[1] * vmy) * rz * rz + float(v_depths[c, n])
                gz += -fx * rz * rz * gj00 - fy * rz * rz * gj11
                if clx:  # J02 = -fx tx / z^2 with tx = z * lim: depends on z only
                    gz += fx * tx * rz * rz * rz * gj02
                else:
                    gx += -fx * rz * rz * gj02
                    gz += 2.0 * fx * tx * rz * rz * rz * gj02
                if cly:
                    gz += fy * ty * rz * rz * rz * gj12
                else:
                    gy += -fy * rz * rz * gj12
                    gz += 2.0 * fy * ty * rz * rz * rz * gj12
                for i in range(3):
                    gm[i] += W[0, i] * gx + W[1, i] * gy + W[2, i] * gz
            # Sigma = M M^T -> M -> (R, s) -> q
            _mm(gS, M, gM)
            for j in range(3):
                acc = 0.0
                for i in range(3):
                    gM[i, j] *= 2.0
                    acc += gM[i, j] * R[i, j]
                    gM[i, j] *= scales[n, j]  # now G_R
                v_scales[n, j] = acc
            w, x, y, z = q[0], q[1], q[2], q[3]
            gR = gM
            gw = 2.0 * (-z * gR[0, 1] + y * gR[0, 2] + z * gR[1, 0] - x * gR[1, 2] - y * gR[2, 0] + x * gR[2, 1])
            gx_ = 2.0 * (
                y * gR[0, 1] + z * gR[0, 2] + y * gR[1, 0] - 2.0 * x * gR[1, 1]
                - w * gR[1, 2] + z * gR[2, 0] + w * gR[2, 1] - 2.0 * x * gR[2, 2]
            )  # fmt: skip
            gy_ = 2.0 * (
                -2.0 * y * gR[0, 0] + x * gR[0, 1] + w * gR[0, 2] + x * gR[1, 0]
                + z * gR[1, 2] - w * gR[2, 0] + z * gR[2, 1] - 2.0 * y * gR[2, 2]
            )  # fmt: skip
            gz_ = 2.0 * (
                -2.0 * z * gR[0, 0] - w * gR[0, 1] + x * gR[0, 2] + w * gR[1, 0]
                - 2.0 * z * gR[1, 1] + y * gR[1, 2] + x * gR[2, 0] + y * gR[2, 1]
            )  # fmt: skip
            dot = gw * w + gx_ * x + gy_ * y + gz_ * z
            v_quats[n, 0] = (gw - dot * w) / qn
            v_quats[n, 1] = (gx_ - dot * x) / qn
            v_quats[n, 2] = (gy_ - dot * y) / qn
            v_quats[n, 3] = (gz_ - dot * z) / qn
            for i in range(3):
                v_means[n, i] = gm[i]
