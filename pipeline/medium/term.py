"""The medium's part of a training step: turn a rendered view (J, alpha, z-depth) into the with-water image,
score it with the DualPhys losses, and step the medium's own optimiser.

The trainer owns the Gaussians; this object owns the :class:`~pipeline.medium.model.Medium`, its Adam (two
parameter groups: attenuation and scattering, the controller's learning rates) and the fixed per-scene
quantities (depth normaliser, per-view ray-length factors). Densification never sees these parameters.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import asdict
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pipeline.config import MediumConfig
from pipeline.medium.losses import LossWeights, loss_terms
from pipeline.medium.measure import measure_water
from pipeline.medium.model import Medium, MediumOutput
from pipeline.ops.jit import dynamic_rows, maybe_compiled
from pipeline.profiling import section
from pipeline.scene.records import Camera, Scene, View, ray_length_factor, view_ranges
from pipeline.scene.seen import view_point_ranges
from pipeline.water.controller import medium_start_iteration

log = logging.getLogger(__name__)


def scene_depth_scale(scene: Scene, views: Sequence[View]) -> float:
    """Median camera-space depth of the sparse points over the given views: the scene's one depth normaliser.

    Falls back to the median camera-to-centroid distance when there are no points.
    """
    zs = []
    pts = np.asarray(scene.points, dtype=np.float64)
    for v in views:
        if len(pts):
            z = (pts @ v.R.T + v.t)[:, 2]
            zs.append(z[z > 0])
    z = np.concatenate(zs) if zs else np.zeros(0)
    if z.size:
        return float(np.median(z))
    centres = np.stack([v.center for v in views])
    return float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1))) or 1.0


def surface_pixels(scene: Scene, view: View, device: torch.device) -> tuple[Tensor, Tensor]:
    """The distinct pixels where ``view`` saw sparse points, at its camera's size: flat indices (y·W + x) [K] and
    the distance from the camera to the nearest point on each [K] (scene units)."""
    xy, r = view_point_ranges(scene, view)
    w, h = view.camera.width, view.camera.height
    x = np.clip(np.floor(xy[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.floor(xy[:, 1]).astype(np.int64), 0, h - 1)
    flat = y * w + x
    order = np.lexsort((r, flat))  # per pixel, the nearest point first
    flat, r = flat[order], r[order]
    first = np.ones(len(flat), dtype=bool)
    first[1:] = flat[1:] != flat[:-1]
    return (torch.as_tensor(flat[first], dtype=torch.long, device=device),
            torch.as_tensor(r[first], dtype=torch.float32, device=device))


RANGE_MAP_CELLS = 96  # the reference range map has about this many cells along the image's long side
COVER_MAX_RANGE = 5.0  # cover_range_map trusts a plane fit out to this many times the view's far points
COVER_TRANSMISSION = (0.05, 0.15)  # cover_weight: no weight below the first transmission, full from the second
RANGE_MAP_NEIGHBOURS = 32  # each cell fits the inverse range of this many nearest sparse-point pixels
RANGE_MAP_RIDGE = 1e-4  # ridge on the fit's slope (per neighbour, coordinates in image long sides)


class RangeMap(NamedTuple):
    """:func:`point_range_map`'s grid: the range per cell, and whether the cell's plane fit found the surface
    (False where it ran out to the horizon and the range is only the held bound)."""

    range: Tensor  # [1, 1, h, w]
    fitted: Tensor  # [1, 1, h, w] bool


def point_range_map(view: View, pixels: Tensor, ranges: Tensor) -> RangeMap:
    """A coarse map of how far the surface is from the camera, everywhere in the view, from its sparse points.

    Each cell of a ~96-cell grid (long side) fits the inverse range 1/r of the 32 point pixels nearest its centre
    as a linear function of the image position (exact for a plane: a plane's 1/z is linear in the pixel) and
    takes the fit at its centre. Between points that interpolates; beyond them (the far seabed of an oblique
    view, where SfM found points only in the near part) it follows the slope instead of repeating the nearest
    points' range. A fit that runs out to or past the horizon (1/r at most a tenth of its neighbours'
    smallest) is held at ten times their largest range, and no fit comes nearer than their nearest.
    (pixels, ranges) as :func:`surface_pixels`. Returns the grid (h, w ~96 on the long side) as a
    :class:`RangeMap`, empty when the view saw no point; its cost is bounded by the grid."""
    W, H = view.camera.width, view.camera.height
    if pixels.numel() == 0:
        return RangeMap(ranges.new_zeros((0,)), torch.zeros(0, dtype=torch.bool, device=ranges.device))
    cell = max(1, int(np.ceil(max(W, H) / RANGE_MAP_CELLS)))
    gw, gh = int(np.ceil(W / cell)), int(np.ceil(H / cell))
    side = float(max(W, H))
    px = torch.stack([(pixels % W).double() + 0.5, torch.div(pixels, W, rounding_mode="floor").double() + 0.5], 1)
    gy, gx = torch.meshgrid(torch.arange(gh, device=px.device), torch.arange(gw, device=px.device), indexing="ij")
    centres = torch.stack([(gx.reshape(-1) + 0.5) * cell, (gy.reshape(-1) + 0.5) * cell], 1).double()
    inv = 1.0 / ranges.double()
    k = min(RANGE_MAP_NEIGHBOURS, len(px))
    ridge = torch.diag(torch.tensor([0.0, 1.0, 1.0], dtype=px.dtype, device=px.device)) * RANGE_MAP_RIDGE * k
    out, fitted = [], []
    for chunk in centres.split(2048):
        idx = torch.cdist(chunk, px).topk(k, largest=False).indices  # [n, k]
        d = (px[idx] - chunk[:, None]) / side  # [n, k, 2]
        X = torch.cat([torch.ones_like(d[..., :1]), d], -1)  # [n, k, 3]
        y = inv[idx]  # [n, k]
        coef = torch.linalg.solve(X.transpose(1, 2) @ X + ridge, (X.transpose(1, 2) @ y[..., None]))[:, 0, 0]
        lo, hi = 0.1 * y.min(dim=1).values, y.max(dim=1).values  # never nearer than the nearest neighbour
        out.append(1.0 / torch.minimum(torch.where(coef > lo, coef, lo), hi))
        fitted.append(coef > lo)
    shape = (1, 1, gh, gw)
    return RangeMap(torch.cat(out).reshape(shape).to(ranges.dtype), torch.cat(fitted).reshape(shape))


def cover_range_map(rm: RangeMap, ranges: Tensor) -> Tensor:
    """The range of the surface the sparse points predict, where they predict one: ``rm.range`` where the
    fit did not run to the horizon and lies within ``COVER_MAX_RANGE`` times the view's 95th-percentile point
    range, ∞ elsewhere (no prediction). [1, 1, h, w], or empty when the view saw no point."""
    if rm.range.numel() == 0:
        return rm.range
    limit = COVER_MAX_RANGE * float(ranges.double().quantile(0.95))
    keep = rm.fitted & (rm.range < limit)
    return torch.where(keep, rm.range, torch.full_like(rm.range, float("inf")))


def cover_weight(cover_map: Tensor, beta: Tensor) -> Tensor:
    """How visible the predicted surface is through the water: the transmission exp(−β·r) at the
    :func:`cover_range_map` range r, ramped from 0 at ``COVER_TRANSMISSION[0]`` to 1 at
    ``COVER_TRANSMISSION[1]``; 0 where no surface is predicted. Same grid. ``beta`` is the medium's current
    β_D per channel (or one value); the clearest channel decides, since the seabed is in sight while any channel
    carries it (with the channels' mean, red-strangled water called seabed out of sight that green still
    showed: photo medium s1 in ``dualphys`` left 5 % of a view's visible seabed as veil; docs/DECISIONS.md)."""
    if cover_map.numel() == 0:
        return cover_map
    lo, hi = COVER_TRANSMISSION
    return ((torch.exp(-beta.min() * cover_map) - lo) / (hi - lo)).clamp(0.0, 1.0)


MIN_DENSIFY_TRANSMISSION = 0.05  # the densification gain 1/A is capped at 20


def view_transmission(scene: Scene, views: Sequence[View], beta_D: Sequence[float]) -> list[float]:
    """Per view: the direct transmission mean_c exp(−β_D,c · r) at the median range r from its camera to the
    sparse points it sees (``beta_D`` in 1/scene-unit: the measured water, or the starting one); 1 for a view
    that sees no point. The photo shows J·A, so its contrast, and every photometric gradient, is A times the
    scene's; densification divides by it (``Trainer.step``)."""
    ranges = view_ranges(scene.points, views) if len(scene.points) else np.full(len(views), np.nan)
    bd = np.asarray(beta_D, dtype=np.float64)
    return [1.0 if not np.isfinite(r) else float(np.exp(-bd * r).mean()) for r in ranges]


def _nchw(x: Tensor) -> Tensor:  # [H, W, C] → [1, C, H, W]
    return x.permute(2, 0, 1)[None]


class ViewEvidence(NamedTuple):
    """The fixed tensors one view's losses read besides its render (made once per run by :class:`MediumTerm`)."""

    ray: Tensor  # [1, 1, H, W] distance along the ray per unit of z-depth (ray_length_factor)
    pixels: Tensor  # [K] flat indices of the pixels where the view saw sparse points (surface_pixels)
    ranges: Tensor  # [K] the distance to the nearest such point
    range_map: Tensor  # [1, 1, h, w] point_range_map's grid (empty: no point)
    cover_map: Tensor  # [1, 1, h, w] cover_range_map's grid (empty: no point)
    range_fitted: Tensor  # [1, 1, h, w] float: 1 where point_range_map's plane fit found the surface (empty: no point)


def estimate_tensors(estimate: dict[str, Any] | None, device: torch.device) -> dict[str, Tensor] | None:
    """The sparse-point water measurement (:meth:`MediumEstimate.to_dict`) as [1, 3, 1, 1] float32 tensors:
    "beta_D", "beta_B", "B_inf" (None: no measurement)."""
    if estimate is None:
        return None
    return {k: torch.as_tensor(estimate[k], dtype=torch.float32, device=device).reshape(1, 3, 1, 1)
            for k in ("beta_D", "beta_B", "B_inf")}


def water_anchor(beta_eff: Tensor, B: Tensor, D: Tensor, alpha: Tensor,
                 estimate: dict[str, Tensor] | None) -> dict[str, tuple[Tensor, Tensor]] | None:
    """The water the sparse points measured, as (model, measurement) pairs: the view's mean effective β_D
    (including eq. 5's edge modulation, so the network can move attenuation around but not remove it) and
    its alpha-weighted mean backscatter against the measured curve at the rendered ranges.
    beta_eff [3]; B [N,3,H,W]; D, alpha [N,1,H,W]; estimate: "beta_D", "beta_B", "B_inf" as [1,3,1,1] (None: no
    measurement, no anchor)."""
    if estimate is None:
        return None
    dims = (0, 2, 3)
    with torch.no_grad():  # the measured curve at the rendered ranges; 4x4-pooled, it only enters a mean
        Dp, ap = F.avg_pool2d(D, 4, ceil_mode=True), F.avg_pool2d(alpha, 4, ceil_mode=True)
        b_ref = (ap * estimate["B_inf"] * (1 - torch.exp(-estimate["beta_B"] * Dp))).mean(dims)
    return {"attenuation": (beta_eff, estimate["beta_D"].flatten()), "backscatter": ((alpha * B).mean(dims), b_ref)}


def view_losses(medium: Medium, J: Tensor, alpha: Tensor, depth: Tensor, target: Tensor, ev: ViewEvidence,
                estimate: dict[str, Tensor] | None, depth_scale: float, weights: LossWeights, alpha_w: float,
                beta_w: float, enabled: frozenset[str]) -> tuple[dict[str, Tensor], Tensor]:
    """One view's medium and eq. 13's weighted terms: (terms, the view's effective β_D [3], detached).

    J [H,W,3] premultiplied, alpha [H,W,1], z-depth [H,W,1], target [H,W,3]. Pure (no state changes), so
    ``pipeline.ops.jit`` may compile it; this eager function is the compiled graph's reference twin."""
    # Each use takes its own view of J and alpha, in this order: autograd adds their gradients in the order the
    # graph recorded them, and the eager run repeats the runs before this function existed bit for bit only so.
    D = _nchw(depth) * ev.ray
    out = medium(_nchw(J), D, _nchw(alpha))
    _, weighted = loss_terms(out.I, _nchw(target), _nchw(J), out.A, out.B, out.B_frac, D, _nchw(alpha), depth_scale,
                             weights, alpha_w, beta_w, enabled,
                             anchor=water_anchor(out.beta_eff, out.B, D, _nchw(alpha), estimate),
                             surface=(ev.pixels, ev.ranges), range_map=ev.range_map, range_fitted=ev.range_fitted,
                             cover=cover_weight(ev.cover_map, out.beta_eff.detach()))
    return weighted, out.beta_eff.detach()


class MediumTerm:
    """Medium module + optimiser + losses for one training run."""

    def __init__(self, mode: str, cfg: MediumConfig, scene: Scene, views: Sequence[View],
                 targets: Sequence[Tensor], total_iterations: int, device: torch.device, *, compiled: bool = False,
                 exposure_space: str | None = None):
        self.cfg = cfg
        self.mode = mode
        self.depth_scale = scene_depth_scale(scene, views)
        tau = np.asarray(cfg.init_optical_depth)  # β·(typical depth): scale-free starting attenuation
        binf = torch.stack([t.reshape(-1, 3).median(dim=0).values for t in targets]).median(dim=0).values
        init = {"init_beta": tuple(float(x) for x in tau / self.depth_scale),
                "init_binf": tuple(float(x) for x in binf.clamp(0.02, 0.95).tolist())}
        self.estimate: dict[str, Any] | None = None
        self.beta_eff_mean: Tensor | None = None
        if cfg.colour_prior == "tracks" and len(scene.points):
            est = measure_water(scene.points, views, targets, scene.sightings, cfg.init_optical_depth,
                                exposure_space)  # with each view's exposure where the run learns it
            if est is not None:
                self.estimate = est.to_dict()
                init = {"init_beta": est.beta_D, "init_beta_b": est.beta_B, "init_binf": est.B_inf}
        self.medium = Medium.from_config(mode, cfg, self.depth_scale, **init).to(device)
        self.medium.water_factor.fill_(cfg.water_factor)
        rays: dict[Camera, Tensor] = {}  # one map per camera, shared by its views (a survey has one camera:
        for v in views:                 # 300 views' own copies at 640x480 were 369 MB)
            if v.camera not in rays:
                rays[v.camera] = torch.as_tensor(ray_length_factor(v.camera), dtype=torch.float32,
                                                 device=device)[None, None]
        self.ray = [rays[v.camera] for v in views]  # per view [1, 1, H, W], read only
        self.evidence: list[ViewEvidence] = []  # per view: what its losses read besides the render
        for v, ray in zip(views, self.ray):
            pixels, ranges = surface_pixels(scene, v, device)
            rm = point_range_map(v, pixels, ranges)
            self.evidence.append(ViewEvidence(ray, pixels, ranges, rm.range, cover_range_map(rm, ranges),
                                              rm.fitted.to(rm.range.dtype)))
        if compiled:  # every view's point count in one compiled graph (pipeline.ops.jit)
            for ev in self.evidence:
                dynamic_rows(ev.pixels), dynamic_rows(ev.ranges)
        self.transmission = view_transmission(scene, views, init["init_beta"])  # per view: mean A at its range
        self.start = medium_start_iteration(total_iterations, cfg.start_fraction)  # the controller's rule
        # Short runs scale the schedule: the paper's rates are for ~20k medium iterations.
        boost = max(1.0, cfg.lr_reference_iterations / max(1, total_iterations - self.start))
        m = self.medium
        att = [m.beta_d_raw, m.w] + (list(m.edge.parameters()) if m.edge else [])
        scat = [m.beta_b_raw, m.binf_raw] + (list(m.multiscale.parameters()) if m.multiscale else [])
        self.optimizer = torch.optim.Adam([
            {"params": [p for p in att if p.requires_grad], "lr": cfg.lr_attenuation * boost, "name": "attenuation"},
            {"params": scat, "lr": cfg.lr_scattering * boost, "name": "scattering"},
        ], eps=1e-15)
        self.weights = LossWeights(**cfg.loss_weights) if cfg.loss_weights else LossWeights()
        self._estimate_t = estimate_tensors(self.estimate, device)
        self._view_losses = maybe_compiled(view_losses, compiled)
        log.info("medium %s: depth scale %.3f, starts at iteration %d, lr boost %.1f", mode, self.depth_scale,
                 self.start, boost)

    def densify_gain(self, view_index: int) -> float:
        """What the screen-space gradients of view ``view_index`` are multiplied by before densification reads
        them: 1 / its transmission (capped), so the grow threshold means the same for the scene's radiance J
        in murky water as in air. Without it a turbid scene (A ≈ 0.15) stayed at a tenth of its Gaussian budget
        and its restoration was blurred (docs/DECISIONS.md)."""
        if not self.cfg.densify_transmission:
            return 1.0
        return 1.0 / max(self.transmission[view_index], MIN_DENSIFY_TRANSMISSION)

    def active(self, iteration: int) -> bool:
        return iteration > self.start

    def apply(self, view_index: int, J: Tensor, alpha: Tensor, depth: Tensor) -> tuple[MediumOutput, Tensor]:
        """J [H,W,3] premultiplied, alpha [H,W,1], z-depth [H,W,1] → (medium output NCHW, range D [1,1,H,W])."""
        D = _nchw(depth) * self.ray[view_index]
        return self.medium(_nchw(J), D, _nchw(alpha)), D

    def losses(self, view_index: int, J: Tensor, alpha: Tensor, depth: Tensor, target: Tensor) -> dict[str, Tensor]:
        """Eq. 13's weighted terms for one view (their sum is L_total): :func:`view_losses`, compiled when the
        run asked for it (``pipeline.ops.jit``)."""
        with section("losses: medium nets + terms fwd"):
            weighted, beta_eff = self._view_losses(
                self.medium, J, alpha, depth, target, self.evidence[view_index], self._estimate_t,
                self.depth_scale, self.weights, self.cfg.alpha_w, self.cfg.beta_w, frozenset(self.cfg.losses))
        with torch.no_grad():  # running mean over views of eq. 5's effective coefficient, for the report
            self.beta_eff_mean = beta_eff if self.beta_eff_mean is None else 0.95 * self.beta_eff_mean + 0.05 * beta_eff
        return weighted

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def effective_coefficients(self) -> dict[str, Any]:
        """The global per-channel coefficients in 1/scene-unit: β_D as the running mean over training views of
        the effective coefficient (w_c·β_c·(1 − γE)·T, eq. 5), β_B, B∞; plus the pre-training estimate."""
        m = self.medium
        with torch.no_grad():
            base = m.w * m.beta_D * m.water_factor
            bd = self.beta_eff_mean if self.beta_eff_mean is not None else base
            return {"beta_D": bd.tolist(), "beta_D_base": base.tolist(), "beta_B": m.beta_B.tolist(),
                    "B_inf": m.B_inf.tolist(), "depth_scale": self.depth_scale, "estimate": self.estimate,
                    "units": "1/scene-unit (x metric scale for 1/m)"}

    def state_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "config": asdict(self.cfg), "module": self.medium.state_dict(),
                "optimizer": self.optimizer.state_dict(), "depth_scale": self.depth_scale, "estimate": self.estimate,
                "beta_eff_mean": self.beta_eff_mean}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.medium.load_state_dict(sd["module"])
        self.optimizer.load_state_dict(sd["optimizer"])
        self.depth_scale = float(sd["depth_scale"])
        self.estimate = sd.get("estimate")
        self._estimate_t = estimate_tensors(self.estimate, self.medium.depth_scale.device)
        self.beta_eff_mean = sd.get("beta_eff_mean")
