"""Every loss term of DualPhys-GS (paper §4.2.3, eqs. 9–13) as its own function, with the physics made right.

Layout: NCHW. Rendered/target images [N,3,H,W] in [0,1]; depth D (distance along the ray, scene units) and
alpha [N,1,H,W]; A, B_frac [N,3,H,W]. ``depth_scale`` is the scene's fixed depth normaliser (never per frame).

Where we differ from the paper and its authors' code, and why:
- L_ab (eq. 9): the printed form E[B_s·D] − E[A·D] + μ·MSE(B_s + T, 1) *rewards* backscatter falling and
  transmission rising with depth — the opposite of the paper's own text. We use the signs the text describes:
  L_ab = E[A·D̃] − E[B_s·D̃] + μ·MSE(B_s + A, 1), D̃ = D / depth_scale (mean-centred per image so only the
  *correlation* with depth is rewarded, not a global offset). Lower when backscatter rises with depth.
- L_attenuation (in eq. 10): the attenuation held near a *measurement*. Before training, the water's global
  coefficients are fitted to the sparse points' colours across views (the same surface point seen at several
  ranges changes colour only because of the water; ``pipeline.medium.estimate``). L_attenuation is then
  Σ_c (log β̄_c − log β̂_c)² with β̄ the view's mean effective β_D (eq. 5's modulation included) and β̂ the
  measurement. Where the points cannot measure the water (too few seen twice), it falls back to a
  colour-constancy (grey-world) prior on the restored J in log-chromaticity: Σ_c (log mean J_c − mean_c log
  mean J_c)². We measured grey-world first: it makes a sandy seabed grey, and the measurement restores better
  (docs/DECISIONS.md, "Losses" and "Numbers behind code comments").
- L_scattering (in eq. 10): the veil bound. Backscatter can never exceed the light observed at a pixel
  (I = J·A + B with J·A ≥ 0), so mean relu(α·B − I) costs any veil brighter than the photo. With a
  measurement, plus Σ_c (log B̄_c − log B̂_c)²: the view's mean backscatter against the measured backscatter
  curve at the rendered ranges. The red channel needs it most: its direct signal J·A is ~0.1 in medium water,
  so a veil 0.02 too bright darkens the restored red by 20 %. We measured the
  dark-channel prior suggested in the design card on our generated scenes and dropped it: on bright sandy
  seabeds the water absorbs red, so the *observed* dark channel is lower than the true J's, and the DCP ranked
  the trivial solution better than the truth in every view and water type.
- The trivial "no water" solution (A = 1, B = 0, J = I) fits the photometric loss perfectly. What pushes
  against it: L_attenuation (the measured attenuation, or a water cast left in J), L_ab (backscatter must
  rise with depth and complement transmission, so once A < 1 the veil must appear) and, in the trainer, a
  view-independent J in medium modes (low SH degree), so range-dependent colour across views must be
  explained by the water. The first two score the trivial solution worse than the true medium on every
  generated view (tests/medium/test_losses.py).
- L_floater: opacity-entropy-like penalty α(1 − α) on rendered alpha, so the water column is not filled with
  semi-transparent Gaussians imitating backscatter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from pipeline.ops.image_losses import photometric_losses

EPS = 1e-6


def basic_loss(render: Tensor, target: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """L_basic = (1 − w)·L1 + w·(1 − SSIM), w = 0.2 (3DGS): the trainer's photometric loss, summed. [N,3,H,W] x2 → []"""
    terms = photometric_losses(render, target, ssim_weight, channels_first=True)
    return terms["l1"] + terms["dssim"]


def consistency_loss(A: Tensor, B_frac: Tensor, D: Tensor, depth_scale: float, mu: float = 0.1) -> Tensor:
    """Eq. 9, physically signed: L_ab = E[A·D̃] − E[B_s·D̃] + μ·MSE(B_s + A, 1), D̃ mean-centred per image.

    A, B_frac [N,3,H,W]; D [N,1,H,W].
    """
    Dn = D / depth_scale
    Dc = Dn - Dn.mean(dim=(2, 3), keepdim=True)
    return (A * Dc).mean() - (B_frac * Dc).mean() + mu * ((B_frac + A - 1.0) ** 2).mean()


def attenuation_prior(J: Tensor) -> Tensor:
    """L_attenuation: grey-world colour constancy of the restored J in log-chromaticity. [N,3,H,W] → []"""
    m = J.mean(dim=(2, 3)).clamp(min=1e-3).log()  # [N, 3]
    return ((m - m.mean(dim=1, keepdim=True)) ** 2).sum(dim=1).mean()


