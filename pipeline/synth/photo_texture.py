"""Seabed albedo cut from real colour photographs, laid out as a randomised mosaic in world coordinates.

Used by the "photo" scene family (:mod:`.photo`). Why photographs: the procedural family's bright,
high-contrast textures share our own assumptions; real seabeds are darker, lower in contrast and have the
colour statistics of real coral, rubble and sand.

Layout ("texture bombing" on a jittered grid): tile centres sit on a square grid of pitch ``p`` metres, each
jittered. Every tile carries its own photo, crop centre (pixels, inside the photo's seabed part), rotation,
mirror flip, world size ``S`` (metres covered by ``crop_px`` pixels) and a small brightness gain. A world point
takes the colour of the nearby tiles blended by soft-Voronoi weights ``w_i ∝ exp(-d_i² / (2σ²))`` over the
3x3 neighbouring cells, so seams are narrow (about ±2σ²/p) and tiles have irregular, non-repeating shapes.
Beyond a crop's nominal square the tile keeps sampling the real photo around it; only at the edges of the
photo's seabed box is it mirrored (that shows only in far corners of large cells). Tiles are grouped into
substrate patches (several neighbouring tiles cut from the same photo at different places and angles), so
the seabed reads as patches of one kind of bottom rather than a quilt of unrelated photos.

Colour adjustment (the photos are enhanced, so brighter and more contrasted than real reflectance):
``albedo = albedo_scale · (m + contrast · (c − m))`` with ``m`` the mean colour of the photo's seabed part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.scene.images import read_image

F32 = torch.float32


class TextureFolderError(FileNotFoundError):
    """The folder of seabed photographs is missing or lacks a photo the config names."""


@dataclass
class PhotoSet:
    """The seabed parts of the photographs after the colour adjustment, padded into one tensor."""

    pixels: torch.Tensor  # [P, Hmax, Wmax, 3] float32 albedo of each photo's seabed box, zero padded
    packed: torch.Tensor  # [P·Hmax·Wmax, 4, 3] pixel (v, u) with (v, u+1), (v+1, u), (v+1, u+1), edges clamped
    rows: torch.Tensor  # [P] int64, rows of each seabed box
    cols: torch.Tensor  # [P] int64, columns of each seabed box
    names: tuple[str, ...]  # file stems, for the record


@dataclass
class Mosaic:
    """Per-tile parameters of the mosaic, a T x T table indexed by tile cell modulo T."""

    pitch: float  # metres between tile-grid cells
    sigma: float  # metres, soft-Voronoi blend width
    centre: torch.Tensor  # [T, T, 2] tile centre offset inside its cell, metres (cell origin + offset)
    photo: torch.Tensor  # [T, T] int64 photo index
    crop: torch.Tensor  # [T, T, 2] crop centre (u, v) in pixels of the photo's seabed box
    rot: torch.Tensor  # [T, T, 2, 2] world→texture rotation (with mirror flip), pixels per metre folded in
    gain: torch.Tensor  # [T, T] brightness gain


PhotoBox = tuple[str, float, float, float, float]  # (file stem, top, bottom, left, right) as fractions of the size


def load_photos(folder: Path, photos: tuple[PhotoBox, ...], albedo_scale: float, contrast: float) -> PhotoSet:
    """Read ``<folder>/<stem>.jpg`` for each box, keep the seabed box (open water, divers and captions left
    out) and apply the darkening/contrast adjustment. Raises :class:`TextureFolderError`."""
    folder = Path(folder)
    if not folder.is_dir():
        raise TextureFolderError(
            f"seabed texture folder {folder} not found: the photo scene family needs the EUVP photographs "
            f"(shared/data/textures/euvp-gtr-a beside the repository, or set PhotoSynthConfig.textures_dir)")
    if not photos:
        raise ValueError("no photos configured for the seabed mosaic")
    crops = []
    for stem, top, bottom, left, right in photos:
        path = folder / f"{stem}.jpg"
        if not path.is_file():
            raise TextureFolderError(f"seabed photo {path} not found in the texture folder {folder}")
        img = read_image(path).astype(np.float64)  # [H, W, 3] in [0, 1]
        h, w = img.shape[:2]
        r0, r1, c0, c1 = (int(round(f * n)) for f, n in ((top, h), (bottom, h), (left, w), (right, w)))
        if r1 - r0 < 16 or c1 - c0 < 16:
            raise ValueError(f"seabed box of photo {stem} is too small: {(top, bottom, left, right)}")
        sea = img[r0:r1, c0:c1]
        m = sea.reshape(-1, 3).mean(axis=0)
        crops.append(np.clip(albedo_scale * (m + contrast * (sea - m)), 0.0, 1.0))
    hmax, wmax = max(c.shape[0] for c in crops), max(c.shape[1] for c in crops)
    pixels = np.zeros((len(crops), hmax, wmax, 3), dtype=np.float32)
    packed = np.zeros((len(crops), hmax, wmax, 4, 3), dtype=np.float32)
    for i, c in enumerate(crops):
        right_ = np.concatenate([c[:, 1:], c[:, -1:]], 1)
        down = np.concatenate([c[1:], c[-1:]], 0)
        diag = np.concatenate([right_[1:], right_[-1:]], 0)
        pixels[i, : c.shape[0], : c.shape[1]] = c
        packed[i, : c.shape[0], : c.shape[1]] = np.stack([c, right_, down, diag], 2)
    return PhotoSet(torch.from_numpy(pixels), torch.from_numpy(packed.reshape(-1, 4, 3)),
                    torch.tensor([c.shape[0] for c in crops]), torch.tensor([c.shape[1] for c in crops]),
                    tuple(p[0] for p in photos))


def make_mosaic(photos: PhotoSet, rng: np.random.Generator, *, pitch: float, size_range: tuple[float, float],
                crop_px: int, blend: float, gain_spread: float, patch_tiles: int, patch_share: float,
                table: int = 64) -> Mosaic:
    """Random tile parameters (deterministic given ``rng``).

    ``size_range``: metres covered by ``crop_px`` pixels; ``blend``: σ as a fraction of ``pitch``;
    ``gain_spread``: ± relative brightness per tile. Substrate patches: the table is split into blocks of
    ``patch_tiles`` x ``patch_tiles`` tiles, each with a dominant photo that a tile takes with probability
    ``patch_share`` (else a random photo), so the seabed has patches of one kind of bottom, not a quilt.
    The table repeats every ``table · pitch`` metres (51 m by default, beyond any camera's useful range)."""
    t, n_photos = table, len(photos.rows)
    n_blocks = -(-t // patch_tiles)
    dominant = rng.integers(0, n_photos, (n_blocks, n_blocks))
    block = np.arange(t) // patch_tiles
    photo = np.where(rng.random((t, t)) < patch_share, dominant[block[:, None], block[None, :]],
                     rng.integers(0, n_photos, (t, t)))
    rows, cols = photos.rows.numpy()[photo], photos.cols.numpy()[photo]
    half = crop_px / 2

    def centre_in(n: np.ndarray) -> np.ndarray:  # crop centre: the crop inside the box where it fits
        lo = np.minimum(half, n / 2)
        return lo + rng.random(n.shape) * (np.maximum(half, n - half) - lo)

    cu, cv = centre_in(cols), centre_in(rows)
    theta = rng.uniform(0, 2 * math.pi, (t, t))
    flip = np.where(rng.random((t, t)) < 0.5, -1.0, 1.0)
    size = rng.uniform(size_range[0], size_range[1], (t, t))
    ppm = crop_px / size  # pixels per metre
    c, s = np.cos(theta), np.sin(theta)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s * flip, c * flip], -1)], -2) * ppm[..., None, None]
    centre = pitch * (0.5 + rng.uniform(-0.3, 0.3, (t, t, 2)))
    gain = 1.0 + rng.uniform(-gain_spread, gain_spread, (t, t))
    return Mosaic(pitch, blend * pitch, torch.as_tensor(centre, dtype=F32), torch.as_tensor(photo),
                  torch.as_tensor(np.stack([cu, cv], -1), dtype=F32), torch.as_tensor(rot, dtype=F32),
                  torch.as_tensor(gain, dtype=F32))


