"""The synthetic seabed: geometry, analytic ray intersection and textured Lambertian shading.

World frame: metres, z up, mean seabed at z = 0. The seabed is a heightfield (a sum of sinusoids, so height
and gradient are analytic), intersected by sphere tracing with a Lipschitz bound and refined by Newton steps.
Rocks are ellipsoids and corals are clusters of capsules, both intersected in closed form. This renderer is
deliberately independent of the splatting engine: it is the ground truth the engine is tested against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.synth.noise import fbm3, value_noise3, worley2

F64 = torch.float64
LIGHT_DIR = (0.35, 0.25, 1.0)  # towards the light (sun through the surface), normalised at use
AMBIENT = 0.35


@dataclass
class World:
    """Everything the ray caster needs; built deterministically by :func:`make_world`."""

    waves: np.ndarray  # [K, 4] rows (amplitude, kx, ky, phase) of the heightfield
    rocks: np.ndarray  # [R, 7] rows (cx, cy, cz, rx, ry, rz, yaw)
    capsules: np.ndarray  # [Q, 8] rows (ax, ay, az, bx, by, bz, radius, coral_index)
    coral_tints: np.ndarray  # [n_corals, 3] base colours
    seed: int

    @property
    def slope_bound(self) -> float:
        """Lipschitz bound of the heightfield: |∇h| ≤ Σ a·|k|."""
        a, kx, ky = self.waves[:, 0], self.waves[:, 1], self.waves[:, 2]
        return float(np.sum(np.abs(a) * np.hypot(kx, ky)))


def make_world(seed: int, *, relief: float, n_rocks: int, n_corals: int, extent: tuple[float, float]) -> World:
    """Random terrain, rocks and corals over an area of ``extent`` = (half-width x, half-height y) metres."""
    rng = np.random.default_rng(seed)
    wavelengths = np.array([9.0, 5.5, 3.2, 1.9, 1.15, 0.7])
    amps = relief * np.array([0.22, 0.13, 0.07, 0.035, 0.02, 0.012])
    ang = rng.uniform(0, 2 * np.pi, len(wavelengths))
    k = 2 * np.pi / wavelengths
    waves = np.stack([amps, k * np.cos(ang), k * np.sin(ang), rng.uniform(0, 2 * np.pi, len(k))], axis=1)
    world = World(waves, np.zeros((0, 7)), np.zeros((0, 8)), np.zeros((0, 3)), seed)

    hx, hy = extent
    rocks = []
    for _ in range(n_rocks):
        x, y = rng.uniform(-hx, hx), rng.uniform(-hy, hy)
        r = rng.uniform(0.12, 0.38)
        rx, ry, rz = r * rng.uniform(0.8, 1.4), r * rng.uniform(0.7, 1.2), r * rng.uniform(0.45, 0.8)
        cz = terrain_height_np(world, x, y) + 0.35 * rz  # partly buried
        rocks.append((x, y, cz, rx, ry, rz, rng.uniform(0, np.pi)))
    capsules, tints = [], []
    palette = np.array([[0.95, 0.45, 0.35], [0.95, 0.65, 0.25], [0.75, 0.35, 0.70], [0.95, 0.85, 0.35],
                        [0.85, 0.30, 0.45], [0.55, 0.75, 0.45]])
    for ci in range(n_corals):
        x, y = rng.uniform(-hx, hx), rng.uniform(-hy, hy)
        base = np.array([x, y, terrain_height_np(world, x, y) - 0.03])
        trunk_h = rng.uniform(0.18, 0.36)
        top = base + np.array([rng.normal(0, 0.03), rng.normal(0, 0.03), trunk_h])
        capsules.append((*base, *top, rng.uniform(0.035, 0.06), ci))
        for _ in range(rng.integers(3, 6)):
            az, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.35, 1.2)
            length = rng.uniform(0.14, 0.30)
            d = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
            start = base + (top - base) * rng.uniform(0.5, 1.0)
            capsules.append((*start, *(start + length * d), rng.uniform(0.022, 0.04), ci))
        tints.append(palette[rng.integers(len(palette))] * rng.uniform(0.8, 1.0))
    world.rocks = np.asarray(rocks, dtype=np.float64).reshape(-1, 7)
    world.capsules = np.asarray(capsules, dtype=np.float64).reshape(-1, 8)
    world.coral_tints = np.asarray(tints, dtype=np.float64).reshape(-1, 3)
    return world


def terrain_height_np(world: World, x: float, y: float) -> float:
    a, kx, ky, ph = world.waves.T
    return float(np.sum(a * np.sin(kx * x + ky * y + ph)))


def terrain(world: World, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Heightfield h and its gradient. xy: [M, 2] → h [M], grad [M, 2]."""
    w = torch.as_tensor(world.waves, dtype=F64, device=xy.device)
    arg = xy @ w[:, 1:3].T + w[:, 3]  # [M, K]
    h = (torch.sin(arg) * w[:, 0]).sum(-1)
    c = torch.cos(arg) * w[:, 0]
    grad = torch.stack([(c * w[:, 1]).sum(-1), (c * w[:, 2]).sum(-1)], dim=-1)
    return h, grad


