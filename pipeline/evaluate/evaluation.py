"""The evaluate stage: how good the trained model is, and how fast the job was.

- Held-out views are every 8th by sorted name (``pipeline.scene.split.split_views``, as in training), rendered
  at the training resolution with the water (what the camera would see) and scored against the photos:
  PSNR of the pooled MSE, SSIM (11x11 Gaussian window, σ 1.5), LPIPS-VGG only when local weights are
  configured (``pipeline.evaluate.perceptual``), else ``null`` with the reason.
- Where ground truth exists (a generated scene, ``pipeline.synth.ground_truth``), the model is rendered from the
  *true* cameras of the held-out views (carried into the model's world by the similarity that aligns the job's
  cameras to the true ones), because SfM's undistortion changes the image geometry: restored J against the
  true clean images (PSNR, SSIM), the photo itself against them (the baseline restoration starts from),
  the recovered β_D, β_B (1/m via the alignment's metres per scene unit) and B∞ against the truth, and the
  depth error after scale alignment (least-squares scale) and at the SfM alignment's scale.
- Per-stage wall times (the stage markers), training iterations/s and render milliseconds per view.
- The speed-vs-error curve recorded during training (the train stage's result, its history).
"""

from __future__ import annotations

import json
import logging
import math
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.evaluate.perceptual import LPIPSSetting, lpips_from_env, mean_lpips
from pipeline.job.layout import JobLayout
from pipeline.job.markers import read_marker
from pipeline.medium.fall_off import as_photographed
from pipeline.ops.metrics import (
    coefficient_error,
    mean_ssim,
    per_metre,
    pooled_psnr,
    scale_aligned_depth_error,
)
from pipeline.scene.align import align_to_reference, fit_similarity, view_in_estimated_frame
from pipeline.scene.images import write_image
from pipeline.scene.loader import load_scene, load_view_image
from pipeline.scene.records import View, scaled_view
from pipeline.scene.split import split_views
from pipeline.synth.ground_truth import FAR_DEPTH_M, SEEN_DEPTH_TOL, load_ground_truth
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.model import TrainedModel, model_from_state
from pipeline.train.photo_exposure import photo_fall_off, photo_gains
from pipeline.train.render import ViewOutputs, displayed, render_outputs

log = logging.getLogger(__name__)

ALPHA_VALID = 0.5  # pixels the model covers at least this much count for the depth error


@dataclass
class Rendered:
    view: View
    out: ViewOutputs
    ms: float  # wall milliseconds to render this view (Gaussians + medium)


def render_timed(model: TrainedModel, views: Sequence[View], backend: str = "auto") -> list[Rendered]:
    """Render every view once, timing each; one untimed warm-up render first (kernel caches, allocator)."""
    if views:
        render_outputs(model.gaussians, views[0], model.medium, model.sh_degree, backend, model.background)
    out = []
    for v in views:
        t0 = time.perf_counter()
        r = displayed(render_outputs(model.gaussians, v, model.medium, model.sh_degree, backend, model.background),
                      model.colour_space)
        out.append(Rendered(v, r, 1000.0 * (time.perf_counter() - t0)))
    return out


def image_scores(pairs: list[tuple[np.ndarray, np.ndarray]], lp: LPIPSSetting) -> dict[str, Any]:
    """PSNR (pooled MSE), mean SSIM and mean LPIPS (or None with the reason) of (prediction, target) pairs."""
    res: dict[str, Any] = {"psnr": pooled_psnr(pairs), "ssim": mean_ssim(pairs), "lpips": None,
                           "lpips_reason": lp.reason}
    if lp.model is not None:
        res["lpips"] = mean_lpips(lp.model, [(torch.as_tensor(p), torch.as_tensor(t)) for p, t in pairs])
    return res


