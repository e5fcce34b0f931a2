"""The survey stage: the metric scale from the survey's records, the map frame (UTM when GPS fits), and the
products (orthomosaics with and without water, confidence, elevation model) -> ``JobLayout.survey`` and
``JobLayout.survey_result``.

Nothing here fails a job on a measurement that can be wrong: a scale source that disagrees, a GPS track that does
not fit, a scale bar off the surface are warnings in survey.json, and the products fall back (another scale
source, a local frame, scene units).
"""

from __future__ import annotations

import json
import logging
import resource
import time
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from pipeline.job.options import JobOptions, StageContext
from pipeline.restore.views import lens_cameras
from pipeline.scene.images import list_images
from pipeline.scene.loader import load_scene
from pipeline.scene.records import scaled_view
from pipeline.survey.measure import measure_survey, resolve_telemetry
from pipeline.survey.products import NoSurfaceError, make_products
from pipeline.survey.records import frame_records
from pipeline.survey.truth import score_products
from pipeline.synth.ground_truth import find_ground_truth
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.model import model_from_state

log = logging.getLogger(__name__)


def _restored_files(layout: JobLayout) -> dict[str, str]:
    """Image name -> its restored file's name (restore.json), empty in mode 3dgs or before restore."""
    if not layout.restore_result.is_file():
        return {}
    res = json.loads(layout.restore_result.read_text())
    return {v["name"]: v["file"] for v in res.get("views", []) if (layout.restored / v["file"]).is_file()}


def stage_survey(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    t0 = time.perf_counter()
    layout = JobLayout(job)
    state = load_checkpoint(layout.checkpoint)
    model = model_from_state(state)
    scene = load_scene(layout.scene)
    down = int(state["config"].get("downscale", 1))
    views = [scaled_view(v, down) for v in scene.views]
    lenses = lens_cameras(layout.scene)
    images = {p.name: p for p in list_images(layout.images)}
    warnings = []
    try:
        telemetry = resolve_telemetry(opts, layout.records)
    except FileNotFoundError as e:  # the survey's EXIF may still hold what is needed: said, not fatal
        telemetry = None
        warnings.append(f"{e}; read the photos' EXIF only")
    try:
        records = frame_records({v.name: images[v.name] for v in views if v.name in images}, telemetry)
    except ValueError as e:
        records = frame_records({v.name: images[v.name] for v in views if v.name in images})
        warnings.append(f"telemetry not used: {e}")
    geom = measure_survey(model, views, scene, lenses, records, opts)
    geom.warnings[:0] = warnings
    ctx.on_progress("survey", 0.1, f"scale: {geom.scale.source or 'none'}; frame: {geom.frame.crs_name}")
    frame = geom.frame
    res: dict = {
        "scale": geom.scale.to_json(),
        "frame": {"crs": f"EPSG:{frame.epsg}" if frame.epsg else None, "crs_name": frame.crs_name,
                  "georeferenced": geom.gps.georeferenced, "gps_residual_m": geom.gps.residual_m,
                  "gps_extent_m": geom.gps.extent_m, "gps_frames": geom.gps.frames, "units": geom.units,
                  "heading_sigma_deg": geom.gps.heading_sigma_deg,
                  "note": geom.gps.note, "up": "the survey plane's normal (heights are above the fitted plane)"},
        "records": {"altimeter_frames": sum(r.distance_m is not None for r in records.values()),
                    "gps_frames": sum(r.lat is not None for r in records.values()),
                    "telemetry": opts.telemetry},
        "warnings": geom.warnings,
    }
    if opts.ortho:
        try:
            products = make_products(job, geom, lenses, _restored_files(layout), opts.ortho_gsd,
                                     lambda f, m: ctx.on_progress("survey", 0.1 + 0.8 * f, m))
        except NoSurfaceError as e:  # a model with no seabed to map: the job's other results stand
            res.update(files={}, note=f"no orthomosaic: {e}")
        else:
            res.update(products.record)
            gt = find_ground_truth(opts.source, opts.ground_truth)
            if gt is not None:
                res["truth"] = score_products(job, gt, geom, products.grid, scene)
    else:
        res["files"] = {}
        res["note"] = "ortho=false: no orthomosaic or elevation model made"
    res["seconds"] = round(time.perf_counter() - t0, 2)
    res["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    atomic_write_json(layout.survey_result, res)
    log.info("survey products in %.1f s: %s", res["seconds"], ", ".join(res.get("files", {})) or "none")
    return res