def intersect_terrain(world: World, o: torch.Tensor, d: torch.Tensor, t_max: float) -> torch.Tensor:
    """Distance along unit rays to the seabed, +inf where it is not hit before ``t_max``. o, d: [M, 3] → [M]."""
    bound = world.slope_bound
    t = torch.zeros(o.shape[0], dtype=F64, device=o.device)
    active = torch.ones_like(t, dtype=torch.bool)
    lip = d[:, 2].abs() + bound * torch.linalg.norm(d[:, :2], dim=-1) + 1e-12
    for _ in range(400):  # sphere tracing with the Lipschitz bound: never overshoots
        idx = active.nonzero().squeeze(1)
        if idx.numel() == 0:
            break
        p = o[idx] + t[idx, None] * d[idx]
        g = p[:, 2] - terrain(world, p[:, :2])[0]
        t[idx] = t[idx] + g / lip[idx]
        done = (g < 1e-4) | (t[idx] > t_max)
        active[idx[done]] = False
    for _ in range(4):  # Newton on g(t) = z(t) − h(xy(t)) from just above the surface
        p = o + t[:, None] * d
        h, grad = terrain(world, p[:, :2])
        g = p[:, 2] - h
        dg = d[:, 2] - (grad * d[:, :2]).sum(-1)
        step = torch.where(dg.abs() > 1e-9, g / dg, torch.zeros_like(g))
        t = t - step.clamp(-0.05, 0.05)
    return torch.where(t > t_max, torch.full_like(t, math.inf), t)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise dot product of [M, 3] tensors (explicit: much faster than .sum(-1) over a size-3 dim)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _near(o: torch.Tensor, d: torch.Tensor, centre: np.ndarray, radius: float) -> torch.Tensor:
    """Indices of unit rays that pass within ``radius`` of ``centre`` (cheap bounding-sphere preselection)."""
    oc = torch.as_tensor(centre, dtype=F64, device=o.device) - o
    proj = _dot(oc, d)
    dist2 = _dot(oc, oc) - proj * proj
    return ((dist2 < radius * radius) & (proj > -radius)).nonzero().squeeze(1)


