"""The restored photos against a generated scene's truth at full resolution (issue 14's acceptance measure).

Per photo, over the pixels whose true ray hits the seabed, three PSNRs against the true clean image in the
photo's own (distorted) geometry: the restored photo as the user gets it (the 8-bit file), the model's restored
render (what ``restored/`` held before: the training-resolution J) carried into the photo's geometry through the
same lens map and upsampled bilinearly, and the photo itself. And how well the edges line up: the sub-pixel
shift between each image's gradient magnitude and the truth's, by cross-correlation.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.job.layout import JobLayout
from pipeline.ops.metrics import pooled_psnr
from pipeline.restore.lens import LensGrid
from pipeline.restore.sample import sample_maps
from pipeline.scene.images import read_image
from pipeline.scene.records import Camera, LensCamera, View
from pipeline.scene.split import split_views
from pipeline.synth.ground_truth import FAR_DEPTH_M, load_ground_truth


def warp_to_photo(image: np.ndarray, camera: Camera, lens: LensCamera) -> np.ndarray:
    """``image`` [h, w, C] rendered in the PINHOLE ``camera`` carried into the photo's geometry: each photo pixel
    samples it bilinearly where its undistorted ray lands (edge pixels clamped; the restorer's own
    :func:`~pipeline.restore.sample.sample_maps`).  # [H, W, C] float32"""
    xn, yn = LensGrid(lens).rays(0, lens.height)
    return sample_maps(image, xn, yn, camera)[0]


MAX_OFFSET_PX = 8  # edge_offset searches shifts up to this many pixels (a misplaced photo is not "aligned")


def edge_offset(image: np.ndarray, reference: np.ndarray, max_shift: int = MAX_OFFSET_PX) -> float:
    """Length (pixels) of the shift that best aligns ``image``'s edges with ``reference``'s: cross-correlation of
    their gradient magnitudes (Hann-windowed), the peak searched within ``max_shift`` pixels of no shift and
    refined to sub-pixel by a parabola on each axis. A blurred image (a render upsampled) correlates weakly
    everywhere: without the search window its peak can land anywhere."""

    def edges(img: np.ndarray) -> np.ndarray:
        g = img.mean(axis=2) if img.ndim == 3 else img
        gy, gx = np.gradient(g.astype(np.float64))
        m = np.hypot(gx, gy)
        m -= m.mean()
        return m * np.outer(np.hanning(m.shape[0]), np.hanning(m.shape[1]))

    fa, fb = np.fft.rfft2(edges(image)), np.fft.rfft2(edges(reference))
    cross = fa * np.conj(fb)
    corr = np.fft.irfft2(cross, s=image.shape[:2])  # plain cross-correlation: a smooth peak a parabola fits
    H, W = corr.shape
    k = int(max_shift)
    window = np.roll(np.roll(corr, k, axis=0), k, axis=1)[:2 * k + 1, :2 * k + 1]  # shifts -k..k on each axis
    wy, wx = np.unravel_index(int(np.argmax(window)), window.shape)
    iy, ix = (wy - k) % H, (wx - k) % W

    def refine(c_m: float, c_0: float, c_p: float) -> float:
        d = c_m - 2 * c_0 + c_p
        return 0.0 if d == 0 else 0.5 * (c_m - c_p) / d

    dy = (wy - k) + refine(corr[(iy - 1) % H, ix], corr[iy, ix], corr[(iy + 1) % H, ix])
    dx = (wx - k) + refine(corr[iy, (ix - 1) % W], corr[iy, ix], corr[iy, (ix + 1) % W])
    return float(np.hypot(dx, dy))


def score_restored(job: Path, gt_root: Path, views: Sequence[View], lenses: dict[str, LensCamera],
                   files: dict[str, str], renders: dict[str, np.ndarray]) -> dict[str, Any]:
    """Scores of the restored photos (``files``: view name -> file name in ``restored/``) against the truth of
    ``gt_root``, per photo and pooled over the held-out and the training photos. ``renders``: view name -> the
    model's J as displayed ([h, w, 3] in the view's camera; what the restore stage rendered)."""
    layout = JobLayout(job)
    gt = load_ground_truth(gt_root, [v.name for v in views])
    truth_names = {v.name for v in gt.scene.views}
    _, test = split_views(list(views))
    test_names = {v.name for v in test}
    per_view, pools = [], {"test": [], "train": []}
    for v in views:
        if v.name not in truth_names or v.name not in files:
            continue
        truth = gt.clean_original(v.name)
        mask = gt.depth_original(v.name) < FAR_DEPTH_M
        restored = read_image(layout.restored / files[v.name])
        photo = read_image(layout.images / v.name)
        conf_path = layout.confidence / f"{Path(v.name).stem}.png"
        confidence = read_image(conf_path)[..., 0] if conf_path.is_file() else None
        render = warp_to_photo(renders[v.name], v.camera, lenses[v.name])
        row = {"name": v.name, "held_out": v.name in test_names,
               "restored_psnr": pooled_psnr([(restored, truth)], [mask]),
               "render_psnr": pooled_psnr([(render, truth)], [mask]),
               "photo_psnr": pooled_psnr([(photo, truth)], [mask]),
               "restored_offset_px": edge_offset(restored, truth), "render_offset_px": edge_offset(render, truth),
               "confidence_error_correlation": _correlation(confidence, np.abs(restored - truth).mean(-1), mask)}
        per_view.append(row)
        pools["test" if row["held_out"] else "train"].append((restored, render, photo, truth, mask))
    out: dict[str, Any] = {"compared": "the 8-bit restored files and the model's J render carried into each "
                                       "photo's geometry, against the true clean image, over the pixels whose "
                                       "true ray hits the seabed",
                           "ground_truth": str(gt_root), "per_view": per_view}
    for k, items in pools.items():
        if not items:
            out[k] = None
            continue
        masks = [m for *_, m in items]
        rows = [r for r in per_view if r["held_out"] == (k == "test")]
        out[k] = {"n": len(items),
                  "restored_psnr": pooled_psnr([(a, t) for a, _, _, t, _ in items], masks),
                  "render_psnr": pooled_psnr([(b, t) for _, b, _, t, _ in items], masks),
                  "photo_psnr": pooled_psnr([(p, t) for _, _, p, t, _ in items], masks),
                  "restored_offset_px": float(np.mean([r["restored_offset_px"] for r in rows])),
                  "render_offset_px": float(np.mean([r["render_offset_px"] for r in rows])),
                  "min_gain_over_render_db": float(min(r["restored_psnr"] - r["render_psnr"] for r in rows)),
                  "confidence_error_correlation": _mean([r["confidence_error_correlation"] for r in rows])}
    return out


def _correlation(confidence: np.ndarray | None, error: np.ndarray, mask: np.ndarray) -> float | None:
    """Pearson correlation of the confidence map and the restored photo's absolute error over the restored seabed
    pixels (confidence > 0): negative when low confidence marks where the restoration is wrong."""
    if confidence is None:
        return None
    m = mask & (confidence > 0)
    if m.sum() < 10 or confidence[m].std() == 0 or error[m].std() == 0:
        return None
    return float(np.corrcoef(confidence[m], error[m])[0, 1])


def _mean(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None