def held_out_metrics(rendered: Sequence[Rendered], photos: Sequence[np.ndarray], lp: LPIPSSetting,
                     gains: dict[str, np.ndarray] | None = None, fall_off: np.ndarray | None = None
                     ) -> dict[str, Any]:
    """Held-out scores of the with-water render against the photos, pooled and per view; a view in ``gains``
    (log gains [3], :func:`pipeline.train.photo_exposure.photo_gains`) is rendered at its photo's exposure (the model is
    at the survey's mean), and with the survey's fall-off ``fall_off`` when training divided it out of the photos
    (:func:`pipeline.medium.fall_off.as_photographed`)."""
    gains = gains or {}
    pairs = [(np.clip(as_photographed(r.out.I, gains.get(r.view.name), fall_off), 0, 1).astype(np.float32)
              if r.view.name in gains or fall_off is not None else r.out.I, p)
             for r, p in zip(rendered, photos, strict=True)]
    per_view = [{"name": r.view.name, "psnr": pooled_psnr([pair]), "ssim": mean_ssim([pair]),
                 "render_ms": r.ms} for r, pair in zip(rendered, pairs, strict=True)]
    return {**image_scores(pairs, lp), "n_views": len(pairs), "views": [r.view.name for r in rendered],
            "compared": "model rendered with water vs the held-out photos" + (
                " (at each photo's exposure, measured against the model)" if gains else ""),
            "per_view": per_view}


def speed_vs_error(history: Sequence[dict], final_iteration: int, views: Sequence[str]) -> dict[str, Any]:
    """The training-time curve: points (iteration, elapsed_s, psnr), kept strictly increasing in time.

    Training appends a point at a fixed schedule and at the end; a point that does not advance the clock
    (none should) is dropped with a warning rather than drawn backwards.
    """
    points: list[dict[str, float]] = []
    for p in history:
        if points and p["elapsed_s"] <= points[-1]["elapsed_s"]:
            log.warning("speed-vs-error point at iteration %s does not advance time; dropped", p.get("iteration"))
            continue
        points.append({"iteration": int(p["iteration"]), "elapsed_s": float(p["elapsed_s"]), "psnr": float(p["psnr"])})
    return {"points": points, "views": list(views), "metric": "held-out PSNR with water (dB)",
            "time": "training seconds (optimisation steps only, summed across resumes)",
            "includes_final": bool(points) and points[-1]["iteration"] == final_iteration}


def stage_timings(job: Path, stages: Sequence[str]) -> dict[str, float | None]:
    """Wall seconds of each finished stage from its completion marker (None when it has not run)."""
    out: dict[str, float | None] = {}
    for s in stages:
        m = read_marker(job, s)
        out[s] = float(m["seconds"]) if m and "seconds" in m else None
    return out


def _depth_errors(rendered: Sequence[Rendered], truths: Sequence[np.ndarray], metres_per_unit: float) -> dict:
    preds = [r.out.depth for r in rendered]
    masks = [(r.out.alpha >= ALPHA_VALID) & (t < FAR_DEPTH_M) for r, t in zip(rendered, truths, strict=True)]
    if not any(bool((m & (p > 0)).any()) for p, m in zip(preds, masks, strict=True)):
        # A model that lost its scene renders no surface: that is a finding to report, not a crash.
        return {"scale_aligned": None, "at_alignment_scale": None, "units": "metres",
                "reason": f"the model covers no true surface pixel of the held-out views (alpha >= {ALPHA_VALID}): "
                          "no depth to compare"}
    res: dict[str, Any] = {"scale_aligned": scale_aligned_depth_error(preds, truths, masks)}
    p = np.concatenate([x[m] for x, m in zip(preds, masks, strict=True)]).astype(np.float64) * metres_per_unit
    g = np.concatenate([x[m] for x, m in zip(truths, masks, strict=True)]).astype(np.float64)
    ok = p > 0
    err = np.abs(p[ok] - g[ok])
    res["at_alignment_scale"] = {"abs_error_m": float(err.mean()), "rel_error": float((err / g[ok]).mean()),
                                 "n_pixels": int(ok.sum())}
    res["units"] = "metres; masks: model alpha >= 0.5 and a true surface"
    return res


def _coefficients(medium: dict, truth: dict, metres_per_unit: float) -> dict[str, Any] | None:
    """Recovered β_D, β_B (1/scene-unit -> 1/m) and B∞ against the truth; None without a medium."""
    if not medium or "beta_D" not in medium:
        return None
    return {
        "beta_D": coefficient_error(per_metre(medium["beta_D"], metres_per_unit), truth["beta_D"]),
        "beta_B": coefficient_error(per_metre(medium["beta_B"], metres_per_unit), truth["beta_B"]),
        "B_inf": coefficient_error(medium["B_inf"], truth["B_inf"]),
        "units": {"beta_D": "1/m", "beta_B": "1/m", "B_inf": "linear intensity [0, 1]"},
    }


