"""Does the trained model still hold the scene? Coverage, water share and Gaussian count, per training view.

A medium model has a trivial way out on turbid water: leave a pixel uncovered and the water's veiling light B∞
fills it (I = J·A + α·B + (1 − α)·B∞), which in murky water is close to the photo anyway. Such a model "fits"
with a good PSNR while it has lost the seabed. These measurements tell that apart:

- ``coverage``: share of a view's pixels where the Gaussians' alpha ≥ 0.5.
- ``point_coverage``: share of the sparse points the view saw (its SfM track observations, else the points
  projecting inside it) whose pixel has alpha >= 0.5. A warning only: a dark surface needs no opacity over the
  black background, so a healthy model leaves many feature points (the corners of dark pebbles, urchins) below
  it (a plain 3DGS model of a generated scene without water: 45-50 % in every view).
- ``uncovered_content``: share of the uncovered pixels whose photo is not dark: a view with next to nothing covered
  where its photo shows something has lost its scene (:func:`lost_view`).
- ``uncovered_missed``: share of the uncovered pixels whose photo shows something that the prediction does not
  reproduce. In plain splatting it is what tells a lost view: a dark scene is drawn faint over the black background
  and still renders its photo (AIMS Erub in ``3dgs``: alpha 0.25 on average, under 5 % of most views' pixels at
  0.5, renders at 37-40 dB), while a lost model renders the background.
- ``water_share``: mean over pixels of the light the water alone adds, α·B + (1 − α)·B∞, over the predicted
  light I; 1 means the view is all veil.
- ``uncovered_detail``: share of a view's pixels that are uncovered although the photo shows structure there
  that the prediction lacks: the local spread of the residual photo − prediction is well above its typical
  spread on covered pixels. Open water is smooth and passes; a seabed given up as veil (an oblique view's far
  half) does not. It needs no noise model: covered pixels calibrate it per view.

:func:`collapse_warnings` turns them into the verdict and warnings; ``COLLAPSE_*`` are the limits
(docs/DECISIONS.md, "A collapse is what a collapse is").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from pipeline.scene.records import Scene, View, ray_length_factor
from pipeline.scene.seen import view_point_ranges
from pipeline.splat.gaussians import activate
from pipeline.train.model import model_from_state
from pipeline.train.render import render_outputs

COVER_ALPHA = 0.5  # a pixel is covered when the Gaussians' alpha is at least this
POINT_DEPTH_TOL = 0.25  # a point's pixel renders its surface when the rendered distance is within 25 % of it
COLLAPSE_COVERAGE = 0.05  # a view with less of its pixels covered than this, where its photo shows something, is lost
COLLAPSE_VIEW_SHARE = 0.5  # more lost training views than this share: the scene is gone (docs/DECISIONS.md)
COLLAPSE_UNCOVERED_DETAIL = 0.5  # a medium view with this share of its pixels uncovered where the photo shows detail
#                                  is lost (the steep oblique views of photo medium water, far half as veil: ~0.4)
DARK_PHOTO = 0.05  # a photo pixel whose brightest channel is under this shows nothing (a black frame, a shadow)
MISSED = 0.5  # a pixel's prediction misses its photo when they differ by this share of the photo's brightest channel
COLLAPSE_BUDGET_SHARE = 0.02  # fewer Gaussians than this share of the budget: the model collapsed
WARN_POINT_COVERAGE = 0.9  # below this a medium view's sparse points are reported as partly uncovered (a warning)
WARN_POINT_DEPTH = 0.5  # fewer of a view's points rendered at their distance than this: a warning (see below)
FAR_FACTOR = 3.0  # a pixel rendered beyond this x the view's 95th-percentile point distance is "far behind"
WARN_FAR_SHARE = 0.10  # more of a view's covered pixels far behind than this: a warning (real RUIE sand, before
#                         the depth-band term: docs/DECISIONS.md, "The water must not eat the scene")
DETAIL_WINDOW = 7  # pixels: the residual's local spread is measured in this square
DETAIL_FACTOR = 1.5  # an uncovered pixel shows missing detail when its residual spread is this x the covered median
WARN_UNCOVERED_DETAIL = 0.05  # more of a view's pixels than this uncovered with missing detail: a warning


@dataclass
class ViewQuality:
    name: str
    coverage: float  # share of pixels with alpha >= COVER_ALPHA
    point_coverage: float | None  # share of the view's sparse points on covered pixels; None without points
    water_share: float | None  # mean (water light / predicted light); None in mode 3dgs
    n_points: int = 0  # sparse points the view saw
    point_depth: float | None = None  # share of those points whose pixel renders within POINT_DEPTH_TOL of their
    #                                   distance: the surface is where the points are, not far behind as veil
    far_share: float | None = None  # share of covered pixels rendered beyond FAR_FACTOR x the view's farthest points
    #                                 (95th percentile): surface drawn far behind where points are too sparse to say
    uncovered_detail: float | None = None  # share of pixels uncovered where the photo has detail the model lacks
    uncovered_content: float | None = None  # share of the uncovered pixels where the photo is not dark (DARK_PHOTO)
    uncovered_missed: float | None = None  # ... and the prediction misses it (MISSED); None without a prediction

    def to_json(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def box_mean(x: np.ndarray, k: int) -> np.ndarray:
    """Mean of ``x`` [H, W, ...] over a k x k square around each pixel (edges repeated); k odd."""
    r = k // 2
    rest = [(0, 0)] * (x.ndim - 2)
    c = np.pad(np.pad(np.asarray(x, np.float64), [(r, r), (r, r)] + rest, mode="edge").cumsum(0).cumsum(1),
               [(1, 0), (1, 0)] + rest)
    h, w = x.shape[:2]
    return (c[k:k + h, k:k + w] - c[:h, k:k + w] - c[k:k + h, :w] + c[:h, :w]) / (k * k)


def uncovered_detail(photo: np.ndarray, predicted: np.ndarray, covered: np.ndarray) -> float | None:
    """Share of pixels that are uncovered and whose residual (photo − prediction, grey) varies locally more than
    ``DETAIL_FACTOR`` x its median local spread over covered pixels: structure in the photo that no surface
    explains. photo, predicted [H, W, 3]; covered [H, W] bool. None when nothing is covered (no reference)."""
    if not covered.any():
        return None
    g = (np.asarray(photo, dtype=np.float64) - predicted).mean(-1)
    mu = box_mean(g, DETAIL_WINDOW)
    spread = np.sqrt(np.clip(box_mean(g * g, DETAIL_WINDOW) - mu * mu, 0.0, None))
    ref = float(np.median(spread[covered]))
    return float((~covered & (spread > DETAIL_FACTOR * ref)).mean())


def view_quality(name: str, alpha: np.ndarray, points_xy: np.ndarray, water: np.ndarray | None = None,
                 predicted: np.ndarray | None = None, rendered_range: np.ndarray | None = None,
                 point_range: np.ndarray | None = None, photo: np.ndarray | None = None) -> ViewQuality:
    """alpha [H, W]; points_xy [K, 2] pixel positions; water, predicted [H, W, 3] (predicted: the model's photo,
    with water in medium modes); the rendered distance along each pixel's ray [H, W] and the points' distances
    from the camera [K]; the training photo [H, W, 3]."""
    h, w = alpha.shape
    covered = alpha >= COVER_ALPHA
    pc = pd = fs = None
    if len(points_xy):
        x = np.clip(np.floor(points_xy[:, 0]).astype(int), 0, w - 1)
        y = np.clip(np.floor(points_xy[:, 1]).astype(int), 0, h - 1)
        pc = float(covered[y, x].mean())
        if rendered_range is not None and point_range is not None:
            rel = np.abs(rendered_range[y, x] / np.maximum(point_range, 1e-9) - 1.0)
            pd = float(((rel <= POINT_DEPTH_TOL) & covered[y, x]).mean())
            far = rendered_range > FAR_FACTOR * float(np.percentile(point_range, 95))
            fs = float((far & covered).sum() / max(int(covered.sum()), 1))
    share = None
    if water is not None and predicted is not None:
        share = float((water.sum(-1) / np.maximum(predicted.sum(-1), 1e-4)).clip(0, 1).mean())
    ud = uncovered_detail(photo, predicted, covered) if photo is not None and predicted is not None else None
    uc = um = None
    if photo is not None and not covered.all():
        bright = np.asarray(photo, np.float64).max(-1)
        shown = bright[~covered] >= DARK_PHOTO
        uc = float(shown.mean())
        if predicted is not None:
            miss = np.abs(np.asarray(photo, np.float64) - predicted).max(-1)[~covered] > MISSED * bright[~covered]
            um = float((shown & miss).mean())
    return ViewQuality(name, float(covered.mean()), pc, share, int(len(points_xy)), pd, fs, ud, uc, um)


def _flagged(views: Sequence[ViewQuality], field: str, limit: float, below: bool
             ) -> tuple[list[ViewQuality], ViewQuality | None]:
    """The views whose measurement ``field`` is below (or above) ``limit``, and the worst of them (None: none)."""
    flagged = [q for q in views if (v := getattr(q, field)) is not None and (v < limit if below else v > limit)]
    worst = (min if below else max)(flagged, key=lambda q: getattr(q, field)) if flagged else None
    return flagged, worst


def lost_view(q: ViewQuality, medium: bool = True) -> bool:
    """A view whose scene is gone: next to nothing covered (under ``COLLAPSE_COVERAGE`` of its pixels) although
    its photo shows something there (``uncovered_content``; unknown counts as shown) — in plain splatting,
    something the prediction misses (``uncovered_missed``, where measured): a faint model that renders its photo
    holds its scene; or, with a medium, the veil owning at least ``COLLAPSE_UNCOVERED_DETAIL`` of its pixels where
    the photo shows detail. (A medium model left transparent shows the veil, which a turbid photo resembles: there
    uncovered content counts as lost.)"""
    content = q.uncovered_content if medium or q.uncovered_missed is None else q.uncovered_missed
    empty = q.coverage < COLLAPSE_COVERAGE and (content is None or content >= 0.5)
    eaten = medium and q.uncovered_detail is not None and q.uncovered_detail >= COLLAPSE_UNCOVERED_DETAIL
    return empty or eaten


def collapse_warnings(views: Sequence[ViewQuality], n_gaussians: int, budget: int, medium: bool = True
                      ) -> tuple[bool, list[str]]:
    """(collapsed, warnings). Collapsed only on evidence that the scene is gone: the Gaussians pruned away (fewer
    than ``COLLAPSE_BUDGET_SHARE`` of the budget), or more than ``COLLAPSE_VIEW_SHARE`` of the training views lost
    (:func:`lost_view`: nothing covered where the photo shows something). Everything else is a warning that names
    the views: sparse-point coverage and depth agreement are noisy on real data (SfM outliers, points on moving
    things, approximate 3DGS depths), and in plain splatting (``medium`` False) a dark surface is drawn with low
    opacity over the black background, so no point coverage, depth or veil measure is even a warning there."""
    warnings: list[str] = []
    collapsed = False
    lost = [q for q in views if lost_view(q, medium)]
    if lost and len(lost) > COLLAPSE_VIEW_SHARE * len(views):
        collapsed = True
        warnings.append(f"{len(lost)} of {len(views)} training views lost their scene (under "
                        f"{100 * COLLAPSE_COVERAGE:g}% of their pixels covered, or the veil drawn over "
                        f"{100 * COLLAPSE_UNCOVERED_DETAIL:g}% of them where the photo shows detail: {_names(lost)})")
    elif lost:
        warnings.append(f"{len(lost)} of {len(views)} training views are mostly uncovered (under "
                        f"{100 * COLLAPSE_COVERAGE:g}% of their pixels covered, or the veil drawn over "
                        f"{100 * COLLAPSE_UNCOVERED_DETAIL:g}% of them where the photo shows detail: "
                        f"{_names(lost)}): open water, or views the model lost; their restorations are the veil's")
    if budget > 0 and n_gaussians < COLLAPSE_BUDGET_SHARE * budget:
        collapsed = True
        warnings.append(f"only {n_gaussians} Gaussians, {100 * n_gaussians / budget:.1f}% of the budget {budget}")
    if not medium:
        faint = [q for q in views if q.coverage < COLLAPSE_COVERAGE and q not in lost]
        if faint:
            warnings.append(f"{len(faint)} of {len(views)} training views are drawn faint (under "
                            f"{100 * COLLAPSE_COVERAGE:g}% of their pixels at alpha {COVER_ALPHA}) and still render "
                            f"their photos ({_names(faint)}): a dark scene over the black background; its depth "
                            f"maps are less certain than an opaque model's")
        return collapsed, warnings
    thin, worst = _flagged(views, "point_coverage", WARN_POINT_COVERAGE, below=True)
    if worst:
        warnings.append(f"{len(thin)} training views leave some of their sparse points uncovered (worst {worst.name} "
                        f"{100 * (worst.point_coverage or 0):.0f}% covered, below {100 * WARN_POINT_COVERAGE:.0f}%: "
                        f"{_names(thin)}): dark surfaces there are left to the veil")
    deep, worst = _flagged(views, "point_depth", WARN_POINT_DEPTH, below=True)
    if worst:
        warnings.append(f"{len(deep)} training views render under {100 * WARN_POINT_DEPTH:.0f}% of their sparse points "
                        f"at the points' distance (worst {worst.name} {100 * (worst.point_depth or 0):.0f}%): the "
                        f"rest of the surface there is drawn far behind, where it shows only the water")
    far, worst = _flagged(views, "far_share", WARN_FAR_SHARE, below=False)
    if worst:
        warnings.append(f"{len(far)} training views draw part of their surface beyond {FAR_FACTOR:g}x their sparse "
                        f"points' distance (worst {worst.name} {100 * (worst.far_share or 0):.0f}% of its pixels), "
                        f"where it shows only the water: the restored image is dark there")
    bare, worst = _flagged(views, "uncovered_detail", WARN_UNCOVERED_DETAIL, below=False)
    if worst:
        warnings.append(f"{len(bare)} training views leave part of what the photo shows uncovered (worst {worst.name}: "
                        f"{100 * (worst.uncovered_detail or 0):.0f}% of its pixels show detail the model renders as "
                        f"open water): the restored image is dark there")
    return collapsed, warnings


def _names(views: Sequence[ViewQuality], most: int = 5) -> str:
    more = f" and {len(views) - most} more" if len(views) > most else ""
    return ", ".join(q.name for q in views[:most]) + more


def opacity_histogram(opacities: np.ndarray, edges: Sequence[float] = (0, 0.005, 0.01, 0.05, 0.1, 0.5, 0.9, 1.0001)
                      ) -> dict[str, int]:
    """Counts of activated opacities in bins (a diagnostic of resets and pruning)."""
    counts, _ = np.histogram(np.asarray(opacities, dtype=np.float64), bins=np.asarray(edges))
    return {f"{a:g}-{min(b, 1):g}": int(c) for a, b, c in zip(edges[:-1], edges[1:], counts, strict=True)}


def assess_state(state: dict, scene: Scene, views: Sequence[View], budget: int, backend: str = "auto",
                 photos: Sequence[np.ndarray] | None = None) -> dict:
    """The quality block of a trained checkpoint ``state`` over ``views`` (the training views at the training
    resolution; ``scene`` holds their sparse points and tracks; ``photos`` their images [H, W, 3], for
    ``uncovered_detail``): per-view coverage, point coverage and water share, the Gaussian count against
    ``budget`` (0 = no cap), the opacity histogram, collapse and warnings."""
    model = model_from_state(state)
    per_view = []
    for i, v in enumerate(views):
        o = render_outputs(model.gaussians, v, model.medium, model.sh_degree, backend, model.background)
        water = None if o.A is None else np.clip(o.I - o.J * o.A, 0, None)
        xy, ranges = view_point_ranges(scene, v)
        per_view.append(view_quality(v.name, o.alpha, xy, water, o.I, o.depth * ray_length_factor(v.camera),
                                     ranges if len(ranges) else None, None if photos is None else photos[i]))
    n = int(model.gaussians["means"].shape[0])
    collapsed, warnings = collapse_warnings(per_view, n, budget, medium=model.medium is not None)
    opac = activate(model.gaussians).opacities.detach().cpu().numpy() if n else np.zeros(0)
    pcs = [q.point_coverage for q in per_view if q.point_coverage is not None]
    pds = [q.point_depth for q in per_view if q.point_depth is not None]
    fss = [q.far_share for q in per_view if q.far_share is not None]
    uds = [q.uncovered_detail for q in per_view if q.uncovered_detail is not None]
    shares = [q.water_share for q in per_view if q.water_share is not None]
    return {
        "collapsed": collapsed,
        "warnings": warnings,
        "n_gaussians": n,
        "budget": int(budget),
        "coverage_min": round(min((q.coverage for q in per_view), default=0.0), 4),
        "coverage_mean": round(float(np.mean([q.coverage for q in per_view])) if per_view else 0.0, 4),
        "point_coverage_min": round(min(pcs), 4) if pcs else None,
        "point_depth_min": round(min(pds), 4) if pds else None,
        "far_share_max": round(max(fss), 4) if fss else None,
        "uncovered_detail_max": round(max(uds), 4) if uds else None,
        "water_share_mean": round(float(np.mean(shares)), 4) if shares else None,
        "opacity_histogram": opacity_histogram(opac),
        "limits": {"cover_alpha": COVER_ALPHA, "collapse_coverage": COLLAPSE_COVERAGE,
                   "collapse_view_share": COLLAPSE_VIEW_SHARE, "collapse_uncovered_detail": COLLAPSE_UNCOVERED_DETAIL,
                   "point_depth_tol": POINT_DEPTH_TOL, "warn_point_depth": WARN_POINT_DEPTH,
                   "collapse_budget_share": COLLAPSE_BUDGET_SHARE, "warn_point_coverage": WARN_POINT_COVERAGE,
                   "warn_far_share": WARN_FAR_SHARE, "warn_uncovered_detail": WARN_UNCOVERED_DETAIL},
        "per_view": [q.to_json() for q in per_view],
    }
