"""numba kernels: tile binning, front-to-back compositing and its hand-written backward (8x8 tiles).

Data flow (per call; C cameras share one flat list of C * n_tiles tiles):
1. ``bin_and_pack``: radix depth sort of the visible (camera, Gaussian) items, the tiles each ellipse reaches
   (exact span per tile row), a parallel stable counting sort by tile, the items reordered by their first tile
   (locality for the backward's accumulators), and one packed float32 row per (tile, Gaussian) pair:
   ``rows[P, 9 + 4] = (mx, my, a, b, c, opacity, log(255 opacity), y0, y1, f0..f3)`` (y0..y1: the image
   rows of the Gaussian's pixel box, so the kernels only visit the tile rows it can reach; four feature slots,
   zero-padded, so each kernel is one fused SIMD loop; ``repack_features`` swaps in further channel groups).
2. ``raster_fwd``: one tile per work item; Gaussians outer, the 64 pixels inner (one fused SIMD pass). Stores
   the image, the final transmittance, and for every pair a 64-bit mask of the pixels it was composited at (so
   the backward never re-decides anything), plus the end of each tile's used pair range.
3. ``raster_bwd``: back to front per tile (3DGS's T / (1 - alpha) recursion); each pair's gradient
   ``(d mx, d my, d a, d b, d c, d opacity, |d mx|, |d my|, d f0..f3)`` is added to its item's row in one of
   a fixed number of accumulator slices [S, M, 8 + 4]: slice s owns tiles s, s + S, s + 2S, ... and one
   thread works a slice in tile order (no races, no atomics, no index_add). Which tiles are summed together,
   and in which order, never depends on the thread schedule, so training repeats bit for bit (with one slice
   per thread, the dynamic schedule made every run's sums, and after a few hundred steps its model, differ).
4. ``reduce_items``: per item, sum the slices in order.

Bit-reproducibility with the torch reference: ``raster_fwd`` is compiled without fastmath and evaluates sigma
with exactly ``_torch_ref.pair_sigma``'s operation order, so its alpha >= 1/255 decisions match the reference's.

Bit-reproducibility across processes: ``raster_bwd`` is never cached (``cache=False``), every process compiles it.
numba compiles a parallel kernel's loop body (the parfor "gufunc") into a library of its own and links a
``linkonce_odr`` copy into the kernel, which LLVM optimises a second time. A fresh process runs the body's first
build (the weak symbol binds to the definition loaded first); the disk cache keeps only the kernel's object, so a
process that loads it runs the re-optimised copy. With fastmath ``reassoc`` (which the backward's SIMD lane sums
need) the second pass orders float sums differently: cached and fresh gradients differed in their last bits and
a resumed training drifted from the straight run. Every other kernel, ``reduce_items`` (fastmath too) included,
gives the same bits loaded as compiled (tests/splat/test_kernel_cache.py; docs/DECISIONS.md, "Rendering engine").
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from pipeline.splat._constants import ALPHA_MAX, CPU_TILE, T_MIN
from pipeline.splat._numba_math import FASTMATH, fexp

TILE = CPU_TILE
LANES = TILE * TILE  # 64 pixels per tile, one SIMD-friendly block
ROW = 9  # packed row prefix: mx, my, a, b, c, opacity, threshold, first and last pixel row of the box
GROW = 8  # gradient row prefix: mx, my, a, b, c, opacity, |mx|, |my|
NF = 4  # feature slots per pair (RGB, RGB+ED and ED fit; the backend renders more channels in groups of 4)

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_HALF = np.float32(0.5)
_AMAX = np.float32(ALPHA_MAX)
_TMIN = np.float32(T_MIN)
_GATHER = np.uint64(0x0102040810204080)  # 8 bytes of 0/1 (one uint64) times this, >> 56: byte j -> bit j
_S56 = np.uint64(56)


@njit(cache=True)
def argsort_stable(keys):
    """Stable argsort of float64 keys (LSD radix sort, 11-bit digits, constant digits skipped): [M] -> [M] int64.

    Same order as a stable comparison sort (ties keep index order), so the reference's torch.sort(stable=True)
    and this agree exactly; faster than numba's mergesort (docs/DECISIONS.md, "Numbers behind code comments").
    """
    n = keys.shape[0]
    bits = keys.view(np.uint64)
    k = np.empty(n, np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    for i in range(n):  # order-preserving map of IEEE doubles to unsigned integers
        k[i] = ~bits[i] if bits[i] & sign else bits[i] | sign
    idx = np.arange(n)
    k2, idx2 = np.empty_like(k), np.empty_like(idx)
    count = np.empty(2049, np.int64)
    for shift in range(0, 64, 11):
        sh = np.uint64(shift)
        count[:] = 0
        for i in range(n):
            count[((k[i] >> sh) & np.uint64(2047)) + np.uint64(1)] += 1
        if count.max() == n:  # every key has the same digit here
            continue
        for d in range(2048):
            count[d + 1] += count[d]
        for i in range(n):
            d = (k[i] >> sh) & np.uint64(2047)
            j = count[d]
            count[d] = j + 1
            k2[j], idx2[j] = k[i], idx[i]
        k, k2 = k2, k
        idx, idx2 = idx2, idx
    return idx


@njit(inline="always")
def _ellipse_consts(a, b, c, thr):
    """Per-Gaussian constants of ``_row_tiles``: (ok, det, 1/a, k = 2 a thr, v_lim, v*)."""
    det = a * c - b * b
    if not (det > 0 and a > 0 and c > 0 and thr > 0):
        return False, 1.0, 1.0, 0.0, 0.0, 0.0
    return True, det, 1.0 / a, 2.0 * a * thr, np.sqrt(2.0 * thr * a / det), -b * np.sqrt(2.0 * thr / (det * c))


@njit(inline="always")
def _row_tiles(mx, my, b, ok, det, inv_a, k, v_lim, vs, ty, tx0, tx1, width, height):
    """Tiles [lo, hi] of tile row ty that the ellipse sigma <= thr reaches (empty: hi < lo), within [tx0, tx1].

    Exact x-extent of the ellipse over the row's pixel-centre y-span, with a small margin, so only tiles the
    ellipse provably misses are dropped (the pixel box alone keeps more pairs; docs/DECISIONS.md, "Numbers behind
    code comments"). With u = x - mx, v = y - my and det = ac - b^2: u ranges over
    (-b v +- sqrt(2 a thr - det v^2)) / a; the upper bound is concave in v with its maximum sqrt(2 thr c / det)
    at v* = -b sqrt(2 thr / (det c)), the lower bound is its mirror image, so over a v-interval each bound is at
    v* (if inside) or at the nearer end.
    """
    if not ok:
        return tx0, tx1  # degenerate: keep the whole box row
    v0 = max(ty * TILE + 0.5 - my, -v_lim)
    v1 = min(min(ty * TILE + TILE - 1, height - 1) + 0.5 - my, v_lim)
    if v1 < v0:
        return tx0, tx0 - 1
    v = min(max(vs, v0), v1)
    u_hi = (-b * v + np.sqrt(max(k - det * v * v, 0.0))) * inv_a
    v = min(max(-vs, v0), v1)
    u_lo = (-b * v - np.sqrt(max(k - det * v * v, 0.0))) * inv_a
    margin = 1e-3 + 1e-5 * (abs(u_lo) + abs(u_hi))
    x_lo = max(int(np.ceil(mx + u_lo - margin - 0.5)), 0)
    x_hi = min(int(np.floor(mx + u_hi + margin - 0.5)), width - 1)
    if x_hi < x_lo:  # between two pixel-centre columns, or right of the last one: no pixel of the row
        return tx0, tx0 - 1
    return max(x_lo // TILE, tx0), min(x_hi // TILE, tx1)


@njit(parallel=True, cache=True)
def bin_and_pack(means2d, conics, opacities, thresholds, features, radii, depth_keys, width, height, n_chunks):
    """Sort and bin visible items into tiles; pack one row per (tile, Gaussian) pair.

    Inputs: means2d [C, N, 2], conics [C, N, 3], opacities [N], thresholds [N] (log(255 o), float32),
    features [C, N, 4], radii [C, N, 2] int32, depth_keys [C, N] float64.
    Returns rows [P, 9 + 4] f32, tile_offsets [C * n_tiles + 1] i64, items [M] i64 (c * N + n) and pair_item [P]
    i32 (index into items of each pair). Each tile's pairs are in depth order (ties in index order); ``items``
    itself is in the order of each item's first tile (row-major over C * n_tiles, ties in depth order), so the
    items of neighbouring tiles sit close together: the backward's per-item accumulator rows and the packing's
    item rows are then read from cache rather than from all over the table (docs/DECISIONS.md, "Numbers behind
    code comments", item order).
    """
    C, N = depth_keys.shape
    F = NF
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    ntile = ntx * nty
    # 1. visible items, depth-sorted within each camera (stable: ties keep index order, as the reference)
    # No top-level np.zeros here: in a parallel kernel numba makes an array expression a parfor, and under the
    # backend's dynamic schedule (chunk size 1) it hands out one element per scheduling step (~0.25 ms per 1,200
    # elements: 2.3 of the binning's ~11 ms went to zeroing ``hist`` and ``tile_offsets``). Plain loops instead.
    # Visible Gaussians are counted and gathered in blocks of ``block`` (parallel over camera x block, so one
    # camera's 100k Gaussians do not run on one thread), then sorted per camera.
    block = 8192
    nb = (N + block - 1) // block
    n_blk = np.empty((C, nb + 1), np.int64)  # per camera: visible count of each block, then their prefix
    for q in prange(C * nb):
        c, b = q // nb, q % nb
        k = 0
        for n in range(b * block, min(N, (b + 1) * block)):
            if radii[c, n, 0] > 0 or radii[c, n, 1] > 0:
                k += 1
        n_blk[c, b + 1] = k
    cam_start = np.empty(C + 1, np.int64)
    cam_start[0] = 0
    for c in range(C):
        n_blk[c, 0] = 0
        for b in range(nb):
            n_blk[c, b + 1] += n_blk[c, b]
        cam_start[c + 1] = cam_start[c] + n_blk[c, nb]
    M = cam_start[C]
    vis_idx = np.empty(M, np.int64)
    vis_key = np.empty(M, np.float64)
    for q in prange(C * nb):
        c, b = q // nb, q % nb
        k = cam_start[c] + n_blk[c, b]
        for n in range(b * block, min(N, (b + 1) * block)):
            if radii[c, n, 0] > 0 or radii[c, n, 1] > 0:
                vis_idx[k] = n
                vis_key[k] = depth_keys[c, n]
                k += 1
    items = np.empty(M, np.int64)
    for c in range(C):
        idx = vis_idx[cam_start[c] : cam_start[c + 1]]
        keys = vis_key[cam_start[c] : cam_start[c + 1]].copy()
        order = argsort_stable(keys)
        for i in range(cam_start[c + 1] - cam_start[c]):
            items[cam_start[c] + i] = c * N + idx[order[i]]
    # 2. per item: packed parameter row, and the tile rectangle holding the pixel centres inside
    #    [m - r, m + r] (the reference's pixel box)
    item_rows = np.empty((M, ROW + F), np.float32)
    rect = np.empty((M, 4), np.int64)  # tx0, tx1, ty0, ty1 (inclusive; empty when tx1 < tx0)
    iblock = 1024  # items per parallel work item (the backend schedules dynamically, one block at a time)
    for blk in prange((M + iblock - 1) // iblock):
        for i in range(blk * iblock, min(M, (blk + 1) * iblock)):
            c, n = items[i] // N, items[i] % N
            item_rows[i, 0] = means2d[c, n, 0]
            item_rows[i, 1] = means2d[c, n, 1]
            item_rows[i, 2] = conics[c, n, 0]
            item_rows[i, 3] = conics[c, n, 1]
            item_rows[i, 4] = conics[c, n, 2]
            item_rows[i, 5] = opacities[n]
            item_rows[i, 6] = thresholds[n]
            for f in range(F):
                item_rows[i, ROW + f] = features[c, n, f]
            mx, my = float(means2d[c, n, 0]), float(means2d[c, n, 1])
            rx, ry = float(radii[c, n, 0]), float(radii[c, n, 1])
            x0 = max(int(np.ceil(mx - rx - 0.5)), 0)
            x1 = min(int(np.floor(mx + rx - 0.5)), width - 1)
            y0 = max(int(np.ceil(my - ry - 0.5)), 0)
            y1 = min(int(np.floor(my + ry - 0.5)), height - 1)
            item_rows[i, 7] = y0
            item_rows[i, 8] = y1
            if x1 < x0 or y1 < y0:
                rect[i, 0], rect[i, 1], rect[i, 2], rect[i, 3] = 0, -1, 0, -1
            else:
                rect[i, 0], rect[i, 1], rect[i, 2], rect[i, 3] = x0 // TILE, x1 // TILE, y0 // TILE, y1 // TILE
    # 3. tile span of every (item, tile row) once, and per-chunk tile histograms (chunks = consecutive items)
    row_off = np.empty(M + 1, np.int64)
    row_off[0] = 0
    for i in range(M):
        row_off[i + 1] = row_off[i] + max(rect[i, 3] - rect[i, 2] + 1, 0)
    span = np.empty((row_off[M], 2), np.int32)  # first, last tile of the row
    n_chunks = max(1, min(n_chunks, M))
    n_tiles_all = C * ntile
    hist = np.empty((n_chunks, n_tiles_all), np.int64)
    first = np.empty(M, np.int64)  # each item's first tile (n_tiles_all: none), the key of its output order
    for k in prange(n_chunks):
        for t in range(n_tiles_all):
            hist[k, t] = 0
        for i in range(k * M // n_chunks, (k + 1) * M // n_chunks):
            base = (items[i] // N) * ntile
            mx, my, b = float(item_rows[i, 0]), float(item_rows[i, 1]), float(item_rows[i, 3])
            ok, det, inv_a, kk, v_lim, vs = _ellipse_consts(
                float(item_rows[i, 2]), b, float(item_rows[i, 4]), float(item_rows[i, 6])
            )
            e = row_off[i]
            first[i] = n_tiles_all
            for ty in range(rect[i, 2], rect[i, 3] + 1):
                lo, hi = _row_tiles(mx, my, b, ok, det, inv_a, kk, v_lim, vs, ty, rect[i, 0], rect[i, 1], width,
                                    height)  # fmt: skip
                span[e, 0], span[e, 1] = lo, hi
                e += 1
                if hi >= lo and first[i] == n_tiles_all:
                    first[i] = base + ty * ntx + lo
                for tx in range(lo, hi + 1):
                    hist[k, base + ty * ntx + tx] += 1
    # 4. the item order of the outputs: depth-sorted item i goes to slot[i], by its first tile (counting sort,
    #    stable, so ties stay in depth order); items that reach no tile go last
    slot = _counting_order(first, n_tiles_all + 1)
    # 5. stable counting sort by tile: each chunk fills its slice of every tile, in depth order
    tile_offsets = np.empty(n_tiles_all + 1, np.int64)  # every entry is written below
    pos = np.empty((n_chunks, n_tiles_all), np.int64)
    run = 0
    for t in range(n_tiles_all):
        tile_offsets[t] = run
        for k in range(n_chunks):
            pos[k, t] = run
            run += hist[k, t]
    tile_offsets[n_tiles_all] = run
    P = run
    pair_item = np.empty(P, np.int32)
    for k in prange(n_chunks):
        for i in range(k * M // n_chunks, (k + 1) * M // n_chunks):
            base = (items[i] // N) * ntile
            e = row_off[i]
            for ty in range(rect[i, 2], rect[i, 3] + 1):
                for tx in range(span[e, 0], span[e, 1] + 1):
                    t = base + ty * ntx + tx
                    pair_item[pos[k, t]] = slot[i]
                    pos[k, t] += 1
                e += 1
    # 6. items and their rows in slot order, then one row per pair in pair order (sequential writes; the rows read
    #    are those of the tile's neighbourhood)
    items_out = np.empty(M, np.int64)
    slot_rows = np.empty((M, ROW + F), np.float32)
    for blk in prange((M + iblock - 1) // iblock):
        for i in range(blk * iblock, min(M, (blk + 1) * iblock)):
            items_out[slot[i]] = items[i]
            for f in range(ROW + F):
                slot_rows[slot[i], f] = item_rows[i, f]
    rows = np.empty((P, ROW + F), np.float32)
    chunk = 4096
    for k in prange((P + chunk - 1) // chunk):
        for p in range(k * chunk, min(P, (k + 1) * chunk)):
            i = pair_item[p]
            for f in range(ROW + F):
                rows[p, f] = slot_rows[i, f]
    return rows, tile_offsets, items_out, pair_item


@njit(cache=True)
def _counting_order(key, n_keys):
    """slot [M] i64: the position of element i when sorted by key [M] (values in 0..n_keys-1), ties in index order."""
    count = np.zeros(n_keys + 1, np.int64)
    for i in range(key.shape[0]):
        count[key[i] + 1] += 1
    for t in range(n_keys):
        count[t + 1] += count[t]
    slot = np.empty(key.shape[0], np.int64)
    for i in range(key.shape[0]):
        slot[i] = count[key[i]]
        count[key[i]] += 1
    return slot


@njit(inline="always")
def _tile_pixels(t, ntx, ntile, width, height, px, py, inside):
    """Pixel-centre coordinates and in-image flags of tile t's 64 lanes; returns (camera, x0, y0)."""
    c = t // ntile
    r = t - c * ntile
    y0 = (r // ntx) * TILE
    x0 = (r - (r // ntx) * ntx) * TILE
    for p in range(LANES):
        x = x0 + (p % TILE)
        y = y0 + (p // TILE)
        px[p] = np.float32(x) + _HALF
        py[p] = np.float32(y) + _HALF
        inside[p] = x < width and y < height
    return c, x0, y0


@njit(parallel=True, cache=True)
def repack_features(rows, pair_item, items, features):
    """A copy of ``rows`` whose feature slots hold another channel group: features [C, N, 4]."""
    out = rows.copy()
    N = features.shape[1]
    P = rows.shape[0]
    chunk = 4096
    for k in prange((P + chunk - 1) // chunk):
        for p in range(k * chunk, min(P, (k + 1) * chunk)):
            it = items[pair_item[p]]
            for f in range(NF):
                out[p, ROW + f] = features[it // N, it % N, f]
    return out


@njit(parallel=True, cache=True)
def raster_fwd(rows, tile_offsets, width, height, backgrounds, out, out_t, masks, tile_end):
    """Composite every tile front to back.

    rows [P, 9 + 4], tile_offsets [T + 1], backgrounds [C, 4] -> out [C, H, W, 4] (with T_final * bg),
    out_t [C, H, W] final transmittance, masks [P] uint64 (bit p: composited at lane p; pre-zeroed),
    tile_end [T] (one past the last pair with a non-zero mask).
    No fastmath: sigma must round exactly as ``_torch_ref.pair_sigma`` does.

    One fused pass over a pair's lanes, with per-lane flags in byte arrays and no integer reduction inside it, so
    the loop vectorises 8 wide (a 64-bit mask or count built in the loop made it 4 wide, and a separate sigma pass
    to skip pairs that hit no live pixel cost more than it saved: docs/DECISIONS.md, "Numbers behind code
    comments", compositing forward). The 64-bit mask is gathered from the byte flags per tile row afterwards.
    """
    ntx = (width + TILE - 1) // TILE
    ntile = ntx * ((height + TILE - 1) // TILE)
    for t in prange(tile_offsets.shape[0] - 1):
        px, py = np.empty(LANES, np.float32), np.empty(LANES, np.float32)
        inside = np.empty(LANES, np.bool_)
        c, x0, y0 = _tile_pixels(t, ntx, ntile, width, height, px, py, inside)
        T = np.ones(LANES, np.float32)
        live = np.empty(LANES, np.uint8)  # 0/1 per lane; as 8 uint64 words, one per tile row
        take = np.zeros(LANES, np.uint8)  # 0/1: composited at this lane by the current pair
        for p in range(LANES):
            live[p] = inside[p]
        live_w, take_w = live.view(np.uint64), take.view(np.uint64)
        acc = np.zeros((NF, LANES), np.float32)
        end = tile_offsets[t]
        for j in range(tile_offsets[t], tile_offsets[t + 1]):
            any_live = np.uint64(0)
            for r in range(TILE):
                any_live |= live_w[r]
            if any_live == 0:
                break
            mx, my, a, b, cc = rows[j, 0], rows[j, 1], rows[j, 2], rows[j, 3], rows[j, 4]
            op, thr = rows[j, 5], rows[j, 6]
            f0, f1, f2, f3 = rows[j, ROW], rows[j, ROW + 1], rows[j, ROW + 2], rows[j, ROW + 3]
            # lanes lo..hi-1: the tile rows inside the Gaussian's pixel box (outside it sigma > thr). Unsigned, so
            # numba adds no negative-index wraparound and the loop stays SIMD (signed: much slower; docs/DECISIONS.md,
            # "Numbers behind code comments").
            r_lo = max(int(rows[j, 7]) - y0, 0)
            r_hi = min(int(rows[j, 8]) - y0, TILE - 1) + 1
            for p in range(np.uint64(r_lo * TILE), np.uint64(r_hi * TILE)):
                dx = mx - px[p]
                dy = my - py[p]
                s = _HALF * (a * dx * dx + cc * dy * dy) + b * dx * dy  # == _torch_ref.pair_sigma
                s = max(s, _F0)
                alpha = min(_AMAX, op * fexp(-s))
                ok = (s <= thr) & (live[p] != 0)
                tn = T[p] * (_F1 - alpha)
                stop = ok & (tn < _TMIN)
                tk = ok & (tn >= _TMIN)
                w = alpha * T[p] if tk else _F0
                T[p] = tn if tk else T[p]
                live[p] = live[p] & (not stop)
                take[p] = tk
                acc[0, p] += w * f0
                acc[1, p] += w * f1
                acc[2, p] += w * f2
                acc[3, p] += w * f3
            m = np.uint64(0)
            for r in range(r_lo, r_hi):  # 8 flag bytes of row r -> 8 mask bits at r * 8
                m |= ((take_w[r] * _GATHER) >> _S56) << np.uint64(r * TILE)
            if m != 0:
                masks[j] = m
                end = j + 1
        tile_end[t] = end
        for p in range(LANES):
            if inside[p]:
                y, x = y0 + p // TILE, x0 + p % TILE
                out_t[c, y, x] = T[p]
                for f in range(NF):
                    out[c, y, x, f] = acc[f, p] + T[p] * backgrounds[c, f]


@njit(parallel=True, cache=False, fastmath=FASTMATH)  # never cached: module docstring, across processes
def raster_bwd(rows, tile_offsets, tile_end, masks, pair_item, width, height, backgrounds, out_t, v_out, v_alpha,
               acc):  # fmt: skip
    """Backward of ``raster_fwd`` (3DGS's back-to-front recursion), one fused SIMD pass per pair.

    v_out [C, H, W, 4] = dL/d(rendered features), v_alpha [C, H, W] = dL/d(rendered alpha) ->
    acc [S, M, 8 + 4] (zeroed here, each slice by its thread): slice s gets the gradient of every pair of tiles
    s, s + S, ..., added to the pair's item row in tile order by the one thread that runs it (no races, no
    atomics, the same sums whatever the schedule; ``reduce_items`` sums the slices).

    For pair i at a pixel, with T_i its transmittance in front and B the sum of w_j f_j behind it:
      dL/dalpha_i = sum_f v_f (f_i T_i - B_f / (1 - alpha_i)) + T_final / (1 - alpha_i) (v_alpha - v . bg)
      dL/dfeature_i = alpha_i T_i v;  alpha_i = min(0.99, o exp(-sigma)) gives zero gradient when clamped.
    """
    ntx = (width + TILE - 1) // TILE
    ntile = ntx * ((height + TILE - 1) // TILE)
    n_tiles, n_slices = tile_offsets.shape[0] - 1, acc.shape[0]
    # slice k takes tiles k, k + n_slices, ... in order: the sums do not depend on which thread ran what
    for k in prange(n_slices):
        # each slice zeroes its own rows (the caller passes np.empty), just before a tile may first touch them: a
        # tile adds only to rows <= the largest item index among its pairs, so rows z.. are zeroed up to there
        # when the tile comes. With the items in first-tile order (bin_and_pack) a row is thus zeroed shortly
        # before its first use, and its first add finds it in cache rather than where a zeroing pass over the
        # whole slice left it (docs/DECISIONS.md, "Numbers behind code comments", item order).
        z = 0
        for t in range(k, n_tiles, n_slices):
            start, end = tile_offsets[t], tile_end[t]
            if end == start:
                continue
            top = 0
            for j in range(start, end):
                top = max(top, pair_item[j] + 1)
            for i in range(z, top):
                for q in range(GROW + NF):
                    acc[k, i, q] = _F0
            z = max(z, top)
            px, py = np.empty(LANES, np.float32), np.empty(LANES, np.float32)
            inside = np.empty(LANES, np.bool_)
            c, x0, y0 = _tile_pixels(t, ntx, ntile, width, height, px, py, inside)
            T = np.ones(LANES, np.float32)
            t_fin = np.ones(LANES, np.float32)
            v_base = np.zeros(LANES, np.float32)  # v_alpha - v . bg
            vf = np.zeros((NF, LANES), np.float32)
            buf = np.zeros((NF, LANES), np.float32)
            for p in range(LANES):
                if inside[p]:
                    y, x = y0 + p // TILE, x0 + p % TILE
                    T[p] = out_t[c, y, x]
                    t_fin[p] = T[p]
                    vb = v_alpha[c, y, x]
                    for f in range(NF):
                        vf[f, p] = v_out[c, y, x, f]
                        vb -= vf[f, p] * backgrounds[c, f]
                    v_base[p] = vb
            for j in range(end - 1, start - 1, -1):
                m = masks[j]
                if m == 0:
                    continue
                row = pair_item[j]
                mx, my, a, b, cc = rows[j, 0], rows[j, 1], rows[j, 2], rows[j, 3], rows[j, 4]
                op = rows[j, 5]
                f0, f1, f2, f3 = rows[j, ROW], rows[j, ROW + 1], rows[j, ROW + 2], rows[j, ROW + 3]
                # only the tile rows where this pair was composited (unsigned lanes: see raster_fwd)
                r0, r1 = 0, TILE
                while (m >> np.uint64(r0 * TILE)) & np.uint64(255) == 0:
                    r0 += 1
                while (m >> np.uint64((r1 - 1) * TILE)) & np.uint64(255) == 0:
                    r1 -= 1
                g_mx, g_my, g_a, g_b, g_c, g_op, ab_x, ab_y = _F0, _F0, _F0, _F0, _F0, _F0, _F0, _F0
                g0, g1, g2, g3 = _F0, _F0, _F0, _F0
                for p in range(np.uint64(r0 * TILE), np.uint64(r1 * TILE)):
                    on = np.float32((m >> p) & np.uint64(1))
                    dx = mx - px[p]
                    dy = my - py[p]
                    s = max(_HALF * (a * dx * dx + cc * dy * dy) + b * dx * dy, _F0)
                    vis = fexp(-s)
                    raw = op * vis
                    alpha = min(_AMAX, raw) * on
                    rcp = _F1 / (_F1 - alpha)
                    Tp = T[p] * rcp  # transmittance in front of this Gaussian
                    T[p] = Tp
                    fac = alpha * Tp
                    v0, v1, v2, v3 = vf[0, p], vf[1, p], vf[2, p], vf[3, p]
                    va = t_fin[p] * rcp * v_base[p]
                    va += (f0 * Tp - buf[0, p] * rcp) * v0 + (f1 * Tp - buf[1, p] * rcp) * v1
                    va += (f2 * Tp - buf[2, p] * rcp) * v2 + (f3 * Tp - buf[3, p] * rcp) * v3
                    buf[0, p] += f0 * fac
                    buf[1, p] += f1 * fac
                    buf[2, p] += f2 * fac
                    buf[3, p] += f3 * fac
                    g0 += fac * v0
                    g1 += fac * v1
                    g2 += fac * v2
                    g3 += fac * v3
                    ga = va * on if raw <= _AMAX else _F0  # dL/dalpha, zero where the 0.99 clamp is active
                    g_op += vis * ga
                    vs = -op * vis * ga  # dL/dsigma
                    g_a += _HALF * vs * dx * dx
                    g_b += vs * dx * dy
                    g_c += _HALF * vs * dy * dy
                    gx = vs * (a * dx + b * dy)
                    gy = vs * (b * dx + cc * dy)
                    g_mx += gx
                    g_my += gy
                    ab_x += abs(gx)
                    ab_y += abs(gy)
                acc[k, row, 0] += g_mx
                acc[k, row, 1] += g_my
                acc[k, row, 2] += g_a
                acc[k, row, 3] += g_b
                acc[k, row, 4] += g_c
                acc[k, row, 5] += g_op
                acc[k, row, 6] += ab_x
                acc[k, row, 7] += ab_y
                acc[k, row, GROW] += g0
                acc[k, row, GROW + 1] += g1
                acc[k, row, GROW + 2] += g2
                acc[k, row, GROW + 3] += g3
        for i in range(z, acc.shape[1]):  # rows no tile of this slice touched
            for q in range(GROW + NF):
                acc[k, i, q] = _F0


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def reduce_items(acc, items, v_means2d, v_conics, v_opac, v_feat, absgrad):
    """Add the slices' item rows: acc [S, M, 8 + 4] -> v_means2d [C, N, 2], v_conics [C, N, 3],
    v_opac [C, N], v_feat [C, N, 4], absgrad [C, N, 2] (accumulated into, so channel groups can add up)."""
    N = v_opac.shape[1]
    M = items.shape[0]
    chunk = 1024
    for k in prange((M + chunk - 1) // chunk):
        s = np.empty(GROW + NF, np.float32)
        for i in range(k * chunk, min(M, (k + 1) * chunk)):
            c, n = items[i] // N, items[i] % N
            s[:] = _F0
            for th in range(acc.shape[0]):
                for q in range(GROW + NF):
                    s[q] += acc[th, i, q]
            v_means2d[c, n, 0] += s[0]
            v_means2d[c, n, 1] += s[1]
            v_conics[c, n, 0] += s[2]
            v_conics[c, n, 1] += s[3]
            v_conics[c, n, 2] += s[4]
            v_opac[c, n] += s[5]
            absgrad[c, n, 0] += s[6]
            absgrad[c, n, 1] += s[7]
            for f in range(NF):
                v_feat[c, n, f] = s[GROW + f]
