"""A truth-free score of a restoration: does the same seabed point keep its colour across distances?

A restored surface point should have one colour from every view. Its photos differ because the water between
differs: attenuation and veil grow with the range r. A restoration with the right water leaves no trend with
range; one with the water wrong, or no restoration at all, leaves one that every point shares (what is left of
the water is a function of range and of the point's colour, not of the point).

The measure, per channel, from the sparse model's sightings (point p seen at range r_pk with colour c_pk):

1. Each point seen at clearly different ranges (its farthest sighting at least ``MIN_POINT_RANGE_RATIO`` times
   its nearest) gets its own least-squares slope g_p = dc/dr and mean colour c̄_p; the slope's precision is
   S_p = Σ_k (r_pk − r̄_p)².
2. What the water leaves is, to first order in the range, c = a(r)·J + b(r) (a gain and an offset that depend
   on range only), so the slopes follow a line in the point's colour: g_p ≈ s_a·c̄_p + s_b. The line is fitted
   over the points weighted by S_p and robustly (Tukey's biweight on the standardised residuals): points on
   moving things, specular glints or mismatches do not pull it. The fitted slope ĝ_p is the systematic part of
   the point's change with range; the scatter around it (noise, misplaced pixels) is left out.
3. ``drift`` = RMS over the points of ĝ_p · Δr, Δr = the sightings' 90th − 10th range percentile: how much the
   same seabed's colour changes between the survey's near and far sightings.
4. ``contrast`` = the robust spread (1.4826·MAD) of the points' mean colours: how different the seabed's points
   are from one another. ``score`` = drift / contrast.

Why normalise by contrast: the score is then unchanged by any per-channel gain and offset of the whole
restoration (c → α·c + γ scales drift and contrast alike), so a darker, brighter or flatter restoration is not
rewarded for shrinking its colour changes, and a constant "restoration" (contrast 0) has no score: it is
reported as undefined (``MIN_CONTRAST_SHARE``), never as perfect. Normalising by the colour level instead (log
colour, relative change) rewards flattening towards a bright constant, and gives dark points (near the clip,
amplified noise) the most weight. A plain median of the per-point slopes was rejected: in a channel where the
veil is about as bright as the seabed, bright points darken and dark points brighten with range, and their
median slope is near zero while the photos plainly disagree.

The headline ``share``: the restoration's score over the photos' (mean over the channels each), below 1 when
the restoration made the same seabed agree better across distances than the photos do.
"""

from __future__ import annotations

import numpy as np

from pipeline.medium.drift import (
    MIN_POINT_RANGE_RATIO,
    MIN_POINTS,
    channel_drift,
    point_slopes,
    range_span,
)
from pipeline.medium.estimate import Observations

MIN_CONTRAST_SHARE = 0.25  # the restored colours' contrast below this share of the photos': undefined (flattened)
CLIP_LOW, CLIP_HIGH = 0.5 / 255, 254.5 / 255  # a restored value at 0 or 255 of 8 bits: clipped


def colour_consistency(photo: Observations, restored: Observations, min_points: int = MIN_POINTS) -> dict:
    """The score of ``restored`` against ``photo``: the same sightings (point, range) with the photos' colours
    and the restored photos' (both [0, 1], any channel order as long as it is the same).

    Returns a JSON-able dict: ``defined`` (bool), ``reason`` (why not, else None), ``n_points`` (points seen at
    clearly different ranges), ``n_sightings`` (their sightings), ``range_ratio`` (90th / 10th percentile of those
    sightings' ranges), ``range_spread`` (Δr, scene units), ``photo`` and ``restored`` (:class:`ChannelDrift` as
    dicts), ``photo_score`` and ``restored_score`` (mean over the channels of the score), ``share``
    (restored_score / photo_score), ``contrast_ratio`` (restored / photo contrast, per channel), ``clipped`` (share
    of the restored sightings at 0 or 1, per channel)."""
    if photo.point.shape != restored.point.shape or not np.array_equal(photo.point, restored.point) \
            or not np.allclose(photo.range, restored.range):
        raise ValueError("photo and restored observations must be the same sightings (point and range)")
    sp = point_slopes(photo)
    sr = point_slopes(restored)
    keep = np.isin(photo.point, sp.point)
    out: dict = {"defined": False, "reason": None, "n_points": len(sp.point), "n_sightings": int(keep.sum()),
                 "range_ratio": None, "range_spread": None, "photo": None, "restored": None, "photo_score": None,
                 "restored_score": None, "share": None, "contrast_ratio": None, "clipped": None,
                 "min_point_range_ratio": MIN_POINT_RANGE_RATIO}
    if len(sp.point) < min_points:
        out["reason"] = (f"only {len(sp.point)} sparse points were seen at clearly different ranges (farthest "
                         f"sighting at least {MIN_POINT_RANGE_RATIO}x the nearest); {min_points} are needed")
        return out
    out["range_ratio"], out["range_spread"] = range_span(photo, sp.point)
    p = channel_drift(sp, out["range_spread"])
    r = channel_drift(sr, out["range_spread"])
    out["photo"], out["restored"] = p.to_dict(), r.to_dict()
    if min(p.contrast) <= 0:
        out["reason"] = "the photos' colours at the sparse points do not differ in some channel (no contrast)"
        return out
    ratio = [rc / pc for rc, pc in zip(r.contrast, p.contrast, strict=True)]
    out["contrast_ratio"] = ratio
    col = restored.colour[keep]
    out["clipped"] = [float(np.mean((col[:, k] <= CLIP_LOW) | (col[:, k] >= CLIP_HIGH))) for k in range(3)]
    flat = [k for k in range(3) if ratio[k] < MIN_CONTRAST_SHARE]
    if flat:
        out["reason"] = ("the restored colours lost their contrast in channel " + ", ".join(
            f"{'RGB'[k]} ({ratio[k]:.0%} of the photos', {out['clipped'][k]:.0%} of its sightings clipped to 0 or 1)"
            for k in flat) + f": below {MIN_CONTRAST_SHARE:.0%}, a flattened or saturated image would score as "
            "consistent")
        return out
    out["photo_score"] = float(np.mean(p.score))  # type: ignore[arg-type]  # no None: every contrast > 0
    out["restored_score"] = float(np.mean(r.score))  # type: ignore[arg-type]
    out["share"] = out["restored_score"] / out["photo_score"] if out["photo_score"] > 0 else None
    out["defined"] = True
    return out
