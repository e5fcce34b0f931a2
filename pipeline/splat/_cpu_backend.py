"""The ``cpu`` backend: numba kernels with hand-written backward, wrapped in two autograd Functions.

    _Project  (means, quats, scales, [SH DC band, higher bands]) -> means2d, conics, depths, [SH colours]
                                                                                  (+ radii, sort keys)
    _Raster   (means2d, conics, opacities, features, backgrounds) -> image, alpha

The split mirrors gsplat, so ``means2d`` is a real node of the graph and ``info["means2d"].grad`` is filled by
backward (DefaultStrategy reads it). numba is imported, and the kernels compiled or loaded from the on-disk
cache (``cache=True``), on the first call, never at import; ``raster_bwd`` always compiles (3-5 s), so every
process runs the same code (``_cpu_raster_kernels``' docstring). Kernels use numba's thread pool (all cores by default,
``NUMBA_NUM_THREADS`` to change), with dynamic scheduling so both cores stay busy when other jobs interfere.

The thread pool is OpenMP (or numba's own workqueue where OpenMP is missing), never TBB, whatever the machine
has installed: numba prefers TBB when ``libtbb`` is present, and TBB's work stealing changes the order of the
kernels' float sums from run to run, so a resumed training would no longer be the run it resumes
(:func:`pin_threading_layer`; issue 13). ``NUMBA_THREADING_LAYER`` set explicitly still wins.
"""

from __future__ import annotations

import logging
import os

import numpy as np
import torch
from torch import Tensor

from pipeline.profiling import section
from pipeline.splat._constants import CPU_TILE
from pipeline.splat._torch_ref import alpha_thresholds

logger = logging.getLogger(__name__)

TILE_SIZE = CPU_TILE
_TILE_CHUNK = 4  # tiles per dynamically scheduled work item of the compositing kernels
BWD_SLICES = 4  # the backward's accumulator slices (_cpu_raster_kernels, step 3): fixed, not the thread count,
#                 so a run repeats bit for bit whatever the schedule (its cost: docs/DECISIONS.md, "Rendering engine")


_announced = False
# numba takes the first layer of this permutation that loads; workqueue always loads, so TBB is never reached
DETERMINISTIC_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


def pin_threading_layer() -> None:
    """Make numba pick OpenMP or workqueue rather than TBB for the kernels (module docstring), unless the user
    chose a layer with ``NUMBA_THREADING_LAYER`` / ``NUMBA_THREADING_LAYER_PRIORITY``. Must run before numba
    starts its thread pool (the first parallel kernel call of the process); later it changes nothing."""
    import numba  # lazy: numba (~0.4 s) loads with the first kernel call, never at import

    if os.environ.get("NUMBA_THREADING_LAYER") or os.environ.get("NUMBA_THREADING_LAYER_PRIORITY"):
        return
    numba.config.THREADING_LAYER = "default"
    numba.config.THREADING_LAYER_PRIORITY = list(DETERMINISTIC_LAYER_PRIORITY)


def _kernels():
    """The numba kernel modules (imported on first use; each kernel compiles, or loads from the on-disk cache,
    at its first call)."""
    global _announced
    if not _announced:
        pin_threading_layer()
    from pipeline.splat import _cpu_project_kernels, _cpu_raster_kernels  # lazy: numba, kernels load or compile

    if not _announced:
        _announced = True
        logger.info("cpu rasterizer: numba kernels load from cache or compile now (~30-60 s when uncached, 3-5 s "
                    "cached: raster_bwd always compiles)")
    return _cpu_project_kernels, _cpu_raster_kernels


def _dynamic_schedule(chunk: int = 1):
    """numba's dynamic scheduling for the kernels' parallel loops: a thread that the OS pauses (other jobs share
    our 2 cores) does not hold up the others at the end of a static block."""
    import numba  # lazy: numba (~0.4 s) loads with the first kernel call, never at import

    return numba.parallel_chunksize(chunk)


