"""Seabed geometry of the "photo" scene family: a periodic heightfield grid and a ray marcher for it.

Deliberately unlike :mod:`.world` (analytic sum of sinusoids, sphere tracing, closed-form rocks):

- Relief is filtered noise on a grid: white noise shaped in the Fourier domain to a power-law spectrum
  ``P(f) ∝ (f² + f0²)^(-β/2) · exp(-(f/f_max)²)`` (β = 3: a fractal, rubble-like surface), normalised to a given
  standard deviation, plus lumpy boulder domes added into the same grid. The grid is periodic (FFT noise is),
  so the seabed is defined everywhere; its period (about 20 m) is beyond where the water leaves much contrast.
- Heights between grid nodes are bilinear. Rays are marched in two levels: coarse segments are skipped when
  their lowest point is above the local maximum of the heightfield (a max-dilated copy of the grid), the
  first segment that may cross is marched finely, and the crossing is refined by bisection.
- Normals come from central-difference gradient grids, interpolated bilinearly (smooth shading, no facets).

World frame: metres, z up, mean seabed near z = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

F64 = torch.float64


def pack_corners(grid: torch.Tensor) -> torch.Tensor:
    """Periodic grid [N, N, *C] → [N·N, 4, *C]: row i·N + j holds the nodes (i, j), (i+1, j), (i, j+1),
    (i+1, j+1), so bilinear interpolation is one gather of contiguous rows instead of four."""
    n = grid.shape[0]
    corners = [grid, torch.roll(grid, -1, 0), torch.roll(grid, -1, 1), torch.roll(grid, (-1, -1), (0, 1))]
    return torch.stack(corners, 2).reshape(n * n, 4, *grid.shape[2:]).contiguous()


@dataclass
class Terrain:
    """A periodic heightfield on a square grid (node (i, j) at x = i·spacing, y = j·spacing)."""

    height: torch.Tensor  # [N, N] float64 metres, indexed [ix, iy]
    height_q: torch.Tensor  # [N·N, 4] float32 packed corners of `height` (see pack_corners)
    hmax_q: torch.Tensor  # [N·N, 4] float32 packed corners of max(height) within ±dilate_cells nodes
    grad_q: torch.Tensor  # [N·N, 4, 2] float32 packed corners of (∂h/∂x, ∂h/∂y) (central differences)
    spacing: float  # metres between nodes
    dilate_cells: int  # half-width of the max-dilation window, in nodes

    @property
    def size(self) -> int:
        return int(self.height.shape[0])

    @property
    def h_min(self) -> float:
        return float(self.height.min())

    @property
    def h_max(self) -> float:
        return float(self.height.max())


def make_terrain(rng: np.random.Generator, *, n: int, spacing: float, relief_std: float, corr_length: float,
                 roughness_cut: float, boulders_per_m2: float, boulder_radius: tuple[float, float],
                 dilate_cells: int = 6) -> Terrain:
    """Random relief and boulders (deterministic given ``rng``).

    Args:
        n: grid nodes per side (period n·spacing metres).
        relief_std: standard deviation of the noise relief, metres.
        corr_length: metres; the spectrum flattens below f0 = 1/corr_length (no larger undulations).
        roughness_cut: metres; finest relief wavelength (Gaussian roll-off at f_max = 1/roughness_cut).
        boulders_per_m2: boulder density over the whole period.
        boulder_radius: (min, max) footprint radius in metres; height 0.35–0.7 of it, partly buried.
    """
    period = n * spacing
    f = torch.fft.fftfreq(n, d=spacing, dtype=F64)
    fx, fy = torch.meshgrid(f, f, indexing="ij")
    fr2 = fx * fx + fy * fy
    amp = (fr2 + (1.0 / corr_length) ** 2) ** (-3.0 / 4.0) * torch.exp(-fr2 * roughness_cut**2)  # sqrt(P), β = 3
    noise = torch.as_tensor(rng.standard_normal((n, n)), dtype=F64)
    h = torch.fft.ifft2(torch.fft.fft2(noise) * amp).real
    h = (h - h.mean()) / h.std() * relief_std

    xs = torch.arange(n, dtype=F64) * spacing
    n_boulders = int(round(boulders_per_m2 * period * period))
    for _ in range(n_boulders):
        cx, cy = rng.uniform(0, period, 2)
        r = rng.uniform(*boulder_radius)
        rx, ry = r * rng.uniform(0.75, 1.3), r * rng.uniform(0.7, 1.1)
        height = r * rng.uniform(0.35, 0.7)
        yaw = rng.uniform(0, math.pi)
        lobes = rng.uniform(-0.12, 0.12, 3)  # lumpy outline: radius modulated by 2-, 3- and 5-fold harmonics
        phases = rng.uniform(0, 2 * math.pi, 3)
        reach = int(math.ceil(1.4 * max(rx, ry) / spacing))  # wobble ≤ 1.36
        ix = (torch.arange(-reach, reach + 1) + int(round(cx / spacing))) % n
        iy = (torch.arange(-reach, reach + 1) + int(round(cy / spacing))) % n
        dx = _wrap(xs[ix] - cx, period)[:, None]
        dy = _wrap(xs[iy] - cy, period)[None, :]
        c, s = math.cos(yaw), math.sin(yaw)
        u, v = (c * dx + s * dy) / rx, (-s * dx + c * dy) / ry
        ang = torch.atan2(v, u)
        wobble = 1.0 + sum(a * torch.cos(k * ang + p) for a, k, p in zip(lobes, (2, 3, 5), phases))
        rho2 = (u * u + v * v) / wobble**2
        dome = height * (1.0 - rho2).clamp(min=0).pow(0.7) - 0.15 * height  # partly buried
        h[ix[:, None], iy[None, :]] += dome.clamp(min=0)
    return terrain_from_heights(h, spacing, dilate_cells)


def terrain_from_heights(h: torch.Tensor, spacing: float, dilate_cells: int = 6) -> Terrain:
    """Wrap a periodic height grid h [N, N] (metres, [ix, iy]; N a power of two) with its gradients and
    dilated maximum."""
    n = h.shape[0]
    if h.ndim != 2 or h.shape[1] != n or n < 4 or n & (n - 1):
        raise ValueError(f"expected a square height grid [N, N] with N a power of two, got {tuple(h.shape)}")
    h = h.to(F64)
    gx = (torch.roll(h, -1, 0) - torch.roll(h, 1, 0)) / (2 * spacing)
    gy = (torch.roll(h, -1, 1) - torch.roll(h, 1, 1)) / (2 * spacing)
    k = dilate_cells
    padded = F.pad(h[None, None], (k, k, k, k), mode="circular")
    hmax = F.max_pool2d(padded, 2 * k + 1, stride=1)[0, 0]
    f32 = torch.float32
    return Terrain(h, pack_corners(h.to(f32)), pack_corners(hmax.to(f32)),
                   pack_corners(torch.stack([gx, gy], -1).to(f32)), spacing, k)


def _wrap(d: torch.Tensor, period: float) -> torch.Tensor:
    return torch.remainder(d + period / 2, period) - period / 2


def bilinear(packed: torch.Tensor, n: int, spacing: float, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Periodic bilinear interpolation of a packed grid (:func:`pack_corners`, N = n a power of two) at world
    x, y (equal shapes [*S]).  # [*S, *C]"""
    gx, gy = x / spacing, y / spacing
    x0, y0 = torch.floor(gx), torch.floor(gy)
    fx, fy = gx - x0, gy - y0
    mask = n - 1  # two's complement: & (n − 1) is the periodic wrap, negatives included
    q = packed[((x0.long() & mask) * n + (y0.long() & mask)).reshape(-1)].reshape(*x.shape, *packed.shape[1:])
    extra = (None,) * (packed.ndim - 2)
    fx, fy = fx[(..., *extra)], fy[(..., *extra)]
    c00, c10, c01, c11 = (q.select(x.ndim, k) for k in range(4))
    return (c00 + (c10 - c00) * fx) * (1 - fy) + (c01 + (c11 - c01) * fx) * fy