def channel_bias(image: np.ndarray, clean: np.ndarray) -> list[float]:
    """Mean of ``image`` − ``clean`` per channel over the frame ([H, W, 3] each).  # [3]"""
    return [round(float(x), 4) for x in (np.asarray(image, np.float64) - clean).reshape(-1, 3).mean(0)]


def seen_scores(names: Sequence[str], restored: list[tuple[np.ndarray, np.ndarray]],
                photos: list[tuple[np.ndarray, np.ndarray]], seen: Sequence[np.ndarray]) -> dict[str, Any]:
    """Restored J and the photos against the clean images (``(image, clean)`` pairs) over only the pixels some
    training view saw (``GroundTruth.seen_by``), pooled and per view, with the share of pixels kept."""
    per_view = [{"name": n, "fraction": float(m.mean()), "restored_psnr": pooled_psnr([pair], [m]),
                 "input_psnr": pooled_psnr([photo], [m])}
                for n, pair, photo, m in zip(names, restored, photos, seen, strict=True)]
    return {"restored_psnr": pooled_psnr(restored, seen), "input_psnr": pooled_psnr(photos, seen),
            "fraction": float(np.mean([m.mean() for m in seen])), "per_view": per_view,
            "rule": f"pixels whose true surface point a training view sees (in frame, depth within "
                    f"{100 * SEEN_DEPTH_TOL:g} % of its true depth)"}


def restoration_metrics(job: Path, model: TrainedModel, test_names: Sequence[str], downscale: int, gt_root: Path,
                        lp: LPIPSSetting, backend: str = "auto") -> dict[str, Any]:
    """Restored J, coefficients and depth against a generated scene's truth (see the module docstring)."""
    layout = JobLayout(job)
    job_scene = load_scene(layout.scene)
    gt = load_ground_truth(gt_root, [v.name for v in job_scene.views])
    sim = fit_similarity(job_scene, gt.scene)
    alignment = align_to_reference(job_scene, gt.scene)
    true_views = {v.name: v for v in gt.scene.views}
    names = [n for n in test_names if n in true_views]
    if not names:
        raise ValueError(f"none of the held-out views {list(test_names)} is in the ground truth {gt_root}")
    views = [scaled_view(view_in_estimated_frame(true_views[n], sim), downscale) for n in names]
    trained = sorted(({v.name for v in job_scene.views} - set(test_names)) & true_views.keys())
    seen = gt.seen_by([scaled_view(true_views[n], downscale) for n in names], [true_views[t] for t in trained])
    rendered = render_timed(model, views, backend)
    save_renders(rendered, layout.true_camera)
    clean = [gt.clean(v) for v in views]
    photos = [gt.photo(v) for v in views]
    train = json.loads(layout.train_result.read_text())
    restored = [(r.out.J, c) for r, c in zip(rendered, clean, strict=True)]
    unrestored = list(zip(photos, clean, strict=True))
    return {
        "ground_truth": str(gt_root),
        "water_preset": gt.water.get("preset"),
        "views": names,
        "restored": image_scores(restored, lp),
        "input": image_scores(unrestored, lp),
        # Per view, so a restoration that fails on one view (a far oblique one) is not hidden by the pool.
        # and the mean error per channel (restored − truth): a veil left on, or taken off twice, is flat.
        "per_view": [{"name": n, "restored_psnr": pooled_psnr([r]), "input_psnr": pooled_psnr([u]),
                      "bias": channel_bias(*r)}
                     for n, r, u in zip(names, restored, unrestored, strict=True)],
        # The same over the pixels some training view saw: unseen seabed can only be invented, not restored.
        "seen": seen_scores(names, restored, unrestored, seen),
        # The model with water against the photos at the true cameras: close to the held-out score when the
        # cameras were carried over correctly (a check on the alignment, not a restoration score).
        "with_water": image_scores([(r.out.I, p) for r, p in zip(rendered, photos, strict=True)], lp),
        "metres_per_unit": sim.scale,
        "alignment": alignment,
        "coefficients": _coefficients(train.get("medium") or {}, gt.water, sim.scale),
        "depth": _depth_errors(rendered, [gt.depth(v) for v in views], sim.scale),
        "rendered_from": "the true cameras of the held-out views, mapped into the model's world",
    }