def _np(t: Tensor) -> np.ndarray:
    """A C-contiguous numpy view (or copy) of a CPU tensor, without grad."""
    return t.detach().contiguous().numpy()


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh0, shN, viewmats, Ks, width, height, sh_degree, eps2d,
                near_plane, far_plane):  # fmt: skip
        # means [N, 3], quats [N, 4], scales [N, 3], opacities [N], sh0 [N, 1, 3] and shN [N, K - 1, 3] the SH
        # bands as the Gaussians keep them (both [N, 0, 3] without SH), viewmats [C, 4, 4], Ks [C, 3, 3]
        pk, _ = _kernels()
        C, N = viewmats.shape[0], means.shape[0]
        f32 = dict(dtype=torch.float32)
        means2d, conics = torch.empty(C, N, 2, **f32), torch.empty(C, N, 3, **f32)
        depths = torch.empty(C, N, **f32)
        radii = torch.empty(C, N, 2, dtype=torch.int32)
        keys = torch.empty(C, N, dtype=torch.float64)
        deg = -1 if sh_degree is None else sh_degree
        colors = torch.empty(C, N if deg >= 0 else 0, 3, **f32)
        with _dynamic_schedule(), section("raster: project fwd"):
            pk.project_fwd(
                _np(means), _np(quats), _np(scales), _np(opacities), _np(sh0), _np(shN), deg, _np(viewmats), _np(Ks),
                width, height, eps2d, near_plane, far_plane,
                means2d.numpy(), conics.numpy(), depths.numpy(), radii.numpy(), keys.numpy(), colors.numpy(),
            )  # fmt: skip
        ctx.save_for_backward(means, quats, scales, sh0, shN, viewmats, Ks, radii)
        ctx.cfg = (width, height, deg, eps2d)
        ctx.mark_non_differentiable(radii, keys)
        return means2d, conics, depths, colors, radii, keys

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, v_colors, _v_radii, _v_keys):
        pk, _ = _kernels()
        means, quats, scales, sh0, shN, viewmats, Ks, radii = ctx.saved_tensors
        width, height, deg, eps2d = ctx.cfg
        C, N = viewmats.shape[0], means.shape[0]

        def grad_or_zeros(g, shape):
            return _np(g) if g is not None else np.zeros(shape, np.float32)

        f32 = dict(dtype=torch.float32)
        v_means, v_quats, v_scales = torch.empty(N, 3, **f32), torch.empty(N, 4, **f32), torch.empty(N, 3, **f32)
        v_sh0, v_shN = torch.empty(sh0.shape, **f32), torch.empty(shN.shape, **f32)
        with _dynamic_schedule(), section("raster: project bwd"):
            pk.project_bwd(
                _np(means), _np(quats), _np(scales), _np(sh0), _np(shN), deg, _np(viewmats), _np(Ks), width, height,
                eps2d,
                _np(radii), grad_or_zeros(v_means2d, (C, N, 2)), grad_or_zeros(v_conics, (C, N, 3)),
                grad_or_zeros(v_depths, (C, N)), grad_or_zeros(v_colors, (C, N if deg >= 0 else 0, 3)),
                v_means.numpy(), v_quats.numpy(), v_scales.numpy(), v_sh0.numpy(), v_shN.numpy(),
            )  # fmt: skip
        sh_grads = (v_sh0, v_shN) if deg >= 0 else (None, None)
        return (v_means, v_quats, v_scales, None, *sh_grads) + (None,) * 8


