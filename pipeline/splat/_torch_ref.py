"""The ``torch`` backend: slow, obvious, differentiable by autograd. Every fast path is tested against it.

Compositing ("pixel pairs"): each visible Gaussian's opacity-aware box is expanded into (pixel, Gaussian) pairs;
pairs whose alpha < 1/255 are dropped; a stable sort by pixel of pairs generated in depth order gives every pixel
its Gaussians front to back; transmittance is a segmented cumulative sum of log(1 - alpha) in float64; colours are
accumulated with ``index_add``. No Python loop over pixels or Gaussians.

The 3DGS rules (``_constants``): alpha = min(0.99, o exp(-sigma)); skip alpha < 1/255; a pixel stops at the first
Gaussian that would take its transmittance below 1e-4 (that Gaussian is not composited).

Two choices keep this reference and the compiled kernel in exact agreement on the discrete decisions:
- alpha >= 1/255 is tested as ``sigma <= log(255 o)`` (the same inequality), with sigma evaluated in float32 with
  the same operation order as the kernel and the threshold rounded from float64: identical inputs give
  identical decisions, so no pixel flips a Gaussian in or out between backends.
- alpha is formed in float32 (0.99 clamps to float32(0.99) in both); the running log-transmittance is float64.

``composite_loop`` is the same compositing written as the obvious loop over Gaussians (float32 transmittance, as
the kernel keeps it): the twin of the cpu kernels in their per-kernel tests (tests/splat/test_cpu_kernels.py).
"""

from __future__ import annotations

import torch
from torch import Tensor

from pipeline.splat._constants import ALPHA_MAX, T_MIN
from pipeline.splat.project import project_gaussians
from pipeline.splat.sh import sh_to_rgb

TILE_SIZE = 1  # reported in info["tile_size"]; the reference works per pixel


def alpha_thresholds(opacities: Tensor) -> Tensor:
    """log(255 o) rounded from float64: [N] -> [N] float32; alpha >= 1/255 iff sigma <= this."""
    return torch.log(255.0 * opacities.detach().to(torch.float64)).to(torch.float32)


