"""The report's pictures as PNG bytes: the speed-vs-error curve and colour-mapped or plain images.

matplotlib (the ``report`` extra) is imported inside the functions, with the non-interactive Agg backend, so
importing this module costs nothing and never opens a display.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np

from pipeline.scene.images import PNG_COMPRESSION_LEVEL


def _pyplot():
    import matplotlib  # lazy: the optional `report` extra; importing this module costs nothing

    matplotlib.use("Agg", force=True)  # no display: workers and CI have none
    import matplotlib.pyplot as plt

    return plt


def speed_vs_error_png(points: Sequence[dict], title: str = "speed against error") -> bytes:
    """Held-out PSNR (dB) against training seconds, one marker per evaluation, iterations annotated. -> PNG"""
    plt = _pyplot()
    t = [p["elapsed_s"] for p in points]
    y = [p["psnr"] for p in points]
    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    try:
        ax.plot(t, y, "o-", color="#1f6f8b", lw=1.5, ms=4)
        for p in points[-1:]:
            ax.annotate(f"it {p['iteration']}: {p['psnr']:.2f} dB", (p["elapsed_s"], p["psnr"]),
                        textcoords="offset points", xytext=(-8, -14), ha="right", fontsize=8)
        ax.set_xlabel("training time (s)")
        ax.set_ylabel("held-out PSNR with water (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
    finally:
        plt.close(fig)
    return buf.getvalue()


def image_png(img: np.ndarray, cmap: str | None = None, vmin: float | None = None,
              vmax: float | None = None) -> bytes:
    """An [H, W, 3] image in [0, 1] as PNG, or an [H, W] map through ``cmap`` over [vmin, vmax]. -> PNG"""
    import matplotlib.image as mpimg  # lazy: the optional `report` extra

    if img.ndim == 3:
        img = np.clip(img, 0.0, 1.0)
    elif img.ndim != 2:
        raise ValueError(f"image_png expects [H, W, 3] or [H, W], got {img.shape}")
    buf = io.BytesIO()
    mpimg.imsave(buf, img, format="png", cmap=cmap, vmin=vmin, vmax=vmax,
                 pil_kwargs={"compress_level": PNG_COMPRESSION_LEVEL})
    return buf.getvalue()


__all__ = ["image_png", "speed_vs_error_png"]
