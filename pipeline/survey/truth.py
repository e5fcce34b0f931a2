"""The survey products against a generated scene's truth: the scale against the true one, the orthomosaic against
the true seabed colour on the same grid, its planimetric error, and the elevation model's error.

The job's world maps to the truth's (metres) by the similarity of the camera centres (:mod:`pipeline.scene.align`):
its scale is the true metres per scene unit. A grid cell's seabed point (x, y and the DEM's height) is carried into
the truth's world; the generator's surface there (:func:`pipeline.synth.survey_truth.true_surface`) gives the true
height below/above it and the true water-free colour (the colour its clean images show). The planimetric error is
the shift between the mosaic and the true colours rendered on the same cells, by phase correlation on patches (the
checkpoints); the elevation error is the vertical distance, in the truth's frame, from the DEM's points to the
true surface.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import rasterio
from rasterio.windows import Window

from pipeline.job.layout import JobLayout
from pipeline.ops.metrics import psnr as psnr_db
from pipeline.scene.align import fit_similarity
from pipeline.scene.records import Scene
from pipeline.survey.measure import SurveyGeometry
from pipeline.survey.surface import MapGrid
from pipeline.survey.terrain import rugosity
from pipeline.synth.ground_truth import load_ground_truth
from pipeline.synth.survey_truth import load_surface_truth

MAX_SCORED = 2048  # cells per side scored (a central window of larger grids)
PATCH = 64  # checkpoint patch side, cells
MIN_PATCH_VALID = 0.9


def _read(path: Path, window: Window) -> np.ndarray:
    with rasterio.open(path) as ds:
        return np.moveaxis(ds.read(window=window), 0, -1)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB, peak 1) of two colour arrays of the same cells."""
    return psnr_db(float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


def phase_shift(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The (row, col) shift of ``b`` relative to ``a`` (two equal grey patches), by phase correlation with a
    parabolic sub-cell peak."""
    win = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    fa, fb = np.fft.fft2((a - a.mean()) * win), np.fft.fft2((b - b.mean()) * win)
    r = fb * np.conj(fa)
    corr = np.real(np.fft.ifft2(r / np.maximum(np.abs(r), 1e-12)))
    k = np.array(np.unravel_index(np.argmax(corr), corr.shape))
    shift = k.astype(np.float64)
    for ax in (0, 1):
        n = corr.shape[ax]
        idx = [k[0], k[1]]
        idx[ax] = (k[ax] - 1) % n
        lo = corr[tuple(idx)]
        idx[ax] = (k[ax] + 1) % n
        hi = corr[tuple(idx)]
        c = corr[tuple(k)]
        den = lo - 2 * c + hi
        if abs(den) > 1e-12:
            shift[ax] += 0.5 * (lo - hi) / den
    return np.where(shift > np.array(corr.shape) / 2, shift - np.array(corr.shape), shift)


def planimetric_errors(mosaic: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> list[float]:
    """Shift magnitudes (cells) of the checkpoint patches whose cells are nearly all valid."""
    grey_m, grey_t = mosaic.mean(-1), truth.mean(-1)
    out = []
    for r in range(0, mosaic.shape[0] - PATCH + 1, PATCH):
        for c in range(0, mosaic.shape[1] - PATCH + 1, PATCH):
            sl = (slice(r, r + PATCH), slice(c, c + PATCH))
            if valid[sl].mean() < MIN_PATCH_VALID or grey_t[sl].std() < 0.02:
                continue
            out.append(float(np.linalg.norm(phase_shift(grey_t[sl], grey_m[sl]))))
    return out


def score_products(job: Path, gt_root: Path, geom: SurveyGeometry, grid: MapGrid, scene: Scene) -> dict:
    layout = JobLayout(job)
    gt = load_ground_truth(gt_root, [v.name for v in scene.views])
    sim = fit_similarity(scene, gt.scene)
    scale = geom.scale.metres_per_unit
    out: dict = {"true_metres_per_unit": sim.scale,
                 "scale_error": None if scale is None else scale / sim.scale - 1}
    if gt.water.get("family") != "photo":  # the procedural family's seabed has no grid lookup: the scale only
        out["note"] = "the true seabed on a grid is known for photo-family scenes only: products not scored"
        return out
    h, w = min(grid.height, MAX_SCORED), min(grid.width, MAX_SCORED)
    r0, c0 = (grid.height - h) // 2, (grid.width - w) // 2
    win = Window(c0, r0, w, h)
    dem = _read(layout.dem, win)[..., 0].astype(np.float64)
    x, y = grid.centres(r0, r0 + h, c0, c0 + w)
    seen = np.isfinite(dem)
    world = geom.frame.to_world(np.stack([x[seen], y[seen], dem[seen]], 1))
    p = sim.scale * world @ sim.R.T + sim.t  # the truth's world, metres
    truth = load_surface_truth(gt.scene_root or gt_root)
    z_true, _ = truth.at(p[:, 0], p[:, 1])
    _, colour = truth.at(p[:, 0], p[:, 1], cell=grid.gsd * sim.scale / geom.frame.scale)  # a cell's mean colour
    err = p[:, 2] - z_true
    range_m = float(np.median(list(geom.distances.values()))) * sim.scale
    # the DEM's shape alone: its offset and tilt against the true surface (what the camera alignment leaves,
    # a similarity's remaining freedom for a surface) fitted away by least squares
    design = np.stack([np.ones(len(err)), p[:, 0] - p[:, 0].mean(), p[:, 1] - p[:, 1].mean()], 1)
    shape_err = err - design @ np.linalg.lstsq(design, err, rcond=None)[0]
    out["elevation"] = {"rmse_m": float(np.sqrt(np.mean(err**2))), "bias_m": float(np.mean(err)),
                        "median_abs_m": float(np.median(np.abs(err))),
                        "median_abs_share_of_range": float(np.median(np.abs(err)) / (np.median(
                            list(geom.distances.values())) * sim.scale)),
                        "camera_to_bottom_m": range_m,
                        "rmse_share_of_range": float(np.sqrt(np.mean(err**2)) / range_m), "cells": int(seen.sum()),
                        "aligned_rmse_m": float(np.sqrt(np.mean(shape_err**2))),
                        "aligned_rmse_share_of_range": float(np.sqrt(np.mean(shape_err**2)) / range_m)}
    true_dem = np.full((h, w), np.nan)
    true_dem[seen] = z_true  # the true surface under the same cells: what the DEM's rugosity should be
    out["terrain"] = {"rugosity": rugosity(dem, grid.gsd), "rugosity_true": rugosity(true_dem, grid.gsd)}
    truth_img = np.zeros((h, w, 3))
    truth_img[seen] = colour
    for key, path in (("restored", layout.ortho), ("water", layout.ortho_water)):
        if not path.is_file():
            continue
        img = _read(path, win)[..., :3].astype(np.float64) / 255.0
        valid = seen & (_read(layout.ortho_confidence, win)[..., 0] > 0) if key == "restored" else seen
        shifts = planimetric_errors(img, truth_img, valid)
        out[key] = {"psnr": psnr(img[valid], truth_img[valid]), "cells": int(valid.sum()),
                    "checkpoints": len(shifts),
                    "planimetric_px_median": float(np.median(shifts)) if shifts else None,
                    "planimetric_px_max": float(np.max(shifts)) if shifts else None}
    rest = json.loads(layout.restore_result.read_text()) if layout.restore_result.is_file() else {}
    per_view = [v["restored_psnr"] for v in (rest.get("truth") or {}).get("per_view", [])]
    photos = float(np.mean(per_view)) if per_view else None  # the mosaic is made of all of them
    out["restored_photos_psnr"] = photos
    if photos is not None and "restored" in out:
        out["ortho_minus_photos_db"] = out["restored"]["psnr"] - photos
    return out


__all__ = ["phase_shift", "planimetric_errors", "psnr", "score_products"]
