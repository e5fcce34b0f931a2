"""The cpu backend's numba kernels one at a time, each against a small, obvious twin of that one step.

test_rasterize.py checks the kernels only together, through whole renders. Here the test builds each kernel's
inputs itself (the forward and backward get pairs packed by the test, not by ``bin_and_pack``, and the backward
gets the twin's saved state, not ``raster_fwd``'s), so a failure names the step:

- ``bin_and_pack``: the visible items, ordered by their first tile (ties in depth order); per tile, its
  (tile, Gaussian) pairs in depth order (ties in index order) against a numpy twin of the kernel's tile rule:
  the tiles of each Gaussian's pixel box (radii made by project.py's rule) with a pixel-centre column that the
  ellipse sigma <= log(255 o) meets within the tile's pixel-centre rows. Every twin pair must be there (so no
  pixel loses a Gaussian), and no other pair but within the kernel's 1e-3 px margin; the packed parameter rows
  bit for bit; the same for 1, 3 and 64 chunks of the kernel's parallel counting sort.
- ``raster_fwd``: image (with background), final transmittance, the per-pair masks of composited pixels and each
  tile's used pair range against ``_torch_ref.composite_loop`` (itself checked against ``composite``).
- ``raster_bwd`` + ``reduce_items``: gradients of means2d, conics, per-camera opacities, features and the
  absgrad statistic against torch.autograd through ``composite_loop``, on random cotangents of image and alpha.
  (The kernels take no depth: expected depth is just a feature channel to them.)

Inputs: 2 cameras x 40 screen-space Gaussians on a 27 x 20 image (4 x 3 tiles of 8 px, the last tile column 3 px
wide and the last tile row 4 px high), with means on tile borders, Gaussians partly or wholly off-screen, boxes
that reach the image but hold no pixel centre, culled ones (opacity < 1/255, radii 0), opacities just above 1/255
and near one (several stacked ones, so the 0.99 clamp and the T < 1e-4 stop both happen), tied depths.

Tolerances: forward max |diff| <= 1e-5 (float32; the kernel's exp differs from torch's in the last bit);
gradients max |diff| <= 1e-4 of the largest twin gradient of that parameter (see test_rasterize.py on why not
element-wise). Measured: forward <= 2e-7, gradients <= 3e-6 of scale (150 random scenes). Discrete outputs
(items and their order, masks, tile ranges) must be equal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from pipeline.splat._constants import ALPHA_MAX, ALPHA_MIN, CPU_TILE, T_MIN
from pipeline.splat._cpu_backend import BWD_SLICES, _kernels
from pipeline.splat._torch_ref import alpha_thresholds, composite, composite_loop, pair_sigma
from pipeline.splat.project import opacity_extent

W, H, C, N = 27, 20, 2, 40
TILE = CPU_TILE
NTX, NTY = -(-W // TILE), -(-H // TILE)
NTILES = C * NTX * NTY
FWD_ATOL = 1e-5
GRAD_RTOL = 1e-4


@pytest.fixture(scope="module")
def rk():
    """The raster kernel module (the backend's loader pins numba's threading layer first)."""
    return _kernels()[1]


@dataclass
class Splats:
    """Screen-space Gaussians as the raster kernels take them (float32, radii int32, depth keys float64)."""

    means2d: torch.Tensor  # [C, N, 2]
    conics: torch.Tensor  # [C, N, 3]
    opacities: torch.Tensor  # [N]
    features: torch.Tensor  # [C, N, 4]
    backgrounds: torch.Tensor  # [C, 4]
    radii: torch.Tensor  # [C, N, 2]
    depth_keys: torch.Tensor  # [C, N]

    @property
    def thresholds(self) -> torch.Tensor:
        return alpha_thresholds(self.opacities)


def _splats(seed: int = 0) -> Splats:
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=f64)

    means = rand(C, N, 2) * torch.tensor([W + 16.0, H + 16.0], dtype=f64) - 8.0  # some off-screen
    means[:, :5] = torch.tensor([[8.0, 8.0], [16.0, 4.5], [24.0, 16.0], [13.2, 8.0], [24.0, 10.0]], dtype=f64)
    std = 0.4 * torch.exp(2.6 * rand(C, N, 2))  # 0.4 to 5.4 px
    theta = math.pi * rand(C, N)
    # five stacked, almost opaque Gaussians near the image centre (clamp at 0.99, T < 1e-4 stops)
    means[:, 5:10] = torch.tensor([13.0, 10.0], dtype=f64) + 2.0 * rand(C, 5, 2)
    std[:, 5:10] = 3.0 + 2.0 * rand(C, 5, 2)
    means[:, 20:24] = torch.tensor([5.0, 13.0], dtype=f64) + 3.0 * rand(C, 4, 2)  # tied depths, sharing tiles
    cos, sin = torch.cos(theta), torch.sin(theta)
    rot = torch.stack([cos, -sin, sin, cos], dim=-1).reshape(C, N, 2, 2)
    cov = rot @ torch.diag_embed(std**2) @ rot.transpose(-1, -2)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[..., 0, 0], 0.5 * (inv[..., 0, 1] + inv[..., 1, 0]), inv[..., 1, 1]], dim=-1)

    opac = 0.05 + 0.9 * rand(N)
    opac[5:10] = torch.tensor([0.999, 0.9999, 0.995, 0.98, 0.9995], dtype=f64)
    opac[10:14] = torch.tensor([0.004, 0.0045, 0.006, 0.01], dtype=f64)  # just above 1/255
    opac[14:16] = 0.003  # below 1/255: culled
    opacities = opac.to(torch.float32)

    # the radius rule of project.py: the opacity-aware box, culled if it misses the image
    ext = opacity_extent(opacities.to(f64))[None].expand(C, N)
    rx, ry = torch.ceil(ext * cov[..., 0, 0].sqrt()), torch.ceil(ext * cov[..., 1, 1].sqrt())
    # a box that reaches into the image (so the Gaussian is visible) but holds no pixel centre
    means[:, 16, 0], means[:, 16, 1] = -rx[:, 16] + 0.3, 10.0
    mx, my = means[..., 0], means[..., 1]
    inside = (mx + rx > 0) & (mx - rx < W) & (my + ry > 0) & (my - ry < H)
    visible = inside & (opacities.to(f64) >= ALPHA_MIN)[None]
    radii = (torch.stack([rx, ry], dim=-1) * visible[..., None]).to(torch.int32)

    depth = 1.0 + 4.0 * rand(C, N)
    depth[:, 20:24] = 2.5  # ties keep index order
    depth_keys = torch.where(visible, depth, math.inf)
    return Splats(
        means2d=means.to(torch.float32),
        conics=conics.to(torch.float32),
        opacities=opacities,
        features=torch.rand(C, N, 4, generator=g),
        backgrounds=torch.rand(C, 4, generator=g),
        radii=radii,
        depth_keys=depth_keys,
    )


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def _tile(c: int, tx: int, ty: int) -> int:
    """Flat index of a tile in the kernels' list of C * n_tiles tiles."""
    return (c * NTY + ty) * NTX + tx