def _reflect(x: torch.Tensor, n: torch.Tensor | int) -> torch.Tensor:
    """Mirror coordinates into [0, n − 1] (triangle wave of period 2(n − 1))."""
    period = 2 * (n - 1)
    m = torch.remainder(x, period)
    return (n - 1) - (m - (n - 1)).abs()


def sample_photo(photos: PhotoSet, index: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear colour of photo ``index`` [M] at pixel coordinates ``uv`` [M, 2] (pixel-centre convention,
    mirrored at the seabed part's edges).  # [M, 3]"""
    u = _reflect(uv[:, 0] - 0.5, photos.cols[index].to(uv.dtype))
    v = _reflect(uv[:, 1] - 0.5, photos.rows[index].to(uv.dtype))
    u0, v0 = u.floor(), v.floor()
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    h, w = photos.pixels.shape[1], photos.pixels.shape[2]
    q = photos.packed[index * (h * w) + v0.long() * w + u0.long()]  # [M, 4, 3]
    return (q[:, 0] + (q[:, 1] - q[:, 0]) * fu) * (1 - fv) + (q[:, 2] + (q[:, 3] - q[:, 2]) * fu) * fv


def mosaic_albedo(photos: PhotoSet, mosaic: Mosaic, xy: torch.Tensor, keep: int = 3) -> torch.Tensor:
    """Albedo of world points ``xy`` [M, 2] (metres) from the photo mosaic.  # [M, 3] float32 in [0, 1]

    Only the ``keep`` nearest of the 3x3 candidate tiles are sampled (the others weigh < 1e-4 with the
    default blend width except exactly at four-tile junctions)."""
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"expected xy [M, 2], got {tuple(xy.shape)}")
    xy = xy.to(F32)
    t = mosaic.photo.shape[0]
    cell = torch.floor(xy / mosaic.pitch).long()  # [M, 2]
    offsets = torch.tensor([(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1)])  # [9, 2]
    ci = cell[:, None, :] + offsets  # [M, 9, 2]
    flat = torch.remainder(ci[..., 0], t) * t + torch.remainder(ci[..., 1], t)  # [M, 9] table index
    rel = xy[:, None, :] - (ci.to(F32) * mosaic.pitch + mosaic.centre.reshape(-1, 2)[flat])  # [M, 9, 2]
    d2 = (rel * rel).sum(-1)
    near_d2, near = torch.topk(d2, keep, dim=1, largest=False)  # [M, k]
    w = torch.softmax(-near_d2 / (2 * mosaic.sigma**2), dim=-1)  # [M, k]
    tile = flat.gather(1, near).reshape(-1)  # [M·k]
    rel_k = rel.gather(1, near[..., None].expand(-1, -1, 2)).reshape(-1, 2)
    uv = mosaic.crop.reshape(-1, 2)[tile] + (mosaic.rot.reshape(-1, 2, 2)[tile] @ rel_k[:, :, None])[:, :, 0]
    col = sample_photo(photos, mosaic.photo.reshape(-1)[tile], uv) * mosaic.gain.reshape(-1)[tile, None]
    return (col.reshape(-1, keep, 3) * w[..., None]).sum(1).clamp(0, 1)
