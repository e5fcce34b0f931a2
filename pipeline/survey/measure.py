"""The survey measured: each view's rendered depth, the metric scale from the survey's records, and the map frame.

What the products and the report both read: :func:`measure_survey` returns a :class:`SurveyGeometry`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.job.options import JobOptions, parse_scale_bars
from pipeline.scene.records import LensCamera, Scene, View
from pipeline.scene.seen import view_point_ranges
from pipeline.survey.frame import HEADING_WARN_DEG, GpsFit, SurveyFrame, georeference, plane_frame
from pipeline.survey.marks import ScaleBarError, bar_length_units
from pipeline.survey.records import FrameRecord
from pipeline.survey.scale import ScaleFit, altimeter_scale, bar_scale, choose_scale
from pipeline.survey.surface import ViewDepth, centre_distance, render_depths
from pipeline.train.model import TrainedModel

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SurveyGeometry:
    depths: dict[str, ViewDepth]  # image name -> its training camera and rendered surface depth
    distances: dict[str, float]  # image name -> the model's camera-to-bottom distance (scene units)
    scale: ScaleFit
    gps: GpsFit
    frame: SurveyFrame
    units: str  # "m" or "scene units"
    warnings: list[str]


def resolve_telemetry(opts: JobOptions, records_dir: Path) -> Path | None:
    """The telemetry CSV the options name: a file ingest kept from the upload or folder (``records_dir``, matched
    by name or by its flattened ``folder__name``), else a path as given (command-line jobs). FileNotFoundError
    names what was looked for."""
    if not opts.telemetry:
        return None
    name = Path(opts.telemetry).name
    kept = sorted(records_dir.glob("*.csv")) if records_dir.is_dir() else []
    for p in kept:
        if p.name == name or p.name.endswith("__" + name) or p.name == opts.telemetry.replace("/", "__"):
            return p
    path = Path(opts.telemetry).expanduser()
    if path.is_absolute() and path.is_file():
        return path
    raise FileNotFoundError(f"telemetry {opts.telemetry!r}: not among the CSV files that came with the images "
                            f"({', '.join(p.name for p in kept) or 'none'})")


POINT_WINDOW = 0.3  # the sparse points' stand-in for the altimeter: this share of the image around its centre


def sparse_distance(scene: Scene, view: View) -> float | None:
    """The view's camera-to-bottom distance from the sparse points it saw near its centre (median range; None
    with fewer than 5): the stand-in where the render shows no surface at the centre."""
    xy, ranges = view_point_ranges(scene, view)
    c = view.camera
    near = ((np.abs(xy[:, 0] - c.cx) < POINT_WINDOW * c.width / 2)
            & (np.abs(xy[:, 1] - c.cy) < POINT_WINDOW * c.height / 2))
    return float(np.median(ranges[near])) if near.sum() >= 5 else None


def measure_survey(model: TrainedModel, views: list[View], scene: Scene, lenses: dict[str, LensCamera],
                   records: dict[str, FrameRecord], opts: JobOptions) -> SurveyGeometry:
    """Depths, scale and frame of a trained job (module docstring)."""
    warnings = []
    points = np.asarray(scene.points, np.float64).reshape(-1, 3)
    depths = {vd.view.name: vd for vd in render_depths(model, views)}
    distances = {n: d for n, vd in depths.items() if (d := centre_distance(vd)) is not None}
    fallback = {n: d for n, vd in depths.items()
                if n not in distances and (d := sparse_distance(scene, vd.view)) is not None}
    if fallback:
        warnings.append(f"{len(fallback)} views show no rendered surface at their centre: their camera-to-bottom "
                        f"distance is the sparse points' there")
        distances.update(fallback)
    altimeter = {n: r.distance_m for n, r in records.items() if r.distance_m is not None}
    alt = altimeter_scale(altimeter, distances)
    bars = []
    for bar in parse_scale_bars(opts.scale_bar):
        try:
            name, units = bar_length_units(bar, depths, lenses)
            bars.append((f"{name} {bar.a}-{bar.b}", bar.metres, units))
        except ScaleBarError as e:  # a mark we cannot measure is reported, never fails the job
            warnings.append(str(e))
    fit = choose_scale(alt, bar_scale(bars), opts.metric_scale)
    centres = {n: vd.view.center for n, vd in depths.items()}
    c = np.stack(list(centres.values()))
    scale = fit.metres_per_unit
    local = plane_frame(points if len(points) >= 3 else c, c, scale or 1.0, "m" if scale else "scene units")
    gps = georeference(local, centres, records, scale_known=scale is not None)
    if scale is None and gps.scale is not None:
        fit = choose_scale(None, None, None, gps.scale)
    units = "m" if fit.metres_per_unit is not None else "scene units"
    if gps.heading_sigma_deg is not None and gps.heading_sigma_deg > HEADING_WARN_DEG:
        warnings.append(f"georeferenced, but the map's orientation is uncertain by ±{gps.heading_sigma_deg:.0f}°: "
                        f"{gps.note}")
    if fit.outliers:
        warnings.append(f"the altimeter disagrees with the model on {len(fit.outliers)} frames (left out of the "
                        f"scale): {', '.join(fit.outliers[:5])}")
    log.info("survey scale: %s (%s); frame: %s", fit.metres_per_unit, fit.source, gps.frame.crs_name)
    return SurveyGeometry(depths, distances, fit, gps, gps.frame, units, warnings)


__all__ = ["SurveyGeometry", "measure_survey", "resolve_telemetry"]