def pair_sigma(dx: Tensor, dy: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Gaussian exponent at pixel offsets (mean - pixel); the kernel evaluates exactly this expression."""
    return torch.clamp_min(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy, 0.0)


def _pixel_pairs(
    packed: Tensor,  # [C * N, 5] means2d (2), conics (3) of every (camera, Gaussian) item
    thresholds: Tensor,  # [N] float32
    radii: Tensor,  # [C, N, 2] int32
    depth_keys: Tensor,  # [C, N] float64
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """(pixel, Gaussian) pairs with alpha >= 1/255, sorted by pixel then depth (no grad).

    Returns item ids [P] (c * N + n) and global pixel ids [P] (c * H * W + y * W + x).
    """
    C, N = depth_keys.shape
    dev = packed.device
    with torch.no_grad():
        items = torch.nonzero((radii > 0).any(-1).reshape(-1)).squeeze(1)  # [M]
        # depth order within each camera: stable sort by depth, then stable by camera
        items = items[torch.sort(depth_keys.reshape(-1)[items], stable=True).indices]
        items = items[torch.sort(items // N, stable=True).indices]
        cam = items // N
        m = packed[items, :2].to(torch.float64)  # [M, 2]
        r = radii.reshape(-1, 2)[items].to(torch.float64)  # [M, 2]
        # pixel (j, i) is sampled at (j + 0.5, i + 0.5); keep centres inside [m - r, m + r]
        x0 = torch.ceil(m[:, 0] - r[:, 0] - 0.5).clamp_min(0).long()
        x1 = torch.floor(m[:, 0] + r[:, 0] - 0.5).clamp_max(width - 1).long()
        y0 = torch.ceil(m[:, 1] - r[:, 1] - 0.5).clamp_min(0).long()
        y1 = torch.floor(m[:, 1] + r[:, 1] - 0.5).clamp_max(height - 1).long()
        bw = (x1 - x0 + 1).clamp_min(1)
        counts = (x1 - x0 + 1).clamp_min(0) * (y1 - y0 + 1).clamp_min(0)  # [M]
        src = torch.repeat_interleave(torch.arange(len(items), device=dev), counts)  # [P0] index into items
        local = torch.arange(len(src), device=dev) - (torch.cumsum(counts, 0) - counts).index_select(0, src)
        bw_p = bw.index_select(0, src)
        py = y0.index_select(0, src) + local // bw_p
        px = x0.index_select(0, src) + (local - (py - y0.index_select(0, src)) * bw_p)
        pair_items = items.index_select(0, src)
        pix = cam.index_select(0, src) * (height * width) + py * width + px
        # alpha >= 1/255  <=>  sigma <= log(255 o)
        g = packed.index_select(0, pair_items)  # [P0, 5]
        dx = g[:, 0] - (px.to(g.dtype) + 0.5)
        dy = g[:, 1] - (py.to(g.dtype) + 0.5)
        sigma = pair_sigma(dx, dy, g[:, 2], g[:, 3], g[:, 4])
        keep = torch.nonzero(sigma <= thresholds.index_select(0, pair_items % N)).squeeze(1)
        pair_items, pix = pair_items.index_select(0, keep), pix.index_select(0, keep)
        order = torch.sort(pix, stable=True).indices  # pairs were generated in depth order
        return pair_items.index_select(0, order), pix.index_select(0, order)


def composite(
    means2d: Tensor,  # [C, N, 2]
    conics: Tensor,  # [C, N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [C, N, F]
    radii: Tensor,  # [C, N, 2] int32
    depth_keys: Tensor,  # [C, N] float64
    width: int,
    height: int,
    backgrounds: Tensor | None = None,  # [C, F]
    absgrad: bool = False,
) -> tuple[Tensor, Tensor]:
    """Front-to-back alpha compositing (paper eq. 2): -> features [C, H, W, F], alphas [C, H, W, 1].

    With ``absgrad``, backward also sets ``means2d.absgrad`` [C, N, 2]: the sum over pixels of |dL/dmeans2d| per
    pixel (gsplat's AbsGS statistic). Each gathered means2d row belongs to one (pixel, Gaussian) pair, so its
    gradient is exactly that pixel's contribution.
    """
    C, N, F = features.shape
    HW = height * width
    thresholds = alpha_thresholds(opacities)
    geo = torch.cat([means2d, conics], dim=-1).reshape(C * N, 5)
    items, pix = _pixel_pairs(geo.detach(), thresholds, radii, depth_keys, width, height)  # [P], [P]
    px = (pix % width).to(means2d.dtype) + 0.5
    py = ((pix // width) % height).to(means2d.dtype) + 0.5
    g = geo.index_select(0, items)  # [P, 5]: one gather of everything a pair needs
    if absgrad and g.requires_grad:
        g.register_hook(_absgrad_hook(means2d, items))
    sigma = pair_sigma(g[:, 0] - px, g[:, 1] - py, g[:, 2], g[:, 3], g[:, 4])
    alpha = torch.clamp(opacities.index_select(0, items % N) * torch.exp(-sigma), max=ALPHA_MAX)  # [P]
    log_1ma = torch.log1p(-alpha.to(torch.float64))  # [P]
    # segmented inclusive cumsum: subtract the running sum just before each pixel's first pair
    csum = torch.cumsum(log_1ma, 0)
    with torch.no_grad():
        first = torch.ones_like(pix, dtype=torch.bool)
        first[1:] = pix[1:] != pix[:-1]
        seg_start = torch.cummax(torch.where(first, torch.arange(len(pix), device=pix.device), 0), 0).values
    log_t_incl = csum - (csum - log_1ma).index_select(0, seg_start)  # log T after this pair
    with torch.no_grad():
        composited = log_t_incl.exp() >= T_MIN  # the first pair below T_MIN stops the pixel, uncomposited
    weight = torch.where(composited, alpha * (log_t_incl - log_1ma).exp().to(alpha.dtype), 0.0)  # [P]
    feat = features.reshape(C * N, F).index_select(0, items)  # [P, F]
    out = torch.zeros(C * HW, F, dtype=features.dtype, device=features.device)
    out = out.index_add(0, pix, weight[:, None] * feat).reshape(C, height, width, F)
    log_t_final = torch.zeros(C * HW, dtype=torch.float64, device=features.device)
    log_t_final = log_t_final.index_add(0, pix, torch.where(composited, log_1ma, 0.0))
    t_final = log_t_final.exp().to(features.dtype).reshape(C, height, width, 1)
    if backgrounds is not None:
        out = out + t_final * backgrounds[:, None, None, :]
    return out, 1.0 - t_final


def composite_loop(
    means2d: Tensor,  # [C, N, 2]
    conics: Tensor,  # [C, N, 3]
    opacities: Tensor,  # [N], or [C, N] (one leaf per camera, for per-camera gradients)
    features: Tensor,  # [C, N, F]
    radii: Tensor,  # [C, N, 2] int32
    depth_keys: Tensor,  # [C, N] float64
    width: int,
    height: int,
    backgrounds: Tensor | None = None,  # [C, F]
    absgrad: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """``composite`` as the obvious loop: one Gaussian at a time, front to back, over the whole image.

    The twin of the cpu backend's compositing kernels in their per-kernel tests (tens of Gaussians, tiny images;
    far too slow to render with). Same rules and pixel box as ``composite``, but the transmittance is the float32
    running product T <- T (1 - alpha) that the kernel (and 3DGS's CUDA kernel) keep, where ``composite`` sums
    log(1 - alpha) in float64: so the T_MIN stops fall on exactly the kernel's pairs.

    Returns features [C, H, W, F] (plus T_final * background), T_final [C, H, W] and ``composited`` [C, N, H, W]
    bool (no grad): where each Gaussian was composited (the Gaussian that stops a pixel is not). With ``absgrad``,
    backward sets ``means2d.absgrad`` [C, N, 2], the sum over pixels of |dL/dmeans2d| at each pixel.
    """
    C, N, F = features.shape
    dtype, dev = means2d.dtype, means2d.device
    op = opacities.expand(C, N)
    thr = alpha_thresholds(op)
    px = torch.arange(width, dtype=dtype, device=dev) + 0.5  # pixel centres
    py = (torch.arange(height, dtype=dtype, device=dev) + 0.5)[:, None]
    xs, ys = torch.arange(width, device=dev)[None, :], torch.arange(height, device=dev)[:, None]
    composited = torch.zeros(C, N, height, width, dtype=torch.bool, device=dev)
    if absgrad and means2d.requires_grad:
        means2d.absgrad = torch.zeros_like(means2d, requires_grad=False)
    images, t_finals = [], []
    for c in range(C):
        T = torch.ones(height, width, dtype=dtype, device=dev)
        live = torch.ones(height, width, dtype=torch.bool, device=dev)
        acc = torch.zeros(height, width, F, dtype=dtype, device=dev)
        visible = torch.nonzero((radii[c] > 0).any(-1)).squeeze(1)
        for n in visible[torch.sort(depth_keys[c, visible], stable=True).indices].tolist():
            m = means2d[c, n].detach().to(torch.float64)
            r = radii[c, n].to(torch.float64)
            in_box = (
                (xs >= torch.ceil(m[0] - r[0] - 0.5)) & (xs <= torch.floor(m[0] + r[0] - 0.5))
                & (ys >= torch.ceil(m[1] - r[1] - 0.5)) & (ys <= torch.floor(m[1] + r[1] - 0.5))
            )  # fmt: skip
            mx = means2d[c, n, 0].expand(height, width)  # one element per pixel, for the absgrad hook
            my = means2d[c, n, 1].expand(height, width)
            if absgrad and mx.requires_grad:
                mx.register_hook(_pixel_absgrad_hook(means2d, c, n, 0))
                my.register_hook(_pixel_absgrad_hook(means2d, c, n, 1))
            sigma = pair_sigma(mx - px, my - py, conics[c, n, 0], conics[c, n, 1], conics[c, n, 2])
            alpha = torch.clamp(op[c, n] * torch.exp(-sigma), max=ALPHA_MAX)
            with torch.no_grad():
                eligible = in_box & live & (sigma <= thr[c, n])  # alpha >= 1/255, as composite decides it
                t_next = T * (1.0 - alpha)
                take = eligible & (t_next >= T_MIN)
                live &= ~(eligible & (t_next < T_MIN))
            composited[c, n] = take
            weight = torch.where(take, alpha * T, 0.0)
            acc = acc + weight[..., None] * features[c, n]
            T = torch.where(take, T * (1.0 - alpha), T)
        if backgrounds is not None:
            acc = acc + T[..., None] * backgrounds[c]
        images.append(acc)
        t_finals.append(T)
    return torch.stack(images), torch.stack(t_finals), composited


def _pixel_absgrad_hook(means2d: Tensor, c: int, n: int, axis: int):
    def hook(grad: Tensor) -> None:  # grad [H, W]: this Gaussian's dL/dmeans2d[axis] at each pixel
        means2d.absgrad[c, n, axis] += grad.abs().sum()

    return hook


def render(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D] or [N, K, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int | None,
    backgrounds: Tensor | None,  # [C, F] already matching the rendered features
    with_colors: bool,
    with_depth: bool,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    absgrad: bool,
) -> tuple[Tensor, Tensor, dict]:
    """Project, shade, composite. Features are [colours][depth]; depth is accumulated (not normalised)."""
    C = viewmats.shape[0]
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height,
        eps2d=eps2d, near_plane=near_plane, far_plane=far_plane,
    )  # fmt: skip
    feats = []
    if with_colors:
        if sh_degree is None:
            feats.append(colors[None].expand(C, -1, -1))
        else:
            campos = torch.linalg.inv(viewmats.to(torch.float64))[:, :3, 3]  # [C, 3]
            dirs = means[None].to(torch.float64) - campos[:, None, :]  # [C, N, 3]
            feats.append(sh_to_rgb(sh_degree, colors[None].expand(C, -1, -1, -1), dirs))
    if with_depth:
        feats.append(proj.depths[..., None])
    features = torch.cat(feats, dim=-1)  # [C, N, F]
    img, alpha = composite(
        proj.means2d, proj.conics, opacities, features, proj.radii, proj.depth_keys, width, height,
        backgrounds, absgrad=absgrad,
    )  # fmt: skip
    info = {"means2d": proj.means2d, "radii": proj.radii, "depths": proj.depths, "conics": proj.conics}
    return img, alpha, info


def _absgrad_hook(means2d: Tensor, items: Tensor):
    def hook(grad: Tensor) -> None:  # grad [P, 5], the first two columns belong to means2d
        acc = torch.zeros(means2d.shape[0] * means2d.shape[1], 2, dtype=grad.dtype, device=grad.device)
        means2d.absgrad = acc.index_add(0, items, grad[:, :2].abs()).reshape(means2d.shape)

    return hook
