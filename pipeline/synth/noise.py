"""Deterministic procedural noise for the synthetic scenes' textures (torch, float64).

Integer-lattice hashing (no global RNG), so a texture is a pure function of position and seed and the same
surface point gets the same colour from every view.
"""

from __future__ import annotations

import torch

_MASK = 0x7FFFFFFF


def hash3(ix: torch.Tensor, iy: torch.Tensor, iz: torch.Tensor, seed: int) -> torch.Tensor:
    """Hash integer lattice coordinates to uniform floats in [0, 1). Inputs int64 of one shape."""
    h = (ix * 1597334677 + iy * 3812015801 + iz * 2798796415 + seed * 1013904223) & _MASK
    h = ((h ^ (h >> 15)) * 2246822519) & _MASK
    h = ((h ^ (h >> 13)) * 3266489917) & _MASK
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).to(torch.float64) / float(1 << 24)


def value_noise3(p: torch.Tensor, seed: int) -> torch.Tensor:
    """Smooth value noise in [0, 1). p: [..., 3] → [...]."""
    i = torch.floor(p)
    f = p - i
    u = f * f * (3.0 - 2.0 * f)
    i = i.to(torch.int64)
    ix, iy, iz = i[..., 0], i[..., 1], i[..., 2]
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    out = torch.zeros(p.shape[:-1], dtype=torch.float64, device=p.device)
    for dx in (0, 1):
        wx = ux if dx else 1.0 - ux
        for dy in (0, 1):
            wy = uy if dy else 1.0 - uy
            for dz in (0, 1):
                wz = uz if dz else 1.0 - uz
                out = out + wx * wy * wz * hash3(ix + dx, iy + dy, iz + dz, seed)
    return out


def fbm3(p: torch.Tensor, base_freq: float, octaves: int, seed: int) -> torch.Tensor:
    """Fractal sum of value noise, normalised to about [0, 1]. p in metres: [..., 3] → [...]."""
    total = torch.zeros(p.shape[:-1], dtype=torch.float64, device=p.device)
    norm = 0.0
    for o in range(octaves):
        amp = 0.55**o
        total = total + amp * value_noise3(p * (base_freq * 2.0**o), seed + 101 * o)
        norm += amp
    return total / norm


def worley2(xy: torch.Tensor, cell: float, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cellular noise on a plane: distance to nearest / second-nearest feature point and the nearest cell's hash.

    xy: [..., 2] metres; cell: cell size in metres. Returns (F1, F2, cell_id in [0, 1)), each [...].
    """
    q = xy / cell
    base = torch.floor(q).to(torch.int64)
    inf = torch.full(xy.shape[:-1], float("inf"), dtype=torch.float64, device=xy.device)
    f1, f2, ident = inf.clone(), inf.clone(), torch.zeros_like(inf)
    zero = torch.zeros_like(base[..., 0])
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            cx, cy = base[..., 0] + dx, base[..., 1] + dy
            jx = hash3(cx, cy, zero, seed)
            jy = hash3(cx, cy, zero + 1, seed)
            d = torch.hypot(cx + jx - q[..., 0], cy + jy - q[..., 1])
            h = hash3(cx, cy, zero + 2, seed)
            closer = d < f1
            f2 = torch.where(closer, f1, torch.minimum(f2, d))
            ident = torch.where(closer, h, ident)
            f1 = torch.where(closer, d, f1)
    return f1 * cell, f2 * cell, ident
