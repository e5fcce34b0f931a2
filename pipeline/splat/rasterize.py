"""The one entry point of the rendering engine: ``rasterize`` (paper eqs. 1-2), with selectable backends.

Backends (docs/DECISIONS.md, "Rendering engine"):
- ``torch``: the reference (``_torch_ref``), slow and obvious, autograd-differentiable, any device.
- ``cpu``: the fast one (``_cpu_backend``): numba kernels with a hand-written backward, CPU tensors only.
  numba is imported and its kernels are compiled (or loaded from the on-disk cache) on first use.
- ``cuda``: gsplat's CUDA rasterizer (``_cuda_backend``), only with CUDA tensors on a CUDA machine.
- ``auto``: ``cuda`` for CUDA tensors when CUDA is available, else ``cpu`` for CPU tensors, else ``torch``.

All backends return gsplat's output layout, so ``gsplat.strategy.DefaultStrategy`` drives densification for each.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from pipeline.splat import _cpu_backend, _cuda_backend, _torch_ref

logger = logging.getLogger(__name__)

RENDER_MODES = ("RGB", "RGB+ED", "ED")
BACKENDS = ("auto", "torch", "cpu", "cuda")


def rasterize(
    means: Tensor,  # [N, 3] world positions
    quats: Tensor,  # [N, 4] wxyz, not necessarily normalised
    scales: Tensor,  # [N, 3] activated (positive)
    opacities: Tensor,  # [N] activated, in (0, 1)
    colors: Tensor,  # [N, D], or SH coefficients [N, K, 3] when sh_degree is given
    viewmats: Tensor,  # [C, 4, 4] cam_from_world
    Ks: Tensor,  # [C, 3, 3] pinhole intrinsics
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    sh_rest: Tensor | None = None,  # [N, K - 1, 3] higher SH bands, colors then being the DC band [N, 1, 3]
    backgrounds: Tensor | None = None,  # [C, D]
    render_mode: str = "RGB",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    backend: str = "auto",
    absgrad: bool = False,
) -> tuple[Tensor, Tensor, dict]:
    """Render N 3D Gaussians into C pinhole cameras, front to back (3DGS, Kerbl et al. 2023, eqs. 1-2).

    Returns ``(render_colors [C, H, W, X], render_alphas [C, H, W, 1], info)`` where X is D for "RGB", D + 1 for
    "RGB+ED" (last channel: expected camera-space depth, the alpha-normalised sum of w_i z_i), 1 for "ED".
    ``backgrounds`` are added as T_final * bg to the colour channels (never to depth).

    With ``sh_degree`` the colours are SH coefficients evaluated per camera along the camera-to-mean direction,
    then ``max(rgb + 0.5, 0)`` (3DGS / gsplat). ``sh_rest`` passes the bands above the DC term apart, as the
    Gaussians keep them (``sh0`` and ``shN``): the coefficients are ``colors`` and ``sh_rest`` concatenated. The
    ``cpu`` backend reads the two as they are (no copy of both a step, nor a split of their gradient); the others
    concatenate them here. ``absgrad`` also fills ``info["means2d"].absgrad`` on backward
    (gsplat's option for ``DefaultStrategy(absgrad=True)``).

    ``info`` (gsplat's keys): ``means2d`` [C, N, 2] pixels (``retain_grad`` called, so ``.grad`` is filled by
    backward), ``radii`` [C, N, 2] int32 (0 = culled), ``depths`` [C, N], ``conics`` [C, N, 3], ``opacities``
    [C, N], ``gaussian_ids``/``camera_ids``/``batch_ids`` None (not packed), ``width``, ``height``,
    ``n_cameras``, ``tile_size``, ``backend``.

    >>> import torch
    >>> q = torch.tensor([[1.0, 0, 0, 0]])
    >>> K = torch.tensor([[[32.0, 0, 16], [0, 32, 12], [0, 0, 1]]])
    >>> img, alpha, info = rasterize(torch.tensor([[0.0, 0, 2]]), q, torch.full((1, 3), 0.1),
    ...     torch.tensor([0.9]), torch.ones(1, 3), torch.eye(4)[None], K, 32, 24, backend="torch")
    >>> img.shape, alpha.shape, round(float(alpha.max()), 2)  # peak 0.9 * exp(-sigma) half a pixel off the mean
    (torch.Size([1, 24, 32, 3]), torch.Size([1, 24, 32, 1]), 0.82)
    """
    _check_call(means, quats, scales, opacities, colors, sh_rest, viewmats, Ks, width, height, sh_degree, backgrounds,
                render_mode)
    name = _resolve_backend(backend, means)
    if sh_rest is not None and name != "cpu":  # the other backends read the coefficients whole
        colors, sh_rest = torch.cat([colors, sh_rest], dim=1), None
    if name == "cuda":
        return _cuda_backend.rasterize(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            sh_degree=sh_degree, backgrounds=backgrounds, render_mode=render_mode,
            near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, absgrad=absgrad,
        )  # fmt: skip
    C = viewmats.shape[0]
    with_colors = render_mode in ("RGB", "RGB+ED")
    with_depth = render_mode in ("ED", "RGB+ED")
    bg = _feature_backgrounds(backgrounds, C, with_colors, with_depth, means)  # [C, F] or None
    impl = _cpu_backend if name == "cpu" else _torch_ref
    apart = {} if sh_rest is None else {"sh_rest": sh_rest}  # only the cpu backend keeps one (concatenated above)
    img, alpha, info = impl.render(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        sh_degree=sh_degree, backgrounds=bg, with_colors=with_colors, with_depth=with_depth,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, absgrad=absgrad, **apart,
    )  # fmt: skip
    if with_depth:  # expected depth = sum(w z) / sum(w), as gsplat's "ED"
        img = torch.cat([img[..., :-1], img[..., -1:] / alpha.clamp_min(1e-10)], dim=-1)
    _complete_info(info, opacities, C, width, height, impl.TILE_SIZE, name)
    return img, alpha, info


def _check_call(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, sh_rest: Tensor | None,
    viewmats: Tensor, Ks: Tensor, width: int, height: int, sh_degree: int | None, backgrounds: Tensor | None,
    render_mode: str,
) -> None:
    """Raise ValueError for the first bad argument of :func:`rasterize` (with ``sh_rest``, the coefficients are
    checked as ``colors`` and ``sh_rest`` together)."""
    shaped = colors  # what the checks read: with sh_rest, a free view shaped as all the coefficients
    if sh_rest is not None:
        _check_sh_rest(colors, sh_rest, sh_degree)
        shaped = colors.expand(-1, 1 + sh_rest.shape[1], -1)
    _check_inputs(means, quats, scales, opacities, shaped, viewmats, Ks, width, height, sh_degree, backgrounds)
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")


def _complete_info(info: dict, opacities: Tensor, C: int, width: int, height: int, tile_size: int,
                   backend: str) -> None:
    """Fill ``info`` with the rest of gsplat's keys (unpacked), and make ``means2d`` keep its gradient."""
    means2d = info["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    info.update(
        opacities=opacities[None].expand(C, -1),
        gaussian_ids=None,
        camera_ids=None,
        batch_ids=None,
        width=width,
        height=height,
        n_cameras=C,
        tile_size=tile_size,
        backend=backend,
    )


def _resolve_backend(backend: str, means: Tensor) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        if means.is_cuda and torch.cuda.is_available():
            return "cuda"
        return "cpu" if means.device.type == "cpu" else "torch"
    if backend == "cpu" and means.device.type != "cpu":
        raise ValueError(f"backend 'cpu' needs CPU tensors, got device {means.device}")
    if backend == "cuda" and not (means.is_cuda and torch.cuda.is_available()):
        raise ValueError(f"backend 'cuda' needs CUDA tensors on a CUDA machine, got device {means.device}")
    return backend


def _check_sh_rest(colors: Tensor, sh_rest: Tensor, sh_degree: int | None) -> None:
    """Raise ValueError unless ``colors`` is an SH DC band [N, 1, 3] and ``sh_rest`` its higher bands [N, K - 1, 3]
    on the same device (their band count against sh_degree is checked by _check_inputs)."""
    if sh_degree is None:
        raise ValueError("sh_rest needs sh_degree: it holds the SH bands above the DC term")
    n = colors.shape[0]
    if colors.ndim != 3 or tuple(colors.shape[1:]) != (1, 3):
        raise ValueError(f"with sh_rest, colors must be the SH DC band [N, 1, 3], got {tuple(colors.shape)}")
    if sh_rest.ndim != 3 or sh_rest.shape[0] != n or sh_rest.shape[2] != 3 or sh_rest.device != colors.device:
        raise ValueError(f"sh_rest must be [N, K - 1, 3] with N={n} on {colors.device}, got {tuple(sh_rest.shape)} "
                         f"on {sh_rest.device}")


def _feature_backgrounds(
    backgrounds: Tensor | None, C: int, with_colors: bool, with_depth: bool, ref: Tensor
) -> Tensor | None:
    """Backgrounds for the rendered feature channels [C, F]: colour channels get ``backgrounds``, depth gets 0."""
    if backgrounds is None:
        return None
    parts = []
    if with_colors:
        parts.append(backgrounds)
    if with_depth:
        parts.append(torch.zeros(C, 1, dtype=ref.dtype, device=ref.device))
    return torch.cat(parts, dim=-1)


def _check_inputs(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    sh_degree: int | None,
    backgrounds: Tensor | None,
) -> None:
    """Raise ValueError naming the first bad shape, dtype, device or size."""
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    N = means.shape[0]
    expect = {"quats": (quats, (N, 4)), "scales": (scales, (N, 3)), "opacities": (opacities, (N,))}
    for name, (t, shape) in expect.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must be {list(shape)} for N={N}, got {tuple(t.shape)}")
    if sh_degree is None:
        if colors.ndim != 2 or colors.shape[0] != N:
            raise ValueError(f"colors must be [N, D] with N={N} (no sh_degree), got {tuple(colors.shape)}")
    else:
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        k = (sh_degree + 1) ** 2
        if colors.ndim != 3 or colors.shape[0] != N or colors.shape[2] != 3 or colors.shape[1] < k:
            raise ValueError(
                f"colors must be SH coefficients [N, K>={k}, 3] for sh_degree={sh_degree}, N={N}, "
                f"got {tuple(colors.shape)}"
            )
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or viewmats.shape[0] < 1:
        raise ValueError(f"viewmats must be [C, 4, 4] with C >= 1, got {tuple(viewmats.shape)}")
    C = viewmats.shape[0]
    if tuple(Ks.shape) != (C, 3, 3):
        raise ValueError(f"Ks must be [C, 3, 3] for C={C}, got {tuple(Ks.shape)}")
    D = colors.shape[-1] if sh_degree is None else 3
    if backgrounds is not None and tuple(backgrounds.shape) != (C, D):
        raise ValueError(f"backgrounds must be [C, D] = [{C}, {D}], got {tuple(backgrounds.shape)}")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"width and height must be positive integers, got {width}x{height}")
    tensors = [means, quats, scales, opacities, colors, viewmats, Ks]
    if backgrounds is not None:
        tensors.append(backgrounds)
    if any(t.device != means.device for t in tensors):
        raise ValueError(f"all tensors must be on one device, got {sorted({str(t.device) for t in tensors})}")
    if any(not t.is_floating_point() for t in tensors):
        raise ValueError(f"all tensors must be floating point, got {sorted({str(t.dtype) for t in tensors})}")