# ---------------------------------------------------------------- binning twin


@dataclass
class Bins:
    items: list[int]  # visible c * N + n, depth order per camera
    box: dict[int, list[int]]  # tile -> items whose pixel box reaches it, depth order
    columns: dict[int, list[int]]  # ... whose ellipse meets one of the tile's pixel-centre columns in its rows
    pixels: dict[int, list[int]]  # ... with a pixel centre inside the box and the ellipse (float32 sigma)


def _pixel_box(mx: float, my: float, rx: float, ry: float) -> tuple[int, int, int, int]:
    """Pixels whose centre lies in [m - r, m + r], clipped to the image (the reference's and the kernel's box)."""
    x0, x1 = max(math.ceil(mx - rx - 0.5), 0), min(math.floor(mx + rx - 0.5), W - 1)
    y0, y1 = max(math.ceil(my - ry - 0.5), 0), min(math.floor(my + ry - 0.5), H - 1)
    return x0, x1, y0, y1


def _min_sigma_on_rect(a: float, b: float, c: float, u0: float, u1: float, v0: float, v1: float) -> float:
    """min of sigma(u, v) = a u^2 / 2 + b u v + c v^2 / 2 (positive definite) over [u0, u1] x [v0, v1]: 0 if the
    rectangle holds the mean, else the least of the four edges' minima (each a clamped 1D quadratic)."""
    if u0 <= 0 <= u1 and v0 <= 0 <= v1:
        return 0.0

    def sigma(u, v):
        return 0.5 * (a * u * u + c * v * v) + b * u * v

    return min(
        *(sigma(u, min(max(-b * u / c, v0), v1)) for u in (u0, u1)),
        *(sigma(min(max(-b * v / a, u0), u1), v) for v in (v0, v1)),
    )


