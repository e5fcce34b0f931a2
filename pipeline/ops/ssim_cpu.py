"""SSIM on the CPU as one operator: numba kernels forward and a closed-form backward (``_ssim_kernels``).

The training step's SSIM was torch's: five depthwise convolutions forward and three more backward, with ~30
element-wise ops around them; compiled with the medium's losses it still cost ~6.4 ms of a ~100 ms step at 320x240
(the convolutions are mkldnn calls inductor cannot fuse), eager in the coarse start ~7 ms at 160x120. The kernels
do the same arithmetic in ~2.3 ms forward and backward together at 320x240; in the compiled graph the step's SSIM
costs ~3.2 ms (docs/DECISIONS.md, "Whole-job speed", session 25).

``ssim_planes`` is a ``torch.library`` custom operator with its own autograd formula, so a ``torch.compile``d
loss graph keeps it as one opaque call instead of breaking around the numba code. Its twin is
:func:`pipeline.ops.image_losses.ssim_map` (torch), which tests hold it against, forward and backward.
Registering the two operators at import defines them and runs nothing; numba loads on the first call.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from pipeline.splat._cpu_backend import pin_threading_layer


def _kernels():
    pin_threading_layer()  # SSIM may be the first parallel numba call of a process (evaluation)
    from pipeline.ops import _ssim_kernels  # lazy: imports numba and loads (or compiles) the kernels

    return _ssim_kernels


@torch.library.custom_op("dualphys::ssim_planes", mutates_args=())
def _ssim_fwd(x: Tensor, y: Tensor, g: Tensor, c1: float, c2: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(mean SSIM [], ∂s/∂μx, ∂s/∂E[x²], ∂s/∂E[xy] [P, H, W]) of planes x, y [P, H, W] (contiguous), window g."""
    k = _kernels()
    xn, yn, gn = x.detach().numpy(), y.detach().numpy(), g.detach().numpy()
    m1, m2, m3 = (torch.empty_like(x) for _ in range(3))
    rowsum = np.empty(x.shape[:2], np.float64)
    k.ssim_fwd(xn, yn, gn, gn.dtype.type(c1), gn.dtype.type(c2), m1.numpy(), m2.numpy(), m3.numpy(), rowsum)
    mean = torch.tensor(rowsum.sum() / max(1, x.numel()), dtype=x.dtype)
    return mean, m1, m2, m3


@_ssim_fwd.register_fake
def _(x: Tensor, y: Tensor, g: Tensor, c1: float, c2: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    return x.new_empty(()), torch.empty_like(x), torch.empty_like(x), torch.empty_like(x)


@torch.library.custom_op("dualphys::ssim_planes_backward", mutates_args=())
def _ssim_bwd(grad: Tensor, x: Tensor, y: Tensor, g: Tensor, m1: Tensor, m2: Tensor, m3: Tensor) -> Tensor:
    """dL/dx [P, H, W] from dL/d(mean SSIM) ``grad`` [] and the forward's saved maps."""
    k = _kernels()
    dx = torch.empty_like(x)
    gn = g.detach().numpy()
    scale = gn.dtype.type(float(grad) / max(1, x.numel()))
    k.ssim_bwd(x.detach().numpy(), y.detach().numpy(), gn, m1.numpy(), m2.numpy(), m3.numpy(), scale, dx.numpy())
    return dx


@_ssim_bwd.register_fake
def _(grad: Tensor, x: Tensor, y: Tensor, g: Tensor, m1: Tensor, m2: Tensor, m3: Tensor) -> Tensor:
    return torch.empty_like(x)


def _setup_context(ctx, inputs, output) -> None:  # noqa: ANN001  (torch.library's signature)
    x, y, g, _, _ = inputs
    _, m1, m2, m3 = output
    ctx.save_for_backward(x, y, g, m1, m2, m3)
    ctx.mark_non_differentiable(m1, m2, m3)


def _backward(ctx, grad, *_maps):  # noqa: ANN001, ANN202
    x, y, g, m1, m2, m3 = ctx.saved_tensors
    return _ssim_bwd(grad, x, y, g, m1, m2, m3), None, None, None, None


_ssim_fwd.register_autograd(_backward, setup_context=_setup_context)


def ssim_planes(x: Tensor, y: Tensor, g: Tensor, c1: float, c2: float) -> Tensor:
    """Mean SSIM of planes x, y [P, H, W] (float32 or float64, CPU; each plane one channel of one image) with the
    separable window g [S] (S odd, symmetric: ``image_losses.gaussian_window_1d``), zero-padded, and the
    stabilisers c1, c2. Differentiable in x only (y is the target: ``image_losses.ssim`` sends a y that needs a
    gradient to the torch twin). → []"""
    if x.shape != y.shape or x.dim() != 3 or x.dtype != y.dtype or g.dtype != x.dtype or g.dim() != 1 \
            or g.shape[0] % 2 != 1:
        raise ValueError(f"ssim_planes needs two [P, H, W] tensors of one shape and dtype and an odd window [S] "
                         f"of that dtype, got {tuple(x.shape)} {x.dtype}, {tuple(y.shape)} {y.dtype}, "
                         f"{tuple(g.shape)} {g.dtype}")
    return _ssim_fwd(x.contiguous(), y.contiguous(), g.contiguous(), c1, c2)[0]


def compile_ssim_kernels() -> float:
    """Call both kernels once (forward and backward of a small image), so they compile into numba's on-disk cache
    before the first job (``dualphys warmup``); returns the seconds it took."""
    t0 = time.perf_counter()
    x = torch.rand(3, 16, 24, requires_grad=True)
    ssim_planes(x, torch.rand(3, 16, 24), torch.full((11,), 1 / 11), 1e-4, 9e-4).backward()
    return round(time.perf_counter() - t0, 2)
