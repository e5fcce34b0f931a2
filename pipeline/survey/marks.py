"""Scale bars: a known length between two points a user marked in one photo, measured in the model.

A mark is a pixel of the photo as uploaded (column, row from its top-left corner). Its ray comes from the photo's
lens (SfM's camera model, distortion included); the model's rendered depth along that ray in the training camera
(same pose) gives the seabed point. The bar's model length is the distance between its two points.
"""

from __future__ import annotations

import numpy as np

from pipeline.job.options import ScaleBar
from pipeline.scene.records import LensCamera
from pipeline.survey.surface import ViewDepth


class ScaleBarError(ValueError):
    """A scale bar that cannot be measured (unknown photo, a point off the photo or off the surface)."""


def _photo_name(bar: ScaleBar, names: list[str]) -> str:
    hits = [n for n in names if n == bar.photo or n.split("__")[-1] == bar.photo]
    if not hits:
        raise ScaleBarError(f"scale bar in {bar.photo!r}: no registered photo of that name")
    return hits[0]


def bar_length_units(bar: ScaleBar, depths: dict[str, ViewDepth], lenses: dict[str, LensCamera]) -> tuple[str, float]:
    """(the photo's name in the job, the bar's length in scene units)."""
    name = _photo_name(bar, sorted(set(depths) & set(lenses)))
    lens, vd = lenses[name], depths[name]
    pts = np.array([bar.a, bar.b], np.float64) + 0.5  # COLMAP's pixel centres sit at +0.5
    if ((pts < 0.5) | (pts > [lens.width - 0.5, lens.height - 0.5])).any():
        raise ScaleBarError(f"scale bar in {bar.photo!r}: a point lies outside the {lens.width}x{lens.height} photo")
    xy = np.asarray(lens.colmap().cam_from_img(pts), np.float64)  # normalised undistorted rays [2, 2]
    c = vd.view.camera
    world, ok = vd.point_at(c.fx * xy[:, 0] + c.cx, c.fy * xy[:, 1] + c.cy)
    if not ok.all():
        raise ScaleBarError(f"scale bar in {bar.photo!r}: the model has no surface under a marked point")
    return name, float(np.linalg.norm(world[0] - world[1]))


__all__ = ["ScaleBarError", "bar_length_units"]
