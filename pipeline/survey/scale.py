"""Metres per scene unit, from what the survey recorded, in order of preference:

1. the altimeter: per frame, the recorded camera-to-bottom distance over the model's (its rendered depth at the
   image centre, :func:`pipeline.survey.surface.centre_distance`); the scale is the median ratio, its spread the
   ratios' robust relative deviation, and frames far off the median are named as outliers;
2. scale bars the user marked (a known length between two photo pixels: :mod:`pipeline.survey.marks`);
3. ``metric_scale`` as the user typed it;
4. the GPS track's fit (:func:`pipeline.survey.frame.georeference`), metres of boat track per scene unit.

Without any, the products are in scene units and nothing claims metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_ALTIMETER_FRAMES = 3
MAX_ALTIMETER_SPREAD = 0.15  # per-frame ratios deviating more than this (robust, relative): the altimeter is not used
OUTLIER_FLOOR = 0.05  # a frame is an outlier beyond max(4 spreads, this) from the median ratio


@dataclass(frozen=True)
class ScaleFit:
    metres_per_unit: float | None
    source: str | None  # "altimeter" | "scale_bar" | "metric_scale" | "gps" | None
    frames: int = 0  # measurements behind it
    spread: float | None = None  # robust relative spread of the measurements (1.4826 MAD / median)
    outliers: list[str] = field(default_factory=list)
    per_frame: list[dict] = field(default_factory=list)
    note: str = ""

    def to_json(self) -> dict:
        return {"metres_per_unit": self.metres_per_unit, "source": self.source, "frames": self.frames,
                "spread": self.spread, "outliers": self.outliers, "note": self.note, "per_frame": self.per_frame}


def robust_ratio(ratios: np.ndarray) -> tuple[float, float]:
    """(median, 1.4826·MAD / median) of positive ratios."""
    med = float(np.median(ratios))
    return med, float(1.4826 * np.median(np.abs(ratios - med)) / med)


def altimeter_scale(altimeter_m: dict[str, float], model_units: dict[str, float]) -> ScaleFit | None:
    """The scale from per-frame altimeter distances (metres) against the model's distances (scene units) of the
    same frames; None with fewer than MIN_ALTIMETER_FRAMES frames that have both."""
    names = sorted(n for n in altimeter_m if n in model_units and model_units[n] > 0 and altimeter_m[n] > 0)
    if len(names) < MIN_ALTIMETER_FRAMES:
        return None
    ratios = np.array([altimeter_m[n] / model_units[n] for n in names])
    med, spread = robust_ratio(ratios)
    dev = ratios / med - 1
    limit = max(4 * spread, OUTLIER_FLOOR)
    outliers = [n for n, d in zip(names, dev) if abs(d) > limit]
    keep = np.abs(dev) <= limit
    med, spread = robust_ratio(ratios[keep])
    per_frame = [{"name": n, "altimeter_m": round(altimeter_m[n], 4), "model_units": round(model_units[n], 5),
                  "metres_per_unit": round(float(r), 6), "deviation": round(float(d), 4)}
                 for n, r, d in zip(names, ratios, dev)]
    note = (f"altimeter of {int(keep.sum())} frames against the model's camera-to-bottom distance: spread "
            f"{100 * spread:.1f} %" + (f", {len(outliers)} outlier frames left out" if outliers else ""))
    return ScaleFit(med, "altimeter", int(keep.sum()), spread, outliers, per_frame, note)


def bar_scale(lengths: list[tuple[str, float, float]]) -> ScaleFit | None:
    """The scale from scale bars: (label, metres, model length in scene units) each."""
    ok = [(label, m, u) for label, m, u in lengths if u > 0 and np.isfinite(u)]
    if not ok:
        return None
    ratios = np.array([m / u for _, m, u in ok])
    med, spread = robust_ratio(ratios) if len(ok) > 1 else (float(ratios[0]), None)
    per = [{"bar": label, "metres": m, "model_units": round(u, 5), "metres_per_unit": round(m / u, 6)}
           for label, m, u in ok]
    return ScaleFit(med, "scale_bar", len(ok), spread, [], per, f"{len(ok)} scale bar(s) marked in the photos")


def choose_scale(altimeter: ScaleFit | None, bars: ScaleFit | None, metric_scale: float | None,
                 gps_scale: float | None = None) -> ScaleFit:
    """The first usable source in the order of the module docstring; what was passed over is said in the note."""
    passed = []
    if altimeter is not None:
        if altimeter.spread is not None and altimeter.spread <= MAX_ALTIMETER_SPREAD:
            return altimeter
        passed.append(f"the altimeter's frames disagree with the model by {100 * (altimeter.spread or 0):.0f} % "
                      f"(limit {100 * MAX_ALTIMETER_SPREAD:.0f} %)")
    if bars is not None:
        return _with_note(bars, passed)
    if metric_scale is not None:
        return _with_note(ScaleFit(float(metric_scale), "metric_scale", 1, None, [], [], "metric_scale as given"),
                          passed)
    if gps_scale is not None:
        return _with_note(ScaleFit(float(gps_scale), "gps", 0, None, [], [],
                                   "the GPS track's length against the camera track's"), passed)
    return ScaleFit(None, None, note="; ".join(passed + ["no altimeter, scale bar, metric_scale or GPS: the "
                                                         "products are in scene units (arbitrary)"]))


def _with_note(fit: ScaleFit, passed: list[str]) -> ScaleFit:
    if not passed:
        return fit
    return ScaleFit(fit.metres_per_unit, fit.source, fit.frames, fit.spread, fit.outliers, fit.per_frame,
                    "; ".join([fit.note] + passed))


__all__ = ["ScaleFit", "altimeter_scale", "bar_scale", "choose_scale", "robust_ratio"]
