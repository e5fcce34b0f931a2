"""Why SfM left a frame out: read from the matching database and the models (``pipeline.sfm.recipe``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass
class DroppedFrame:
    """A readable frame the kept model does not place, and why (:func:`drop_reasons`)."""

    name: str
    reason: str  # "no features", "matched to no other frame (...)", "in a side model of N frames (...)", ...


def drop_reasons(
    db_path: Path, names: list[str], placed: set[str], side_models: list[tuple[int, list[str]]], min_matches: int
) -> list[DroppedFrame]:
    """One :class:`DroppedFrame` per name in ``names`` (sorted) that is not in ``placed``.

    ``side_models`` are (index on disk, images outside the kept model) of the other models. The reason is the first
    that holds: in a side model; no SIFT features; no verified pair with at least ``min_matches`` inliers (the
    mapper ignores weaker pairs); else it had matches but the mapper could not register it (the best pair is
    named, and the best pair with a frame of the kept model)."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {im.image_id: im.name for im in db.read_all_images()}
        features = {n: db.num_keypoints_for_image(i) if db.exists_keypoints(i) else 0 for i, n in ids.items()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    best: dict[str, tuple[int, str]] = {}  # the pair with the most inliers
    best_placed: dict[str, tuple[int, str]] = {}  # the same among pairs with a frame of the kept model
    for pid, k in zip(pair_ids, inliers, strict=True):
        a, b = (ids[int(i)] for i in pycolmap.pair_id_to_image_pair(pid))
        for x, y in ((a, b), (b, a)):
            if int(k) > best.get(x, (0, ""))[0]:
                best[x] = (int(k), y)
            if y in placed and int(k) > best_placed.get(x, (0, ""))[0]:
                best_placed[x] = (int(k), y)
    side = {n: (idx, len(imgs)) for idx, imgs in side_models for n in imgs}
    out = []
    for n in names:
        if n in placed:
            continue
        k, partner = best.get(n, (0, ""))
        k_placed, partner_placed = best_placed.get(n, (0, ""))
        if n in side:
            idx, size = side[n]
            reason = f"in a side model of {size} frames (distorted/sparse/{idx})"
        elif features.get(n, 0) == 0:
            reason = "no features"
        elif k < min_matches:
            reason = (f"matched to no other frame ({features[n]} features; best pair {k} inliers, "
                      f"{min_matches} needed)")  # fmt: skip
        else:
            with_kept = f"{k_placed} with {partner_placed}" if k_placed else "none"
            reason = (f"failed to register ({features[n]} features; best pair {k} inliers with {partner}; "
                      f"with a registered frame: {with_kept})")  # fmt: skip
        out.append(DroppedFrame(n, reason))
    return out