def march(terrain: Terrain, o: torch.Tensor, d: torch.Tensor, *, fine_steps: int = 12, coarse_max: float = 0.6,
          coarse_batch: int = 4, bisections: int = 8) -> torch.Tensor:
    """Distance along unit rays to the first crossing of the bilinear heightfield. o, d: [M, 3] → t [M] float64
    (+inf for rays that do not point down; every downward ray hits, the heightfield being unbounded).

    Coarse segments have a horizontal half-length of at most ``(dilate_cells − 1) · spacing`` so the dilated
    maximum, bilinear at their midpoint, bounds the bilinear heights under the whole segment (one node spare
    for the interpolation stencils): a segment whose end (its lowest point) is above that bound cannot cross.
    The first segment that may cross is sampled at ``fine_steps`` points; a crossing found there is refined by
    ``bisections`` halvings and a final secant step (bracket ≤ 5 cm / 2^8 ≈ 0.2 mm; the surface is nearly
    linear at that scale, so the secant brings the error to micrometres). A crossing narrower than a fine step
    can be missed (the ray then hits the surface behind it): the fine step is at most
    ``coarse_max / fine_steps`` = 5 cm along steep rays (which barely move sideways) and about
    10 · spacing / fine_steps ≈ 1.7 cm along grazing ones, below the relief's finest wavelength; against a
    1 mm brute-force reference, 199 of 200 random rays agree to 1 mm. Marching runs
    in float32 (positions within 30 m: 2 µm resolution), the result is float64.
    """
    if o.shape != d.shape or o.ndim != 2 or o.shape[1] != 3:
        raise ValueError(f"expected o, d [M, 3], got {tuple(o.shape)} and {tuple(d.shape)}")
    o, d = o.to(torch.float32), d.to(torch.float32)
    t_out = torch.full((o.shape[0],), math.inf, dtype=F64)
    hits = _bracket_crossings(terrain, o, d, fine_steps, coarse_max, coarse_batch)
    if hits is not None:
        ids, lo, hi = hits
        t_out[ids] = _refine_crossings(terrain, o[ids].to(F64), d[ids].to(F64), lo.to(F64), hi.to(F64), bisections)
    return t_out


