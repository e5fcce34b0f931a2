"""The job's report: ``report.json`` (schema ``pipeline/data/report.schema.json``, documented in docs/REPORT.md)
and a self-contained ``report.html`` (every picture embedded as a ``data:`` URI), both in the job's output folder.

Built at the end of the export stage from what the stages wrote (paths in :class:`pipeline.job.layout.JobLayout`):
the options, the classifier's decision, the train stage's result and, with ``--mode auto``, its selection, the
evaluation and its true-camera renders, and the export's images.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.evaluate.evaluation import json_safe, stage_timings
from pipeline.evaluate.plots import image_png, speed_vs_error_png
from pipeline.export.report_html import render_html
from pipeline.export.report_survey import survey_pictures
from pipeline.job.layout import RENDER_FOLDERS, JobLayout
from pipeline.job.markers import atomic_write_json, atomic_write_text, read_marker
from pipeline.job.table import STAGES
from pipeline.ops.metrics import per_metre
from pipeline.scene.images import read_image, resize_area_to
from pipeline.scene.loader import load_scene, load_view_image
from pipeline.scene.records import scaled_view
from pipeline.scene.split import split_views
from pipeline.synth.ground_truth import load_ground_truth

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
SCHEMA_FILE = Path(__file__).resolve().parents[1] / "data" / "report.schema.json"
MAX_VIEWS_SHOWN = 6  # held-out views pictured in the HTML (all are scored)
MAX_PHOTOS_SHOWN = 4  # restored photos pictured (held-out first; 5 pictures each, at up to SHOWN_WIDTH)


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text()) if path.is_file() else None


def selection_of(job: Path, options: dict, mode: str) -> dict[str, Any]:
    """What mode was chosen and why: the selection (written by ``--mode auto``: ``requested``,
    ``chosen``, ``reason``, the probe's numbers) when present, with ``mode`` = the chosen mode; else the mode
    the user asked for."""
    sel = _read_json(JobLayout(job).selection)
    if isinstance(sel, dict) and ("chosen" in sel or "mode" in sel):
        return {"reason": "chosen automatically", **sel, "mode": sel.get("chosen", sel.get("mode"))}
    return {"mode": mode, "requested": options.get("mode", mode), "reason": "requested by the user"}


def water_coefficients(medium: dict | None, metres_per_unit: float | None) -> dict[str, Any] | None:
    """Each learned water coefficient with the sparse-point measurement it was held to and that measurement's
    uncertainty (σ of its log, or logit for B∞) and source: ``measured`` (the data pinned it), ``prior`` (the
    data could not: the classified water type's value), ``measured+prior``; or the fallback when the points
    could not measure the water at all. None without a medium."""
    if not medium or "beta_D" not in medium:
        return None
    est = medium.get("estimate")
    unc = (est or {}).get("uncertainty") or {}
    out: dict[str, Any] = {}
    for k in ("beta_D", "beta_B", "B_inf"):
        entry: dict[str, Any] = {
            "learned": medium[k], "units": "1/scene-unit" if k != "B_inf" else "linear intensity",
            "measured": est.get(k) if est else None,
            "sigma": unc.get(k, {}).get("sigma"), "data_sigma": unc.get(k, {}).get("data_sigma"),
            "source": unc.get(k, {}).get("source") or (
                None if est else ["not measured (too few points seen twice): grey-world prior"] * 3),
            "sigma_scale": (unc.get("scale") or {}).get(k)}
        if metres_per_unit and k != "B_inf":
            entry["learned_per_metre"] = per_metre(medium[k], metres_per_unit)
        out[k] = entry
    out["prior"] = unc.get("prior")
    out["failed"] = unc.get("failed")  # per channel: why the points' fit was not a measurement (None: it was)
    return out


def fall_off_of(train: dict) -> dict[str, Any] | None:
    """The photos' in-frame fall-off the sparse points' fit measured beside the exposure
    (:mod:`pipeline.medium.exposure_gains`): its brightest over its darkest value over the frame and its log
    field's coefficients, and whether training and the restored photos had it divided out
    (:mod:`pipeline.medium.fall_off`; None: a job from before that was decided). None where it was not measured
    (no medium, or a job from before it was)."""
    est = (train.get("medium") or {}).get("estimate") or {}
    if est.get("field_span") is None:
        return None
    decided = (train.get("exposure") or {}).get("fall_off") or {}
    return {"span": est["field_span"], "log_field": est.get("exposure_field"),
            "terms": "x, y, x², y², xy over half-widths / half-heights from the frame's centre; grey",
            "removed": decided.get("removed"), "reason": decided.get("reason")}


def quality_of(train: dict) -> dict[str, Any] | None:
    """Did the model keep its scene (``pipeline.train.quality``, measured by the train stage), and was it recovered
    from a collapse (``pipeline.train.guard``)? None for jobs trained before the check existed."""
    q = train.get("quality")
    if not isinstance(q, dict):
        return None
    return {**q, "recovery": train.get("recovery")}


def build_report(job: str | Path, export_s: float | None = None) -> dict[str, Any]:
    """The report.json content of a job whose evaluate stage has run (``export_s``: the export stage's seconds
    so far, as its marker is not written yet)."""
    job = Path(job)
    layout = JobLayout(job)
    ev = _read_json(layout.evaluate)
    if ev is None:
        raise FileNotFoundError(f"{layout.evaluate} is missing: run the evaluate stage first")
    options = _read_json(layout.options) or {}
    stages = stage_timings(job, [s for s in STAGES if s != "export"])
    stages["export"] = export_s
    timings = {k: v for k, v in ev["timings"].items() if k != "stages_s"}
    timings.update(stages_s=stages, total_s=sum(v for v in stages.values() if v is not None))
    restoration = ev.get("restoration")
    survey = _read_json(layout.survey_result)
    scale, scale_source = metric_scale_of(restoration, survey, options)
    model = {**ev["model"], "metres_per_unit": scale, "metres_per_unit_source": scale_source}
    medium = model.get("medium")
    if medium and scale:
        model["medium_per_metre"] = {"beta_D": per_metre(medium["beta_D"], scale),
                                     "beta_B": per_metre(medium["beta_B"], scale), "B_inf": medium["B_inf"],
                                     "units": "1/m (B_inf: linear intensity)"}
    model["water_coefficients"] = water_coefficients(medium, scale)
    train = _read_json(layout.train_result) or {}
    restore = _read_json(layout.restore_result)
    water = layout.classify_written  # a job folder from before the classifier's file was renamed: the legacy one
    report = {
        "schema_version": SCHEMA_VERSION,
        "created_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "job": {"name": job.resolve().name, "options": options},
        "water": _read_json(water) if water is not None else None,
        "mode": ev["mode"],
        "preset": options.get("preset", ""),
        "selection": selection_of(job, options, ev["mode"]),
        "quality": quality_of(train),
        "schedule": train.get("schedule"),  # None for jobs trained before schedules followed the survey
        "exposure": train.get("exposure"),  # each training view's learned gains; None: not learned
        "fall_off": fall_off_of(train),
        "metrics": ev["metrics"],
        "restoration": restoration,
        "timings": timings,
        "speed_vs_error": {**ev["speed_vs_error"],
                           "plot": layout.curve_png.name if ev["speed_vs_error"]["points"] else None},
        "model": model,
        "config": ev.get("config", {}),
        "outputs": {f: sum(1 for p in layout.render_folder(f).glob("*.png")) for f in RENDER_FOLDERS
                    if layout.render_folder(f).is_dir()},
        "restore": None if restore is None else {k: v for k, v in restore.items() if k != "consistency"},
        "consistency": consistency_of(restore),  # restore.json's, lifted to the top
        "input": input_summary(job, options),
        "sfm": sfm_summary(job),
        "survey": survey,  # survey.json: scale, frame, products (None: a job from before the survey stage)
    }
    return json_safe(relative_paths(report, job))


def metric_scale_of(restoration: dict | None, survey: dict | None, options: dict) -> tuple[float | None, str | None]:
    """Metres per scene unit and where it came from: a generated scene's truth (the alignment to its true cameras,
    so its water is compared in 1/m exactly), else the survey's measured scale (altimeter, scale bar, metric_scale
    or GPS: :mod:`pipeline.survey.scale`), else ``metric_scale`` as given."""
    if restoration and restoration.get("metres_per_unit"):
        return restoration["metres_per_unit"], "ground truth (alignment to the true cameras)"
    fit = (survey or {}).get("scale") or {}
    if fit.get("metres_per_unit"):
        return fit["metres_per_unit"], fit.get("source")
    if options.get("metric_scale"):
        return options["metric_scale"], "metric_scale"
    return None, None


def consistency_of(restore: dict | None) -> dict[str, Any]:
    """The restored photos' colour consistency across distances (``pipeline.restore.consistency``, computed by
    the restore stage into restore.json), or an undefined block saying why there is none."""
    if restore is None:
        why = "the job has no restored photos (it ran before the restore stage existed)"
    elif restore.get("restored", 0) == 0:
        why = restore.get("note") or "no photo was restored"
    elif isinstance(restore.get("consistency"), dict):
        return restore["consistency"]
    else:
        why = "the restore stage ran before the score existed (re-run it to compute it)"
    return {"defined": False, "reason": why}


SFM_FIELDS = ("registered", "total", "mean_reproj_error_px", "num_points3D", "matcher", "pairs_matched", "loop_pairs",
              "outcome", "other_models", "unregistered", "dropped", "retries")


def input_summary(job: Path, options: dict) -> dict[str, Any]:
    """What went in: the input's name (the ``name`` of the service's ``JobLayout.source_name`` when it wrote one,
    e.g. the uploaded file's name; else the source's own name), the images ingest kept and the files it skipped."""
    layout = JobLayout(job)
    ingested = _read_json(layout.ingest) or {}
    named = _read_json(layout.source_name) or {}
    name = named.get("name") or Path(str(options.get("source", "") or ingested.get("source", ""))).name
    return {"name": name or None, "images": len(ingested.get("images", [])) if ingested else None,
            "skipped": len(ingested.get("skipped", [])) if ingested else None}


def sfm_summary(job: Path) -> dict[str, Any] | None:
    """The SfM stage's summary from its completion marker: registered / total images, mean reprojection error,
    points, matcher (None when the stage has not run)."""
    marker = read_marker(job, "sfm")
    result = (marker or {}).get("result") or {}
    return {k: result.get(k) for k in SFM_FIELDS} if result else None


def relative_paths(value: Any, job: Path) -> Any:
    """``value`` with every absolute path string made relative to the job folder (or cut to its own name when it
    lies outside, e.g. ``dualphys run``'s input): the report travels to the service's clients, who must never
    see the server's file system."""
    if isinstance(value, dict):
        return {k: relative_paths(v, job) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [relative_paths(v, job) for v in value]
    if isinstance(value, str) and value.startswith("/") and "\n" not in value:
        path, base = Path(value), job.resolve()
        try:
            return path.resolve().relative_to(base).as_posix()
        except (ValueError, OSError):
            return path.name
    return value


def validate_report(report: dict) -> None:
    """Raise ``jsonschema.ValidationError`` when ``report`` does not follow the schema (jsonschema is a dev
    dependency: the pipeline itself never needs it)."""
    import jsonschema  # lazy: a dev dependency (the pipeline never validates)

    jsonschema.validate(report, json.loads(SCHEMA_FILE.read_text()))


@dataclass
class Pictures:
    """The HTML's embedded pictures as PNG bytes."""

    views: list[tuple[str, list[tuple[str, bytes]]]]  # per held-out view: (name, [(label, png)])
    maps: list[tuple[str, list[tuple[str, bytes]]]]  # per held-out view: A, B, depth
    curve: bytes | None
    # per shown photo: (name, [(label, png)]): the photo and its restored copy side by side, their confidence,
    # and the same crop of both at full resolution
    originals: list[tuple[str, list[tuple[str, bytes]]]] = field(default_factory=list)
    survey: list[tuple[str, bytes]] = field(default_factory=list)  # the survey products' previews, (label, png)


SHOWN_WIDTH = 560  # px: the side-by-side photo and restored copy in report.html
CROP = 224  # px: the full-resolution crop shown beside them


def original_pictures(job: Path, report: dict) -> list[tuple[str, list[tuple[str, bytes]]]]:
    """Photo | restored at a useful size, the confidence map, and a CROP x CROP crop of both at full resolution
    (centred on the photo's most detailed restored area), for the held-out photos first."""
    layout = JobLayout(job)
    rest = report.get("restore") or {}
    done = [v["name"] for v in rest.get("views", [])]
    test = report["metrics"]["test"]["views"]
    names = ([n for n in test if n in done] + [n for n in done if n not in test])[:MAX_PHOTOS_SHOWN]
    out = []
    for n in names:
        photo_path, restored_path = layout.images / n, layout.restored / next(
            (v["file"] for v in rest["views"] if v["name"] == n), n)
        if not (photo_path.is_file() and restored_path.is_file()):
            continue
        photo, restored = read_image(photo_path), read_image(restored_path)
        conf_path = layout.confidence / f"{Path(n).stem}.png"
        conf = read_image(conf_path)[..., 0] if conf_path.is_file() else None
        H, W = photo.shape[:2]
        w = min(W, SHOWN_WIDTH)
        h = max(1, round(H * w / W))

        def small(img, h=h, w=w):
            return img if img.shape[:2] == (h, w) else resize_area_to(img, (h, w))

        y, x = _crop_corner(photo, conf, CROP)
        cells = [(f"photo ({W}x{H})", image_png(small(photo))), ("restored", image_png(small(restored)))]
        if conf is not None:
            cells.append(("confidence (white: full; black: not restored)", image_png(small(conf), "gray", 0, 1)))
        cells += [(f"photo, {CROP}x{CROP} crop at full resolution", image_png(photo[y:y + CROP, x:x + CROP])),
                  ("restored, same crop", image_png(restored[y:y + CROP, x:x + CROP]))]
        out.append((n, cells))
    return out


def _crop_corner(photo: np.ndarray, conf: np.ndarray | None, size: int) -> tuple[int, int]:
    """Top-left corner of the size x size window with the most image detail (gradient energy) among restored
    pixels (confidence > 0: reconstructed surface), on a coarse grid of candidate windows; the centre when the
    photo is smaller than the window."""
    H, W = photo.shape[:2]
    if H <= size or W <= size:
        return 0, 0
    g = photo.mean(axis=2)
    detail = np.abs(np.diff(g, axis=0))[:, :-1] + np.abs(np.diff(g, axis=1))[:-1, :]
    if conf is not None:
        detail = detail * (conf[:-1, :-1] > 0)
    ii = np.pad(detail.astype(np.float64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))  # integral image
    ys = np.arange(0, H - size, max(size // 2, 1))
    xs = np.arange(0, W - size, max(size // 2, 1))
    m = size - 1
    energy = ii[ys[:, None] + m, xs[None, :] + m] - ii[ys[:, None], xs[None, :] + m] \
        - ii[ys[:, None] + m, xs[None, :]] + ii[ys[:, None], xs[None, :]]
    i, j = np.unravel_index(int(np.argmax(energy)), energy.shape)
    corner = (int(ys[i]), int(xs[j]))
    return corner


def collect_pictures(job: Path, report: dict) -> Pictures:
    """Side-by-side with-water / restored / ground truth per held-out view and its A / B / depth maps."""
    layout = JobLayout(job)
    out = layout.render_folder
    names = report["metrics"]["test"]["views"][:MAX_VIEWS_SHOWN]
    down = int(report["model"].get("downscale", 1))
    rest = report["restoration"]
    views = []
    restored = report["mode"] != "3dgs"  # 3dgs models no water: its "restored" image is the model, not a restoration
    if rest is not None:  # the true cameras: photo, model, restored and truth share one geometry
        # the report names the ground truth without its server path; evaluate.json has the real one
        gt = load_ground_truth(((_read_json(layout.evaluate) or {}).get("restoration") or {}).get(
            "ground_truth", rest["ground_truth"]), rest["views"])
        true_views = {v.name: scaled_view(v, down) for v in gt.scene.views}
        for n in (n for n in names if n in rest["views"]):
            v, stem = true_views[n], Path(n).stem
            cells = [("photo", image_png(gt.photo(v))),
                     ("model, with water", (layout.true_camera / "with_water" / f"{stem}.png").read_bytes()),
                     ("restored J", (layout.true_camera / "restored" / f"{stem}.png").read_bytes()),
                     ("ground truth J", image_png(gt.clean(v)))]
            cells = [c for c in cells if restored or c[0] != "restored J"]
            views.append((n, cells))
    else:
        _, test = split_views(load_scene(layout.scene).views)
        by_name = {v.name: scaled_view(v, down) for v in test}
        for n in (n for n in names if n in by_name):
            stem = Path(n).stem
            views.append((n, [("photo", image_png(load_view_image(by_name[n]))),
                              ("model, with water", (out("with_water") / f"{stem}.png").read_bytes())]
                          + ([("restored J", (out("restored") / f"{stem}.png").read_bytes())] if restored else [])))
    maps = []
    depths = {n: np.load(out("depth") / f"{Path(n).stem}.npy") for n in names
              if (out("depth") / f"{Path(n).stem}.npy").is_file()}
    zmax = max((float(d.max()) for d in depths.values()), default=1.0) or 1.0
    for n in names:
        stem, cells = Path(n).stem, []
        for folder, label in (("attenuation", "attenuation A"), ("backscatter", "backscatter B")):
            if (out(folder) / f"{stem}.png").is_file():
                cells.append((label, image_png(read_image(out(folder) / f"{stem}.png"))))
        if n in depths:
            cells.append((f"depth (0-{zmax:.3g} scene units)", image_png(depths[n], "viridis", 0.0, zmax)))
        if cells:
            maps.append((n, cells))
    points = report["speed_vs_error"]["points"]
    curve = speed_vs_error_png(points) if points else None
    return Pictures(views, maps, curve, original_pictures(job, report), survey_pictures(job))


def write_report(job: str | Path, out: str | Path | None = None, export_s: float | None = None) -> list[Path]:
    """Write report.json, report.html and the curve's PNG into ``out`` (default: the job's output folder, where
    they have the names of ``JobLayout``); returns the paths written."""
    t0 = time.perf_counter()
    job = Path(job)
    layout = JobLayout(job)
    out = Path(out) if out is not None else layout.output
    out.mkdir(parents=True, exist_ok=True)
    report_json, report_html, curve_png = (out / p.name for p in (layout.report_json, layout.report_html,
                                                                  layout.curve_png))
    report = build_report(job, export_s)
    pictures = collect_pictures(job, report)
    written = [atomic_write_json(report_json, report)]
    if pictures.curve is not None:
        curve_png.write_bytes(pictures.curve)
        written.append(curve_png)
    written.append(atomic_write_text(report_html, render_html(report, pictures)))
    log.info("report written to %s (%.1f s)", report_html, time.perf_counter() - t0)
    return written


__all__ = ["SCHEMA_FILE", "SCHEMA_VERSION", "build_report", "selection_of", "validate_report", "write_report"]