def _reaches(s: Splats, it: int, tx: int, ty: int, x0: float, x1: float, widen: float = 0.0) -> bool:
    """Whether item it's ellipse sigma <= log(255 o) meets [x0 - widen, x1 + widen] x (tile row ty's pixel-centre
    rows) in float64; x0 = x1 is one pixel-centre column."""
    c, n = divmod(it, N)
    mx, my = (float(v) for v in s.means2d[c, n])
    v0, v1 = ty * TILE + 0.5 - my, min(ty * TILE + TILE - 1, H - 1) + 0.5 - my
    sigma = _min_sigma_on_rect(*(float(v) for v in s.conics[c, n]), x0 - widen - mx, x1 + widen - mx, v0, v1)
    return sigma <= float(s.thresholds[n])


def _reaches_a_column(s: Splats, it: int, tx: int, ty: int, widen: float = 0.0) -> bool:
    """The tile rule of ``bin_and_pack`` (``_row_tiles``): the ellipse meets a pixel-centre column of the tile
    (in the image) over the tile's pixel-centre rows."""
    return any(_reaches(s, it, tx, ty, x + 0.5, x + 0.5, widen) for x in range(tx * TILE, min(tx * TILE + TILE, W)))


def _twin_bins(s: Splats) -> Bins:
    keys = s.depth_keys.numpy()
    items = []
    for c in range(C):
        vis = np.nonzero((s.radii[c] > 0).any(-1).numpy())[0]
        items += [c * N + int(n) for n in vis[np.argsort(keys[c, vis], kind="stable")]]
    thr = s.thresholds.numpy()
    box, columns, pixels = {}, {}, {}
    for it in items:
        c, n = divmod(it, N)
        mx, my = (float(v) for v in s.means2d[c, n])
        x0, x1, y0, y1 = _pixel_box(mx, my, *(float(v) for v in s.radii[c, n]))
        if x1 < x0 or y1 < y0:
            continue
        # float32 sigma at every pixel centre of the box, as the compositing decides alpha >= 1/255
        xs, ys = torch.arange(x0, x1 + 1, dtype=torch.float32) + 0.5, torch.arange(y0, y1 + 1)[:, None] + 0.5
        sig = pair_sigma(s.means2d[c, n, 0] - xs, s.means2d[c, n, 1] - ys.float(), *s.conics[c, n]).numpy()
        for ty in range(y0 // TILE, y1 // TILE + 1):
            for tx in range(x0 // TILE, x1 // TILE + 1):
                t = _tile(c, tx, ty)
                box.setdefault(t, []).append(it)
                if _reaches_a_column(s, it, tx, ty):
                    columns.setdefault(t, []).append(it)
                rows = slice(max(ty * TILE, y0) - y0, min(ty * TILE + TILE - 1, y1) - y0 + 1)
                cols = slice(max(tx * TILE, x0) - x0, min(tx * TILE + TILE - 1, x1) - x0 + 1)
                if (sig[rows, cols] <= thr[n]).any():
                    pixels.setdefault(t, []).append(it)
    for lists in (box, columns, pixels):  # depth order within each tile (ties: index order)
        for t in lists:
            lists[t].sort(key=lambda it: (keys[it // N, it % N], it))
    return Bins(items, box, columns, pixels)


def _packed_row(s: Splats, it: int) -> np.ndarray:
    """The kernels' row of one item: mx, my, a, b, c, opacity, log(255 o), first and last box row, 4 features."""
    c, n = divmod(it, N)
    mx, my = (float(v) for v in s.means2d[c, n])
    _, _, y0, y1 = _pixel_box(mx, my, *(float(v) for v in s.radii[c, n]))
    head = [*s.means2d[c, n].tolist(), *s.conics[c, n].tolist(), float(s.opacities[n]), float(s.thresholds[n])]
    return np.array(head + [y0, y1] + s.features[c, n].tolist(), np.float32)


def _pack(s: Splats, items: list[int], tiles: dict[int, list[int]]):
    """Pack per-tile item lists the way ``bin_and_pack`` does: rows [P, 13], tile_offsets, items, pair_item."""
    pos = {it: i for i, it in enumerate(items)}
    offsets, pair_item = [0], []
    for t in range(NTILES):
        pair_item += [pos[it] for it in tiles.get(t, [])]
        offsets.append(len(pair_item))
    rows = np.stack([_packed_row(s, items[i]) for i in pair_item]) if pair_item else np.zeros((0, 13), np.float32)
    return rows, np.array(offsets, np.int64), np.array(items, np.int64), np.array(pair_item, np.int32)


def _kernel_tiles(tile_offsets, items, pair_item) -> dict[int, list[int]]:
    out = {}
    for t in range(NTILES):
        lst = [int(items[i]) for i in pair_item[tile_offsets[t] : tile_offsets[t + 1]]]
        if lst:
            out[t] = lst
    return out


# ---------------------------------------------------------------- binning


def _bin(rk, s: Splats, n_chunks: int = 3):
    return rk.bin_and_pack(
        _np(s.means2d), _np(s.conics), _np(s.opacities), _np(s.thresholds), _np(s.features), _np(s.radii),
        _np(s.depth_keys), W, H, n_chunks,
    )  # fmt: skip


MARGIN_PX = 2e-3  # the kernel widens each ellipse's extent by 1e-3 px + 1e-5 of it (< 1.5e-3 px here)


def _extra_pairs(s: Splats, twin: Bins, got: dict[int, list[int]]) -> list[tuple[int, int]]:
    """Pairs the kernel keeps although the ellipse misses every pixel-centre column of the tile, even widened by
    the kernel's margin."""
    return [
        (t, it)
        for t, lst in got.items()
        for it in sorted(set(lst) - set(twin.columns.get(t, [])))
        if not _reaches_a_column(s, it, *reversed(divmod(t % (NTX * NTY), NTX)), MARGIN_PX)
    ]


@pytest.mark.parametrize("seed, n_chunks", [(0, 1), (1, 3), (2, 64)])
def test_bin_and_pack_matches_twin(rk, seed, n_chunks):
    s = _splats(seed)
    rows, offsets, items, pair_item = _bin(rk, s, n_chunks)
    twin = _twin_bins(s)
    assert sorted(items.tolist()) == sorted(twin.items) and len(set(items.tolist())) == len(items)
    assert offsets.shape == (NTILES + 1,) and offsets[0] == 0 and np.all(np.diff(offsets) >= 0)
    got = _kernel_tiles(offsets, items, pair_item)
    # items in the order of their first tile (ties in depth order), items without a pair last
    first = {}
    for t in range(NTILES):
        for i in pair_item[offsets[t] : offsets[t + 1]]:
            first.setdefault(int(i), t)
    key = [(first.get(i, NTILES), twin.items.index(int(items[i]))) for i in range(len(items))]
    assert key == sorted(key)
    for t in sorted(set(got) | set(twin.box)):
        lst, box = got.get(t, []), twin.box.get(t, [])
        assert lst == [it for it in box if it in lst], f"tile {t}: not a depth-ordered subset of the box pairs"
        missing = set(twin.columns.get(t, [])) - set(lst)
        assert not missing, f"tile {t}: pairs missing {sorted(missing)}"
        assert set(twin.pixels.get(t, [])) <= set(lst)  # (implied) no pixel loses a Gaussian
    # beyond the 1e-3 px margin, no pair the ellipse misses
    extra = _extra_pairs(s, twin, got)
    assert not extra, f"(tile, item) pairs kept although the ellipse misses the tile: {extra}"
    assert np.array_equal(rows, _pack(s, items.tolist(), got)[0])
    # the scene exercises what the test is about
    n_box, n_col = sum(map(len, twin.box.values())), sum(map(len, twin.columns.values()))
    assert n_box > n_col >= sum(map(len, twin.pixels.values())) > 0  # the ellipse prunes box pairs
    assert any(len(twin.columns.get(_tile(c, NTX - 1, NTY - 1), [])) > 0 for c in range(C))  # the partial tile
    assert len(got) > NTILES // 2 and max(map(len, got.values())) >= 8
    keys = s.depth_keys.reshape(-1).numpy()
    assert any(len(lst) > len(set(keys[lst])) for lst in got.values())  # tied depths share a tile
    culled = (s.radii == 0).all(-1)
    assert culled.any() and not set(np.nonzero(culled.reshape(-1).numpy())[0]) & set(twin.items)


def test_bin_and_pack_drops_a_tile_the_ellipse_misses_between_columns(rk):
    """Seed 1 has five pairs whose ellipse passes between two pixel-centre columns of a tile, or right of the
    image's last pixel centre in the last, partial tile column; the kernel kept them while it clamped x_hi to the
    image but not x_lo and tested the column span only after dividing by the tile size."""
    s = _splats(1)
    _, offsets, items, pair_item = _bin(rk, s)
    assert not _extra_pairs(s, _twin_bins(s), _kernel_tiles(offsets, items, pair_item))


# ---------------------------------------------------------------- forward


def _expected_masks(composited: torch.Tensor, items, tile_offsets, pair_item):
    """Per pair the 64-bit mask of the tile's pixels where its Gaussian was composited; per tile one past the last
    pair with a non-empty mask."""
    masks = np.zeros(pair_item.shape[0], np.uint64)
    tile_end = tile_offsets[:-1].copy()
    lane = (np.arange(TILE)[:, None] * TILE + np.arange(TILE)[None, :]).astype(np.uint64)
    for t in range(NTILES):
        c, r = divmod(t, NTX * NTY)
        ty, tx = divmod(r, NTX)
        for j in range(tile_offsets[t], tile_offsets[t + 1]):
            n = int(items[pair_item[j]]) % N
            on = np.zeros((TILE, TILE), bool)
            block = composited[c, n, ty * TILE : ty * TILE + TILE, tx * TILE : tx * TILE + TILE].numpy()
            on[: block.shape[0], : block.shape[1]] = block
            masks[j] = np.bitwise_or.reduce(np.left_shift(np.uint64(1), lane[on]), initial=np.uint64(0))
            if masks[j]:
                tile_end[t] = j + 1
    return masks, tile_end


def _raster_fwd(rk, s: Splats, rows, offsets):
    out = np.empty((C, H, W, 4), np.float32)
    out_t = np.empty((C, H, W), np.float32)
    masks = np.zeros(rows.shape[0], np.uint64)
    tile_end = np.empty(NTILES, np.int64)
    rk.raster_fwd(rows, offsets, W, H, _np(s.backgrounds), out, out_t, masks, tile_end)
    return out, out_t, masks, tile_end


def _twin_loop(s: Splats, **kw):
    return composite_loop(
        s.means2d, s.conics, s.opacities, s.features, s.radii, s.depth_keys, W, H, s.backgrounds, **kw
    )


def test_composite_loop_matches_reference_composite():
    """The twin is the reference's compositing: same image and alpha as ``_torch_ref.composite``."""
    s = _splats(0)
    img, t_final, composited = _twin_loop(s)
    ref_img, ref_alpha = composite(s.means2d, s.conics, s.opacities, s.features, s.radii, s.depth_keys, W, H,
                                   s.backgrounds)  # fmt: skip
    assert float((img - ref_img).abs().max()) <= FWD_ATOL
    assert float((1 - t_final - ref_alpha[..., 0]).abs().max()) <= FWD_ATOL
    assert composited.any()


def _sigma_images(s: Splats) -> torch.Tensor:
    """float32 sigma of every Gaussian at every pixel centre: [C, N, H, W]."""
    dx = s.means2d[..., 0, None, None] - (torch.arange(W) + 0.5)
    dy = s.means2d[..., 1, None, None] - (torch.arange(H) + 0.5)[:, None]
    a, b, c = (s.conics[..., k, None, None] for k in range(3))
    return pair_sigma(dx, dy, a, b, c)


def _eligible(s: Splats) -> torch.Tensor:
    """Pixels inside each visible Gaussian's box with alpha >= 1/255: [C, N, H, W]."""
    out = _sigma_images(s) <= s.thresholds[None, :, None, None]
    box = torch.zeros_like(out)
    for c in range(C):
        for n in range(N):
            if (s.radii[c, n] > 0).any():
                x0, x1, y0, y1 = _pixel_box(*s.means2d[c, n].tolist(), *s.radii[c, n].tolist())
                box[c, n, y0 : y1 + 1, x0 : x1 + 1] = True
    return out & box


@pytest.mark.parametrize("pairs", ["box", "binned"])
def test_raster_fwd_matches_twin(rk, pairs):
    """``box``: every tile of every pixel box, packed by the test (pairs that composite nothing included);
    ``binned``: ``bin_and_pack``'s pruned pairs (nothing a pixel needs was pruned)."""
    s = _splats(1)
    twin = _twin_bins(s)
    if pairs == "box":
        rows, offsets, items, pair_item = _pack(s, twin.items, twin.box)
    else:
        rows, offsets, items, pair_item = _bin(rk, s)
    out, out_t, masks, tile_end = _raster_fwd(rk, s, rows, offsets)
    img, t_final, composited = _twin_loop(s)
    want_masks, want_end = _expected_masks(composited, items, offsets, pair_item)
    assert np.array_equal(masks, want_masks), f"{int((masks != want_masks).sum())} pair masks differ"
    assert np.array_equal(tile_end, want_end)
    assert float(np.abs(out - img.numpy()).max()) <= FWD_ATOL
    assert float(np.abs(out_t - t_final.numpy()).max()) <= FWD_ATOL
    # the scene exercises the rules: pairs that composite nothing, the 0.99 clamp, the T < 1e-4 stop
    assert (masks != 0).any() and (pairs == "binned" or (masks == 0).any())
    raw = s.opacities[5:10, None, None] * torch.exp(-_sigma_images(s)[:, 5:10])
    assert bool(((raw > ALPHA_MAX) & composited[:, 5:10]).any())
    assert float(t_final.min()) < 1e-3
    assert bool((_eligible(s) & ~composited).any())  # only a T < 1e-4 stop leaves an eligible pixel out
    assert T_MIN <= float(t_final.min())


# ---------------------------------------------------------------- backward


def _assert_grad_close(name: str, got: torch.Tensor, want: torch.Tensor) -> None:
    scale = float(want.abs().max())
    assert scale > 0, f"{name}: the twin has no gradient"
    err = float((got - want).abs().max())
    assert err <= GRAD_RTOL * scale, f"{name}: max |diff| {err:.3g} > {GRAD_RTOL} * {scale:.3g}"


@pytest.mark.parametrize("seed", [1, 2])
def test_raster_bwd_matches_autograd_of_twin(rk, seed):
    s = _splats(seed)
    twin = _twin_bins(s)
    rows, offsets, items, pair_item = _pack(s, twin.items, twin.box)
    g = torch.Generator().manual_seed(100 + seed)
    v_out = torch.randn(C, H, W, 4, generator=g)
    v_alpha = torch.randn(C, H, W, generator=g)

    # twin: autograd through the loop (per-camera opacity leaves: the kernel's gradients are per camera)
    means2d = s.means2d.clone().requires_grad_()
    conics = s.conics.clone().requires_grad_()
    opac = s.opacities[None].repeat(C, 1).requires_grad_()
    feats = s.features.clone().requires_grad_()
    img, t_final, composited = composite_loop(means2d, conics, opac, feats, s.radii, s.depth_keys, W, H,
                                              s.backgrounds, absgrad=True)  # fmt: skip
    ((img * v_out).sum() + ((1.0 - t_final) * v_alpha).sum()).backward()

    # kernel: the twin's saved state in, per-item gradients out
    masks, tile_end = _expected_masks(composited, items, offsets, pair_item)
    acc = np.full((BWD_SLICES, len(items), rk.GROW + rk.NF), np.nan, np.float32)  # the kernel zeroes it
    rk.raster_bwd(rows, offsets, tile_end, masks, pair_item, W, H, _np(s.backgrounds), _np(t_final), _np(v_out),
                  _np(v_alpha), acc)  # fmt: skip
    v_means2d, v_conics = np.zeros((C, N, 2), np.float32), np.zeros((C, N, 3), np.float32)
    v_opac, v_feat, absgrad = np.zeros((C, N), np.float32), np.zeros((C, N, 4), np.float32), np.zeros_like(v_means2d)
    rk.reduce_items(acc, items, v_means2d, v_conics, v_opac, v_feat, absgrad)

    for name, got, want in [
        ("means2d", v_means2d, means2d.grad),
        ("conics", v_conics, conics.grad),
        ("opacities", v_opac, opac.grad),
        ("features", v_feat, feats.grad),
        ("absgrad", absgrad, means2d.absgrad),
    ]:
        _assert_grad_close(name, torch.from_numpy(got), want)
    # Gaussians that composite nothing (culled, empty box, or never reaching alpha 1/255) get exactly nothing
    idle = ~composited.flatten(2).any(-1)
    assert idle.any() and not np.any(v_means2d[idle.numpy()]) and not np.any(v_opac[idle.numpy()])