def _bracket_crossings(terrain: Terrain, o: torch.Tensor, d: torch.Tensor, fine_steps: int, coarse_max: float,
                       coarse_batch: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """March float32 rays o, d [M, 3] coarse then fine (:func:`march`): (the rays that hit [H], a distance above
    the surface [H], one at or below it [H]; float32), or None when no ray pointed down."""
    f32 = torch.float32
    h_lo, h_hi = terrain.h_min - 1e-3, terrain.h_max + 1e-3
    dxy = torch.linalg.norm(d[:, :2], dim=-1)
    reach = 2 * (terrain.dilate_cells - 1) * terrain.spacing  # horizontal length of a coarse segment (march)
    seg = (reach / dxy.clamp(min=1e-9)).clamp(max=coarse_max)  # [M] coarse segment length along the ray
    idx = (d[:, 2] < -1e-9).nonzero().squeeze(1)
    t_cur = ((o[idx, 2] - h_hi) / -d[idx, 2]).clamp(min=0)
    t_end = (o[idx, 2] - h_lo) / -d[idx, 2]  # below the lowest node: always under the surface
    lo_list, hi_list, id_list = [], [], []
    ks = torch.arange(coarse_batch, dtype=f32)
    fk = torch.arange(1, fine_steps + 1, dtype=f32) / fine_steps
    while idx.numel():
        oi, di, si = o[idx], d[idx], seg[idx]
        ta, tb, has, first = _coarse_candidates(terrain, oi, di, si, t_cur, t_end, ks)
        t_cur = torch.where(has, t_cur, ta[:, -1] + si)  # no candidate: move on by the whole batch
        # Fine: sample the first candidate segment.
        sel = has.nonzero().squeeze(1)
        found = torch.zeros_like(has)
        if sel.numel():
            a, b = ta[sel, first[sel]], tb[sel, first[sel]]
            hit, above, below = _fine_crossing(terrain, oi[sel], di[sel], a, b, fk)
            lo_list.append(above[hit])
            hi_list.append(below[hit])
            id_list.append(idx[sel[hit]])
            found[sel[hit]] = True
            t_cur[sel[~hit]] = b[~hit]
        keep = ~found
        idx, t_cur, t_end = idx[keep], t_cur[keep], t_end[keep]
    if not id_list:
        return None
    return torch.cat(id_list), torch.cat(lo_list), torch.cat(hi_list)


def _coarse_candidates(terrain: Terrain, oi: torch.Tensor, di: torch.Tensor, si: torch.Tensor, t_cur: torch.Tensor,
                       t_end: torch.Tensor, ks: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Which of the next K = len(ks) coarse segments (length si [A]) from t_cur [A] of rays oi, di [A, 3] may cross:
    (segment starts [A, K], ends [A, K], whether any may [A], the first that may [A])."""
    n, sp = terrain.size, terrain.spacing
    ta = t_cur[:, None] + si[:, None] * ks  # [A, K] segment starts
    tb = torch.minimum(ta + si[:, None], t_end[:, None])
    tm = 0.5 * (ta + tb)
    bound = bilinear(terrain.hmax_q, n, sp, oi[:, None, 0] + tm * di[:, None, 0],
                     oi[:, None, 1] + tm * di[:, None, 1])
    maybe = (oi[:, None, 2] + tb * di[:, None, 2] <= bound) | (tb >= t_end[:, None])
    return ta, tb, maybe.any(1), maybe.to(torch.int8).argmax(1)


def _fine_crossing(terrain: Terrain, os_: torch.Tensor, ds_: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
                   fk: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample the segments [a, b] [S] of rays os_, ds_ [S, 3] at the fractions fk [F]: (whether a sample is at or
    below the surface [S], the sample before the first such (or a) [S], that first sample [S])."""
    n, sp = terrain.size, terrain.spacing
    tf = a[:, None] + (b - a)[:, None] * fk  # [S, F]
    g = (os_[:, None, 2] + tf * ds_[:, None, 2]) - bilinear(
        terrain.height_q, n, sp, os_[:, None, 0] + tf * ds_[:, None, 0], os_[:, None, 1] + tf * ds_[:, None, 1])
    below = g <= 0
    k = below.to(torch.int8).argmax(1)
    prev = torch.where(k > 0, tf.gather(1, (k - 1).clamp(min=0)[:, None])[:, 0], a)
    return below.any(1), prev, tf.gather(1, k[:, None])[:, 0]


def _refine_crossings(terrain: Terrain, oi: torch.Tensor, di: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                      bisections: int) -> torch.Tensor:
    """The crossing of rays oi, di [H, 3] between lo (above the surface) and hi (at or below) [H], float64:
    ``bisections`` halvings of the bracket, then a secant step. → t [H]"""
    n, sp = terrain.size, terrain.spacing

    def gap(t: torch.Tensor) -> torch.Tensor:  # height of the ray above the surface, float64
        p = oi + t[:, None] * di
        return p[:, 2] - bilinear(terrain.height_q, n, sp, p[:, 0], p[:, 1]).to(F64)

    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        above = gap(mid) > 0
        lo = torch.where(above, mid, lo)
        hi = torch.where(above, hi, mid)
    g_lo, g_hi = gap(lo), gap(hi)
    denom = g_lo - g_hi
    frac = torch.where(denom > 0, g_lo / denom.clamp(min=1e-12), torch.full_like(lo, 0.5)).clamp(0, 1)
    return lo + (hi - lo) * frac


def normals(terrain: Terrain, xy: torch.Tensor) -> torch.Tensor:
    """Unit normals (−∂h/∂x, −∂h/∂y, 1)/‖·‖ at world points xy [M, 2], smooth across cells.  # [M, 3] float64"""
    g = bilinear(terrain.grad_q, terrain.size, terrain.spacing, xy[:, 0], xy[:, 1]).to(F64)  # [M, 2]
    n = torch.cat([-g, torch.ones_like(g[:, :1])], dim=-1)
    return n / torch.linalg.norm(n, dim=-1, keepdim=True)
