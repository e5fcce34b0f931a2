"""Reading the dashboard's survey map (service/web/static/surveymap.js) from a Playwright page, and what survey.json
says it should show: for tests/service/test_dashboard.py."""

from __future__ import annotations

import re

from svc_helpers import wait_for

IMG = "#survey-map .smap-img"
VIEWPORT = "#survey-map .smap"

# the image's transform as the browser applies it (a = d: the scale; e, f: the translation in CSS pixels)
_VIEW = """() => {
  const img = document.querySelector('#survey-map .smap-img');
  const m = new DOMMatrix(getComputedStyle(img).transform);
  return {scale: m.a, x: m.e, y: m.f, transform: img.style.transform, src: img.src, path: img.dataset.path,
          w: img.naturalWidth, h: img.naturalHeight, box: [img.offsetWidth, img.offsetHeight]};
}"""
_SHOWS = """p => {
  const img = document.querySelector('#survey-map .smap-img');
  return !!img && img.dataset.path === p && img.complete && img.naturalWidth > 0
    && img.closest('.smap').dataset.shown === p;
}"""
_SCALE_BAR = """() => {
  const s = document.querySelector('#survey-map .smap-scale');
  return {hidden: s.hidden, width: parseFloat(s.querySelector('.smap-scale-bar').style.width),
          label: s.querySelector('span').textContent};
}"""
_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "units": 1.0}


def view(page) -> dict:
    return page.evaluate(_VIEW)


def wait_shows(page, path: str, timeout: float = 30) -> dict:
    """The map once it shows the preview ``path``, loaded and placed; its view."""
    wait_for(f"the survey map to show {path}", lambda: page.evaluate(_SHOWS, path), timeout=timeout, interval=0.25)
    return view(page)


def wait_view_change(page, what: str, before: dict, key: str, timeout: float = 10) -> dict:
    """The view once its ``key`` differs from ``before``'s (a pointer or wheel event is handled asynchronously)."""
    wait_for(what, lambda: view(page)[key] != before[key], timeout=timeout, interval=0.1)
    return view(page)


def scale_bar(page) -> dict:
    return page.evaluate(_SCALE_BAR)


def facts(page) -> dict[str, tuple[str, str]]:
    """key -> (the number or name survey.json holds, the text shown)."""
    return {d.get_attribute("data-fact"): (d.get_attribute("data-value"), d.inner_text())
            for d in page.query_selector_all("#survey-map dd[data-fact]")}


def shown_length(text: str) -> float:
    """'2.1 mm per pixel' -> 0.0021, '62.2 cm (...)' -> 0.622, '6.17 m²' -> 6.17, '3 units' -> 3."""
    m = re.match(r"(-?[\d.]+) (mm|cm|m|units)(?![a-z])", text)
    assert m, f"no length in {text!r}"
    return float(m[1]) * _UNITS[m[2]]


def ground_per_pixel(survey: dict, preview_width: int) -> float | None:
    """The ground size of one preview pixel: the mosaic's bounds (or gsd × width) over the preview's width."""
    grid = survey.get("grid") or {}
    b = grid.get("bounds")
    if isinstance(b, list) and len(b) == 4 and b[2] > b[0]:
        return (b[2] - b[0]) / preview_width
    if grid.get("gsd") and grid.get("width"):
        return grid["gsd"] * grid["width"] / preview_width
    return None