def log_anchor(value: Tensor, reference: Tensor) -> Tensor:
    """Σ_c (log value_c − log reference_c)²: a per-channel quantity held near a measurement, scale free.
    Used with the multi-view estimate from the sparse points (``pipeline.medium.estimate``): in L_attenuation
    for the view's mean effective β_D, in L_scattering for the view's mean backscatter against the measured
    backscatter curve at the same ranges. [3] x2 → []"""
    return ((value.clamp(min=1e-6).log() - reference.clamp(min=1e-6).log()) ** 2).sum()


def scattering_prior(B: Tensor, observed: Tensor, alpha: Tensor) -> Tensor:
    """L_scattering, the veil bound: mean relu(α·B − I). B, I [N,3,H,W]; alpha [N,1,H,W] → []"""
    return F.relu(alpha * B - observed).mean()


def water_adaptive_loss(l_att: Tensor, l_scat: Tensor, l_ab: Tensor, alpha_w: float, beta_w: float,
                        gamma: float = 1.0) -> Tensor:
    """Eq. 10: L_wat = α(w)·L_attenuation + β(w)·L_scattering + γ·L_ab."""
    return alpha_w * l_att + beta_w * l_scat + gamma * l_ab


def _grad_xy(x: Tensor) -> tuple[Tensor, Tensor]:
    gx = F.pad(x[..., :, 1:] - x[..., :, :-1], (0, 1, 0, 0))
    gy = F.pad(x[..., 1:, :] - x[..., :-1, :], (0, 0, 0, 1))
    return gx, gy


def edge_loss(B_frac: Tensor, D: Tensor, depth_scale: float, lam: float = 0.5, a: float = 10.0) -> Tensor:
    """Eq. 11: L_edge = L1(B_s·W_edge, 0) + λ·mean_p W_smooth(p)·(|∇x B_s| + |∇y B_s|).

    W_edge = the normalised depth-gradient magnitude (large at depth edges), W_smooth = exp(−a·(|∇x d| + |∇y d|))
    with d = D / depth_scale. The sum over p is taken as a mean so the weight is independent of image size.
    """
    d = D / depth_scale
    gx, gy = _grad_xy(d)
    mag = gx.abs() + gy.abs()
    w_edge = mag / (mag.amax(dim=(2, 3), keepdim=True) + EPS)
    w_smooth = torch.exp(-a * mag)
    bx, by = _grad_xy(B_frac)
    return (B_frac * w_edge).abs().mean() + lam * (w_smooth * (bx.abs() + by.abs())).mean()


def multiscale_loss(render: Tensor, target: Tensor, lam_ms: float = 1.0, scales: tuple[int, ...] = (1, 2, 4)) -> Tensor:
    """Eq. 12: L_ms = L1(O, T) + λ_ms/|S| Σ_s L1(D_s O, D_s T), S = {1, ½, ¼}, antialiased (box) downsampling."""
    total = (render - target).abs().mean()
    acc = render.new_zeros(())
    for s in scales:  # the full-resolution term is the one already computed
        acc = acc + (total if s == 1 else (F.avg_pool2d(render, s, ceil_mode=True)
                                          - F.avg_pool2d(target, s, ceil_mode=True)).abs().mean())
    return total + lam_ms / len(scales) * acc


def surface_loss(alpha: Tensor, pixels: Tensor) -> Tensor:
    """Mean 1 − α at the pixels where the view saw sparse points. [N,1,H,W], flat pixel indices [K] → []

    Not in the paper. A matched feature is a surface by construction, so the Gaussians must cover it. This is
    what holds the scene against the medium's shortcut: an uncovered pixel shows the veiling light B∞, which in
    murky water is nearly the photo, so the photometric loss alone barely resists losing the seabed
    (docs/DECISIONS.md, "The water must not eat the scene"). It is zero once the points are covered.
    """
    if pixels.numel() == 0:
        return alpha.new_zeros(())
    return (1.0 - alpha.reshape(-1)[pixels]).mean()


def point_depth_loss(D: Tensor, pixels: Tensor, ranges: Tensor) -> Tensor:
    """Mean |log D − log r| at the pixels where the view saw sparse points, r their distances from the camera.
    D [N,1,H,W] (distance along the ray), flat pixel indices [K], ranges [K] → []

    Not in the paper. In murky water a Gaussian far behind the seabed renders as the veil B∞ whatever its colour
    (its transmission is ~0), so distant Gaussians can paint a low-contrast patch of seabed as water while
    covering it (alpha ≈ 1: ``surface_loss`` is satisfied) — and their colour, unconstrained, drifts until the
    restored view is saturated there. The points say where the surface is (docs/DECISIONS.md)."""
    if pixels.numel() == 0:
        return D.new_zeros(())
    d = D.reshape(-1)[pixels].clamp(min=1e-3 * ranges.min())  # a tensor floor: no host sync, no graph break
    return (d.log() - ranges.log()).abs().mean()