def intersect_rocks(world: World, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest ellipsoid hit: (t [M] with +inf for misses, rock index [M] with −1 for misses)."""
    best = torch.full((o.shape[0],), math.inf, dtype=F64, device=o.device)
    which = torch.full((o.shape[0],), -1, dtype=torch.int64, device=o.device)
    for i, (cx, cy, cz, rx, ry, rz, yaw) in enumerate(world.rocks):
        idx = _near(o, d, np.array([cx, cy, cz]), max(rx, ry, rz) * 1.01)
        if idx.numel() == 0:
            continue
        m = torch.as_tensor(np.diag([1 / rx, 1 / ry, 1 / rz]) @ _rot_z(yaw).T, dtype=F64, device=o.device)
        ol = (o[idx] - torch.tensor([cx, cy, cz], dtype=F64, device=o.device)) @ m.T
        dl = d[idx] @ m.T
        a, b, c = _dot(dl, dl), _dot(ol, dl), _dot(ol, ol) - 1.0
        disc = b * b - a * c
        t = (-b - torch.sqrt(disc.clamp(min=0))) / a
        hit = (disc > 0) & (t > 1e-6) & (t < best[idx])
        best[idx[hit]] = t[hit]
        which[idx[hit]] = i
    return best, which


def intersect_capsules(world: World, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest capsule hit (closed form: cylinder body, then sphere caps): (t [M], capsule index [M])."""
    best = torch.full((o.shape[0],), math.inf, dtype=F64, device=o.device)
    which = torch.full((o.shape[0],), -1, dtype=torch.int64, device=o.device)
    for i, row in enumerate(world.capsules):
        ra = float(row[6])
        idx = _near(o, d, (row[0:3] + row[3:6]) / 2, float(np.linalg.norm(row[3:6] - row[0:3])) / 2 + ra * 1.01)
        if idx.numel() == 0:
            continue
        oi, di = o[idx], d[idx]
        pa = torch.tensor(row[0:3], dtype=F64, device=o.device)
        pb = torch.tensor(row[3:6], dtype=F64, device=o.device)
        ba, oa = pb - pa, oi - pa
        baba = float(ba @ ba)
        bard, baoa = di @ ba, oa @ ba
        rdoa, oaoa = _dot(di, oa), _dot(oa, oa)
        a = baba - bard * bard
        b = baba * rdoa - baoa * bard
        c = baba * oaoa - baoa * baoa - ra * ra * baba
        h = b * b - a * c
        t_body = (-b - torch.sqrt(h.clamp(min=0))) / a.clamp(min=1e-12)
        y = baoa + t_body * bard
        t = torch.where((h > 0) & (y > 0) & (y < baba), t_body, torch.full_like(t_body, math.inf))
        for cap in (pa, pb):  # caps: ray-sphere at either end
            oc = oi - cap
            bq = _dot(di, oc)
            hq = bq * bq - (_dot(oc, oc) - ra * ra)
            tq = -bq - torch.sqrt(hq.clamp(min=0))
            t = torch.where((hq > 0) & (tq > 1e-6) & (tq < t), tq, t)
        hit = (t > 1e-6) & (t < best[idx])
        best[idx[hit]] = t[hit]
        which[idx[hit]] = i
    return best, which


def _normals(world: World, p: torch.Tensor, kind: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Unit surface normals at hit points p [M, 3] for kind 0 terrain / 1 rock / 2 capsule."""
    n = torch.zeros_like(p)
    _, grad = terrain(world, p[:, :2])
    n[:] = torch.cat([-grad, torch.ones_like(grad[:, :1])], dim=-1)
    for i, (cx, cy, cz, rx, ry, rz, yaw) in enumerate(world.rocks):
        sel = (kind == 1) & (index == i)
        if sel.any():
            rot = torch.as_tensor(_rot_z(yaw), dtype=F64, device=p.device)
            local = (p[sel] - torch.tensor([cx, cy, cz], dtype=F64, device=p.device)) @ rot
            n[sel] = (local / torch.tensor([rx * rx, ry * ry, rz * rz], dtype=F64, device=p.device)) @ rot.T
    for i, row in enumerate(world.capsules):
        sel = (kind == 2) & (index == i)
        if sel.any():
            pa = torch.tensor(row[0:3], dtype=F64, device=p.device)
            ba = torch.tensor(row[3:6], dtype=F64, device=p.device) - pa
            s = (((p[sel] - pa) @ ba) / float(ba @ ba)).clamp(0, 1)
            n[sel] = p[sel] - (pa + s[:, None] * ba)
    return n / torch.linalg.norm(n, dim=-1, keepdim=True).clamp(min=1e-12)


def albedo(world: World, p: torch.Tensor, kind: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Procedural surface colour at hit points: sand with pebbles, rocks with lichen, corals with polyps. [M, 3]"""
    out = torch.zeros_like(p)
    for k, fn in ((0, _sand), (1, _rock), (2, _coral)):
        sel = (kind == k).nonzero().squeeze(1)
        if sel.numel():
            out[sel] = fn(world, p[sel], index[sel])
    return out.clamp(0, 1)


def _sand(world: World, p: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Fine fBm grain, scattered pebbles with dark rims, darker weed patches."""
    s = world.seed
    grain = fbm3(p, 3.0, 6, s + 1)
    sand = torch.tensor([0.78, 0.71, 0.55], dtype=F64) * (0.62 + 0.6 * grain)[:, None]
    f1, f2, cid = worley2(p[:, :2], 0.07, s + 2)
    tint = torch.stack([0.45 + 0.5 * cid, 0.42 + 0.45 * cid, 0.38 + 0.4 * cid.pow(0.7)], -1)
    rim = ((f2 - f1) / 0.07).clamp(0, 0.25) / 0.25
    pebble_col = tint * (0.55 + 0.45 * rim)[:, None] * (0.85 + 0.3 * grain)[:, None]
    sea = torch.where((cid < 0.45)[:, None], pebble_col, sand)
    weed = (value_noise3(p * 1.3, s + 3) > 0.68)[:, None]
    return torch.where(weed, sea * torch.tensor([0.45, 0.55, 0.30], dtype=F64), sea)


def _rock(world: World, p: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Grey-brown, high-contrast 3D grain, orange lichen spots."""
    rg = fbm3(p, 5.0, 5, world.seed + 4)
    rock = torch.tensor([0.50, 0.46, 0.42], dtype=F64) * (0.35 + 1.0 * rg)[:, None]
    lichen = value_noise3(p * 14.0, world.seed + 5) > 0.72
    return torch.where(lichen[:, None], torch.tensor([0.85, 0.55, 0.20], dtype=F64) * rg[:, None] + 0.2, rock)


def _coral(world: World, p: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Per-colony tint with polyp dots."""
    colony = torch.as_tensor(world.capsules[:, 7], dtype=torch.int64)[index]
    tints = torch.as_tensor(world.coral_tints, dtype=F64)[colony]
    return tints * (0.55 + 0.6 * value_noise3(p * 45.0, world.seed + 6))[:, None]


def cast(world: World, o: torch.Tensor, d: torch.Tensor, t_max: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Shade unit rays: (radiance J [M, 3] (0 for misses), distance t [M] (+inf for misses))."""
    t_ter = intersect_terrain(world, o, d, t_max)
    t_rock, i_rock = intersect_rocks(world, o, d)
    t_cap, i_cap = intersect_capsules(world, o, d)
    t = torch.minimum(t_ter, torch.minimum(t_rock, t_cap))
    kind = torch.zeros_like(i_rock)
    kind = torch.where(t_rock <= t, torch.ones_like(kind), kind)
    kind = torch.where(t_cap <= t, torch.full_like(kind, 2), kind)
    index = torch.where(kind == 1, i_rock, torch.where(kind == 2, i_cap, torch.full_like(i_rock, -1)))
    hit = torch.isfinite(t)
    J = torch.zeros_like(o)
    if hit.any():
        p = o[hit] + t[hit, None] * d[hit]
        n = _normals(world, p, kind[hit], index[hit])
        light = torch.tensor(LIGHT_DIR, dtype=F64)
        light = light / torch.linalg.norm(light)
        lambert = (n @ light).clamp(min=0)
        J[hit] = (albedo(world, p, kind[hit], index[hit]) * (AMBIENT + (1 - AMBIENT) * lambert)[:, None]).clamp(0, 1)
    return J, t
