"""report.html's "Survey products" section: the scale and where it came from, the map frame, the products' grid
and reef-structure numbers, and small copies of the orthomosaics (without and with water) and the hillshade."""

from __future__ import annotations

from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.evaluate.plots import image_png
from pipeline.job.layout import JobLayout
from pipeline.scene.images import read_image, resize_area_to

SHOWN_WIDTH = 560  # px of each embedded preview


def survey_pictures(job: Path) -> list[tuple[str, bytes]]:
    """(label, PNG) of the previews the survey stage wrote, shrunk to SHOWN_WIDTH."""
    layout = JobLayout(job)
    out = []
    for label, path in (("orthomosaic, water removed", layout.ortho_preview),
                        ("orthomosaic, with water (the photos as taken)", layout.ortho_water_preview),
                        ("elevation model (hillshade)", layout.hillshade_preview)):
        if not path.is_file():
            continue
        img = read_image(path)
        h, w = img.shape[:2]
        if w > SHOWN_WIDTH:
            img = resize_area_to(img, (max(1, round(h * SHOWN_WIDTH / w)), SHOWN_WIDTH))
        elif w < SHOWN_WIDTH // 2:  # a small survey's mosaic: whole pixels enlarged, so it can be seen
            k = SHOWN_WIDTH // 2 // w + 1
            img = np.repeat(np.repeat(img, k, axis=0), k, axis=1)
        out.append((label, image_png(img)))
    return out


def _num(x: Any, digits: int = 3) -> str:
    return "–" if x is None else f"{x:.{digits}g}" if isinstance(x, float) else escape(str(x))


def survey_sentences(s: dict) -> list[str]:
    """The section's plain sentences."""
    scale, frame, grid = s.get("scale") or {}, s.get("frame") or {}, s.get("grid") or {}
    unit = "m" if frame.get("units") == "m" else "scene units"
    out = []
    if scale.get("metres_per_unit"):
        spread = scale.get("spread")
        out.append(f"Metric scale from the {escape(str(scale.get('source')).replace('_', ' '))}: "
                   f"{scale['metres_per_unit']:.5g} m per scene unit"
                   + (f" (frames agree to ±{100 * spread:.1f} %)" if spread is not None else "") + ".")
    else:
        out.append("No metric scale: the products are in arbitrary scene units. "
                   + escape(scale.get("note") or ""))
    out.append(f"Map frame: {escape(frame.get('crs_name', '?'))}"
               + (f" ({escape(frame['crs'])})" if frame.get("crs") else "") + ". " + escape(frame.get("note") or ""))
    if grid:
        terrain = s.get("terrain") or {}
        height = terrain.get("height") or {}
        out.append(f"Grid {grid['width']} x {grid['height']} at {_num(grid['gsd'])} {unit} per pixel; area mapped "
                   f"{_num(grid.get('area'))} {unit}²; rugosity {_num(terrain.get('rugosity'), 4)}; height range "
                   f"(2-98 %) {_num(height.get('robust_range'))} {unit}.")
    return out


def survey_html(s: dict | None, pictures: list[tuple[str, bytes]], data_uri) -> str:
    if s is None:
        return ""
    html = "<h2>Survey products</h2>" + "".join(f"<p>{t}</p>" for t in survey_sentences(s))
    for w in s.get("warnings") or []:
        html += f"<p class=warn>{escape(w)}</p>"
    if pictures:
        html += '<div class="row">' + "".join(
            f'<figure class="wide"><img src="{data_uri(png)}" alt="{escape(label)}"><figcaption>{escape(label)}'
            f"</figcaption></figure>" for label, png in pictures) + "</div>"
    files = s.get("files") or {}
    if files:
        html += "<p class=muted>Files: " + ", ".join(escape(Path(f).name) for f in files.values()) + "</p>"
    return html


__all__ = ["survey_html", "survey_pictures", "survey_sentences"]