DEPTH_BAND = 3.0  # depth_band_loss lets the surface lie up to this factor beyond its neighbourhood's range
NEAR_BAND = 1.1  # ... and, where the points' plane fit holds, up to this factor nearer than it


def depth_band_loss(D: Tensor, alpha: Tensor, range_map: Tensor, fitted: Tensor | None = None,
                    band: float = DEPTH_BAND, near: float = NEAR_BAND) -> Tensor:
    """Mean α·(max(0, log D − log R − log ``band``) + f·max(0, log R − log D − log ``near``)) over all pixels, R
    the view's point range map and f its plane fit's mask (1 where the fit found the surface), both upsampled to
    the image. D, alpha [N,1,H,W], range_map and fitted [N,1,h,w] (:func:`pipeline.medium.term.point_range_map`;
    ``fitted`` None: the far side only) → []

    Not in the paper. ``point_depth_loss`` holds the surface at the sparse points' own pixels; where SfM found
    few points (bright, low-texture sand) Gaussians were still drawn far behind the seabed (real RUIE frames;
    docs/DECISIONS.md, "The water must not eat the scene"), where they show only the veil, and the restored
    view was black there. A surface is continuous with its neighbourhood, so no covered pixel may lie more than
    ``band`` times beyond the range its nearest points predict.
    The near side: in turbid water a surface drawn in front of the seabed (0.4-0.8 of its range) shows the
    photo as well as the true one once its colour takes up the veil it no longer has in front of it; between the
    points nothing resisted, and 10-58 % of each training view of a camera-like turbid scene rendered so, while
    the points' plane fit was within 0.89-1.13 of the true range everywhere; the restored view kept grey veil
    patches there (docs/DECISIONS.md, "A surface in front of the seabed"). So no covered pixel may lie more than
    ``near`` times nearer than the fit either, where there is a fit (where it ran out to the horizon the range is
    a held bound, not a measurement). α is detached: the way out must not be to uncover the pixel, which is the
    shortcut this term closes."""
    if range_map.numel() == 0:
        return D.new_zeros(())
    grids = range_map.log() if fitted is None else torch.cat([range_map.log(), fitted.to(range_map.dtype)], 1)
    up = F.interpolate(grids, size=D.shape[-2:], mode="bilinear", align_corners=False)  # one resize for both
    ref = up[:, :1]
    logD = D.clamp(min=1e-6).log()
    excess = (logD - ref - math.log(band)).clamp(min=0)
    if fitted is not None:
        excess = excess + up[:, 1:] * (ref - logD - math.log(near)).clamp(min=0)
    return (alpha.detach() * excess).mean()


def cover_loss(alpha: Tensor, weight: Tensor) -> Tensor:
    """Mean w·(1 − α) over all pixels, w the visibility of the surface the view's sparse points predict there
    (:func:`pipeline.medium.term.cover_weight`) upsampled to the image. alpha [N,1,H,W], weight [N,1,h,w] → []

    Not in the paper. ``surface_loss`` keeps the points' own pixels covered; between and beyond them (the far
    seabed of an oblique view, where SfM finds points only in the near part) nothing did, and a seabed the
    water dims to 5-20 % of its light was given up as open water: its pixels then show the veil, which is
    nearly the photo, so the photometric loss barely resisted (docs/DECISIONS.md). Where the points' plane
    says a surface lies within sight, the Gaussians must cover it; where the plane runs to the horizon, or
    lies where the water hides it, the weight is 0 and open water stays open."""
    if weight.numel() == 0:
        return alpha.new_zeros(())
    w = F.interpolate(weight, size=alpha.shape[-2:], mode="bilinear", align_corners=False)
    return (w * (1.0 - alpha)).mean()


def floater_loss(alpha: Tensor) -> Tensor:
    """Mean α(1 − α) of rendered alpha: semi-transparent haze made of Gaussians costs. [N,1,H,W] → []"""
    return (alpha * (1 - alpha)).mean()