class _Raster(torch.autograd.Function):
    """Compositing of F feature channels, in groups of ``NF`` = 4 (the kernels' fixed slot count).

    Groups after the first reuse the binning and rerun the kernels with other feature slots; the backward adds
    their geometric gradients (dL/dalpha is linear in the per-pixel cotangents, so per-group sums add up), with
    the alpha-output cotangent counted in the first group only.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, backgrounds, radii, depth_keys, width, height, absgrad):
        with section("raster: composite fwd"):
            return _Raster._forward(ctx, means2d, conics, opacities, features, backgrounds, radii, depth_keys,
                                    width, height, absgrad)  # fmt: skip

    @staticmethod
    def _forward(ctx, means2d, conics, opacities, features, backgrounds, radii, depth_keys, width, height, absgrad):
        # means2d [C, N, 2], conics [C, N, 3], opacities [N], features [C, N, F], backgrounds [C, F],
        # radii [C, N, 2] int32, depth_keys [C, N] float64
        _, rk = _kernels()
        import numba  # lazy: numba (~0.4 s) loads with the first kernel call, never at import

        C, N, F = features.shape
        NF = rk.NF
        groups = max(1, -(-F // NF))
        feats = _pad_channels(features.detach(), groups * NF).reshape(C, N, groups, NF)
        bgs = _pad_channels(backgrounds.detach(), groups * NF).reshape(C, groups, NF)
        thresholds = alpha_thresholds(opacities)  # the reference's exact float32 thresholds
        with _dynamic_schedule(), section("raster: bin (in composite fwd)"):
            rows, tile_offsets, items, pair_item = rk.bin_and_pack(
                _np(means2d), _np(conics), _np(opacities), _np(thresholds), _np(feats[:, :, 0]), _np(radii),
                _np(depth_keys), width, height, 4 * numba.get_num_threads(),
            )  # fmt: skip
        out = torch.empty(C, height, width, groups * NF, dtype=torch.float32)
        out_t = torch.empty(C, height, width, dtype=torch.float32)
        masks = np.zeros(rows.shape[0], np.uint64)
        tile_end = np.empty(tile_offsets.shape[0] - 1, np.int64)
        group_rows = []
        for g in range(groups):
            rows_g = rows if g == 0 else rk.repack_features(rows, pair_item, items, _np(feats[:, :, g]))
            out_g = np.empty((C, height, width, NF), np.float32)
            with _dynamic_schedule(_TILE_CHUNK):
                rk.raster_fwd(rows_g, tile_offsets, width, height, _np(bgs[:, g]), out_g, out_t.numpy(), masks,
                              tile_end)  # fmt: skip
            out[..., g * NF : (g + 1) * NF] = torch.from_numpy(out_g)
            group_rows.append(rows_g)
        ctx.save_for_backward(means2d, out_t)
        ctx.state = (group_rows, bgs, tile_offsets, tile_end, masks, items, pair_item)
        ctx.cfg = (C, N, F, width, height, absgrad)
        img = out if F == groups * NF else out[..., :F].contiguous()
        return img, (1.0 - out_t)[..., None]

    @staticmethod
    def backward(ctx, v_out, v_alpha):
        with section("raster: composite bwd"):
            return _Raster._backward(ctx, v_out, v_alpha)

    @staticmethod
    def _backward(ctx, v_out, v_alpha):
        _, rk = _kernels()

        means2d, out_t = ctx.saved_tensors
        group_rows, bgs, tile_offsets, tile_end, masks, items, pair_item = ctx.state
        C, N, F, width, height, absgrad = ctx.cfg
        NF = rk.NF
        groups = len(group_rows)
        f32 = torch.float32
        v_out = v_out if v_out is not None else torch.zeros(C, height, width, F, dtype=f32)
        v_out = _pad_channels(v_out, groups * NF).reshape(C, height, width, groups, NF)
        v_alpha = v_alpha[..., 0] if v_alpha is not None else torch.zeros(C, height, width, dtype=f32)
        v_means2d, v_conics = torch.zeros(C, N, 2, dtype=f32), torch.zeros(C, N, 3, dtype=f32)
        v_opac, abs_g = torch.zeros(C, N, dtype=f32), torch.zeros(C, N, 2, dtype=f32)
        v_feat = torch.zeros(C, N, groups * NF, dtype=f32)
        v_feat_g = np.empty((C, N, NF), np.float32)
        for g in range(groups):
            acc = np.empty((BWD_SLICES, items.shape[0], rk.GROW + NF), np.float32)  # raster_bwd zeroes it
            v_alpha_g = v_alpha if g == 0 else torch.zeros_like(v_alpha)
            with _dynamic_schedule():
                rk.raster_bwd(group_rows[g], tile_offsets, tile_end, masks, pair_item, width, height,
                              _np(bgs[:, g]), out_t.numpy(), _np(v_out[..., g, :]), _np(v_alpha_g), acc)  # fmt: skip
            v_feat_g[:] = 0.0
            with _dynamic_schedule():
                rk.reduce_items(acc, items, v_means2d.numpy(), v_conics.numpy(), v_opac.numpy(), v_feat_g,
                                abs_g.numpy())  # fmt: skip
            v_feat[..., g * NF : (g + 1) * NF] = torch.from_numpy(v_feat_g)
        if absgrad:
            means2d.absgrad = abs_g
        v_bg = None
        if ctx.needs_input_grad[4]:
            v_bg = (out_t[..., None] * v_out.reshape(C, height, width, -1)[..., :F]).sum(dim=(1, 2))
        return v_means2d, v_conics, v_opac.sum(0), v_feat[..., :F], v_bg, None, None, None, None, None


def _pad_channels(x: Tensor, n: int) -> Tensor:
    """Zero-pad the last dimension to n channels: [..., F] -> [..., n] float32 (a copy only if needed)."""
    x = x.to(torch.float32)
    if x.shape[-1] == n:
        return x
    return torch.cat([x, x.new_zeros(*x.shape[:-1], n - x.shape[-1])], dim=-1)


def render(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D] or [N, K, 3] (or the DC band [N, 1, 3] with sh_rest)
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int | None,
    sh_rest: Tensor | None = None,  # [N, K - 1, 3] the higher SH bands, kept apart from colors' DC band
    backgrounds: Tensor | None,  # [C, F] already matching the rendered features
    with_colors: bool,
    with_depth: bool,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    absgrad: bool,
) -> tuple[Tensor, Tensor, dict]:
    """Same contract as ``_torch_ref.render`` (with ``sh_rest``: its SH coefficients are colors and sh_rest
    concatenated, which the kernels read apart); float32 throughout (inputs are cast)."""
    f32 = torch.float32
    means, quats, scales, opacities, colors = (t.to(f32) for t in (means, quats, scales, opacities, colors))
    viewmats, Ks = viewmats.to(f32), Ks.to(f32)
    C, N = viewmats.shape[0], means.shape[0]
    use_sh = with_colors and sh_degree is not None
    if not use_sh:
        sh0 = shN = torch.zeros(N, 0, 3, dtype=f32)
    elif sh_rest is not None:
        sh0, shN = colors, sh_rest.to(f32)
    else:
        sh0, shN = colors[:, :1], colors[:, 1:]
    means2d, conics, depths, sh_colors, radii, keys = _Project.apply(
        means, quats, scales, opacities, sh0, shN, viewmats, Ks, width, height,
        sh_degree if use_sh else None, float(eps2d), float(near_plane), float(far_plane),
    )  # fmt: skip
    feats = []
    if with_colors:
        feats.append(sh_colors if use_sh else colors[None].expand(C, -1, -1))
    if with_depth:
        feats.append(depths[..., None])
    features = feats[0] if len(feats) == 1 else torch.cat(feats, dim=-1)  # [C, N, F]
    bg = backgrounds.to(f32) if backgrounds is not None else torch.zeros(C, features.shape[-1], dtype=f32)
    img, alpha = _Raster.apply(means2d, conics, opacities, features, bg, radii, keys, width, height, absgrad)
    info = {"means2d": means2d, "radii": radii, "depths": depths, "conics": conics}
    return img, alpha, info
