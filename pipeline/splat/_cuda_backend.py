"""The ``cuda`` backend: a thin adapter to ``gsplat.rasterization`` for CUDA tensors on GPU workers.

Only reached when ``torch.cuda.is_available()`` and the tensors are on CUDA (``rasterize`` checks both), so the
import of gsplat (whose CUDA extension JIT-builds on first use) never happens on CPU machines. Untestable on our
CPU-only machines; kept to argument plumbing.

Known differences from the ``torch``/``cpu`` backends (gsplat's kernel, not ours): alpha is capped at 0.999
instead of 3DGS's 0.99, a pixel stops at T <= 1e-4 instead of T < 1e-4, and 16x16 tiles.
"""

from __future__ import annotations

from torch import Tensor

TILE_SIZE = 16


def rasterize(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D] or [N, K, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int | None,
    backgrounds: Tensor | None,  # [C, D]
    render_mode: str,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    absgrad: bool,
) -> tuple[Tensor, Tensor, dict]:
    """gsplat's rasterization, not packed (means2d [C, N, 2] as the other backends), classic 3DGS mode."""
    from gsplat.rendering import rasterization  # lazy: its CUDA extension builds on first use

    img, alpha, info = rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, packed=False,
        tile_size=TILE_SIZE, backgrounds=backgrounds, render_mode=render_mode, absgrad=absgrad,
        rasterize_mode="classic",
    )  # fmt: skip
    if info["means2d"].requires_grad:
        info["means2d"].retain_grad()
    info["backend"] = "cuda"
    return img, alpha, info
