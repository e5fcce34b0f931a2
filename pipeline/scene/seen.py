"""The sparse points each view saw, where in its image and how far: the tracks of the SfM model where it has them,
else the points projecting inside the view. Read by the collapse guard (``pipeline.train.quality``) and the medium's
per-view evidence (``pipeline.medium.term``)."""

from __future__ import annotations

import numpy as np

from pipeline.scene.records import Scene, Sightings, View


def _points_seen(scene: Scene, view: View) -> tuple[np.ndarray, np.ndarray]:
    """(pixel positions [K, 2], point indices [K]) of the sparse points ``view`` saw (see :func:`view_points`)."""
    s: Sightings | None = (scene.sightings or {}).get(view.name)
    if s is not None and len(s.xy):
        return np.asarray(s.xy, dtype=np.float64) * (view.camera.width / s.width), np.asarray(s.point)
    if not len(scene.points):
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    u, v, _ = view.project(scene.points)
    ok = np.isfinite(u) & (u >= 0) & (u < view.camera.width) & (v >= 0) & (v < view.camera.height)
    return np.stack([u[ok], v[ok]], axis=1), np.nonzero(ok)[0]


def view_points(scene: Scene, view: View) -> np.ndarray:
    """Pixel positions [K, 2] (pixel-centre convention, at ``view.camera``'s resolution) of the sparse points
    ``view`` saw: its track observations when the model has them, else the points projecting inside it."""
    return _points_seen(scene, view)[0]


def view_point_ranges(scene: Scene, view: View) -> tuple[np.ndarray, np.ndarray]:
    """The sparse points ``view`` saw: pixel positions [K, 2] as :func:`view_points`, and each point's distance
    from the camera centre [K] (scene units)."""
    xy, ids = _points_seen(scene, view)
    pts = np.asarray(scene.points, dtype=np.float64).reshape(-1, 3)
    return xy, (np.linalg.norm(pts[ids] - view.center, axis=1) if len(ids) else np.zeros(0))


__all__ = ["view_point_ranges", "view_points"]