def save_renders(rendered: Sequence[Rendered], out: Path) -> None:
    """Write each render's with-water image and restored J as ``out/{with_water,restored}/<stem>.png`` (the
    report's side-by-side at the true cameras)."""
    for sub in ("with_water", "restored"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for r in rendered:
        stem = Path(r.view.name).stem
        write_image(out / "with_water" / f"{stem}.png", r.out.I)
        write_image(out / "restored" / f"{stem}.png", r.out.J)


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (JSON has no Infinity; PSNR of a perfect match is
    infinite), tuples as lists."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    return obj


def evaluate_job(job: str | Path, ground_truth: str | Path | None = None, stages: Sequence[str] = (),
                 backend: str = "auto") -> dict[str, Any]:
    """Score the job's trained model (``JobLayout.checkpoint``); returns the JSON-able evaluation.

    ``stages`` names the stages whose marker timings to collect (those before this one).
    """
    t0 = time.perf_counter()
    job = Path(job)
    layout = JobLayout(job)
    state = load_checkpoint(layout.checkpoint)
    model = model_from_state(state)
    down = int(state["config"].get("downscale", 1))
    _, test = split_views(load_scene(layout.scene).views)
    test = [scaled_view(v, down) for v in test]
    lp = lpips_from_env()
    rendered = render_timed(model, test, backend)
    gains = photo_gains(job)  # the held-out photos' exposure, measured against the model after training
    metrics = held_out_metrics(rendered, [load_view_image(v) for v in test], lp, gains, photo_fall_off(job)[0])
    train = json.loads(layout.train_result.read_text())
    restoration = None
    if ground_truth is not None:
        restoration = restoration_metrics(job, model, [v.name for v in test], down, Path(ground_truth), lp, backend)
    ms = [r.ms for r in rendered]
    elapsed = float(train.get("elapsed_s") or 0.0)
    res = {
        "mode": model.mode,
        "metrics": {"test": metrics},
        "restoration": restoration,
        "timings": {
            "stages_s": stage_timings(job, stages),
            "train_elapsed_s": elapsed,
            "train_iterations": int(train["iterations"]),
            "train_iterations_per_s": train["iterations"] / elapsed if elapsed > 0 else None,
            "render_ms_per_view": {"mean": statistics.fmean(ms), "median": statistics.median(ms), "n": len(ms),
                                   "width": test[0].camera.width, "height": test[0].camera.height},
        },
        "speed_vs_error": speed_vs_error(train.get("history", []), int(train["iterations"]),
                                         train.get("curve_views", metrics["views"])),
        "model": {"n_gaussians": int(model.gaussians["means"].shape[0]), "sh_degree": model.sh_degree,
                  "downscale": down, "iterations": int(train["iterations"]), "medium": train.get("medium") or None},
        "config": state["config"],
    }
    res["timings"]["evaluate_s"] = time.perf_counter() - t0
    _log_summary(res)
    return json_safe(res)


def _log_summary(res: dict) -> None:
    t = res["metrics"]["test"]
    r = res["restoration"]
    log.info("held-out PSNR %.2f dB SSIM %.3f over %d views%s", t["psnr"], t["ssim"], t["n_views"],
             "" if r is None else f"; restored J vs truth PSNR {r['restored']['psnr']:.2f} dB "
             f"(photo vs truth {r['input']['psnr']:.2f} dB; over the pixels a training view saw "
             f"{r['seen']['restored_psnr']:.2f} dB)")
    if not math.isfinite(t["psnr"]):
        log.warning("held-out PSNR is not finite (%s): the renders match the photos exactly?", t["psnr"])


__all__ = ["evaluate_job", "image_scores", "render_timed", "restoration_metrics", "speed_vs_error",
           "stage_timings", "held_out_metrics", "json_safe"]