@dataclass
class LossWeights:
    """Eq. 13 weights w1..w5 and the term parameters."""

    w_basic: float = 1.0  # w1
    w_ab: float = 0.02  # w2
    w_wat: float = 0.05  # w3
    w_edge: float = 0.01  # w4
    w_ms: float = 0.1  # w5
    w_floater: float = 0.005  # not in the paper: keeps the water column free of floaters
    w_surface: float = 0.05  # not in the paper: the sparse points' pixels stay covered (surface_loss)
    w_point_depth: float = 0.05  # not in the paper: and render at the points' distance (point_depth_loss)
    w_depth_band: float = 0.05  # not in the paper: and no covered pixel far behind or in front of its points
    #                            (depth_band_loss)
    w_cover: float = 0.05  # not in the paper: and the surface their planes predict in sight covered (cover_loss)
    mu: float = 0.1  # complementarity weight inside L_ab
    anchor: float = 4.0  # weight of the measured-water anchors inside L_attenuation and L_scattering (4 restored
    #                      better than 1: docs/DECISIONS.md, "Losses" and "Numbers behind code comments")
    gamma_wat: float = 1.0  # γ inside L_wat
    lam_edge: float = 0.5
    lam_ms: float = 1.0
    ssim_weight: float = 0.2


def loss_terms(
    render: Tensor, target: Tensor, J: Tensor, A: Tensor, B: Tensor, B_frac: Tensor, D: Tensor, alpha: Tensor,
    depth_scale: float, w: LossWeights, alpha_w: float = 1.0, beta_w: float = 1.0,
    enabled: frozenset[str] = frozenset({"ab", "wat", "edge", "ms", "floater"}),
    anchor: dict[str, tuple[Tensor, Tensor]] | None = None, surface: tuple[Tensor, Tensor] | None = None,
    range_map: Tensor | None = None, cover: Tensor | None = None, range_fitted: Tensor | None = None,
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """Eq. 13's terms: (raw terms for logging, weighted terms whose sum is L_total).

    Weighted: w1·L_basic, w2·L_ab, w3·L_wat, w4·L_edge, w5·L_ms (+ the floater term); ``enabled`` switches
    terms off for the loss ablation (L_basic is always on). ``anchor`` = {"attenuation": (mean effective β_D,
    measured β_D), "backscatter": (mean B, measured mean B)} replaces the grey-world prior in L_attenuation by
    the first and adds the second to L_scattering.
    """
    raw: dict[str, Tensor] = {"basic": basic_loss(render, target, w.ssim_weight)}
    raw["ab"] = consistency_loss(A, B_frac, D, depth_scale, w.mu)
    if "wat" in enabled:
        raw["attenuation"] = w.anchor * log_anchor(*anchor["attenuation"]) if anchor else attenuation_prior(J)
        raw["scattering"] = scattering_prior(B, target, alpha)
        if anchor:
            raw["scattering"] = raw["scattering"] + w.anchor * log_anchor(*anchor["backscatter"])
        raw["wat"] = water_adaptive_loss(raw["attenuation"], raw["scattering"], raw["ab"], alpha_w, beta_w,
                                         w.gamma_wat)
    if "edge" in enabled:
        raw["edge"] = edge_loss(B_frac, D, depth_scale, w.lam_edge)
    if "ms" in enabled:
        raw["ms"] = multiscale_loss(render, target, w.lam_ms)
    if "floater" in enabled:
        raw["floater"] = floater_loss(alpha)
    if "surface" in enabled:  # the sparse points' evidence; point_depth and depth_band are switched with it
        if surface is not None:
            raw["surface"] = surface_loss(alpha, surface[0])
            raw["point_depth"] = point_depth_loss(D, *surface)
        if range_map is not None:
            raw["depth_band"] = depth_band_loss(D, alpha, range_map, range_fitted)
        if cover is not None:
            raw["cover"] = cover_loss(alpha, cover)
    weights = {"basic": w.w_basic, "ab": w.w_ab, "wat": w.w_wat, "edge": w.w_edge, "ms": w.w_ms,
               "floater": w.w_floater, "surface": w.w_surface, "point_depth": w.w_point_depth,
               "depth_band": w.w_depth_band, "cover": w.w_cover}
    evidence = {"point_depth", "depth_band", "cover"}  # present in raw only when "surface" is enabled
    weighted = {k: weights[k] * raw[k] for k in weights if k in raw and (k == "basic" or k in enabled or k in evidence)}
    return raw, weighted


def total_loss(
    render: Tensor, target: Tensor, J: Tensor, A: Tensor, B: Tensor, B_frac: Tensor, D: Tensor, alpha: Tensor,
    depth_scale: float, w: LossWeights, alpha_w: float = 1.0, beta_w: float = 1.0,
    enabled: frozenset[str] = frozenset({"ab", "wat", "edge", "ms", "floater"}),
) -> dict[str, Tensor]:
    """Eq. 13 as a named dict: every raw term and "total" = w1·L_basic + w2·L_ab + w3·L_wat + w4·L_edge + w5·L_ms
    (+ the floater term)."""
    raw, weighted = loss_terms(render, target, J, A, B, B_frac, D, alpha, depth_scale, w, alpha_w, beta_w, enabled)
    return {**raw, "total": sum(weighted.values())}
