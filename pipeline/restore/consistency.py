"""The restored photos' colour consistency across distances (:mod:`pipeline.evaluate.consistency`) in a job,
with no ground truth: the score every report carries.

Geometry: the score is taken on the files the user gets, the photos in ``images/`` and their restored copies
in ``restored/``, both in the photo's own resolution and lens geometry. The sparse model's sightings are pixel
positions in SfM's undistorted PINHOLE images (``scene/``); each is carried into the photo through the
photo's lens camera (SfM's model before undistortion, :func:`pipeline.restore.views.lens_cameras`): the
undistorted normalised ray (x − c_x)/f_x, (y − c_y)/f_y, distorted by pycolmap's ``img_from_cam``, the same pose
(COLMAP's undistortion keeps poses). The photo and its restored copy are read at that one pixel (as
:func:`pipeline.medium.estimate.gather_observations` reads a sighting), so both colours of a sighting come from
the same place. Sightings on pixels the restorer left alone (confidence 0: no reconstructed surface, the photo's
pixel unchanged) are dropped from both.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pipeline.evaluate.consistency import colour_consistency
from pipeline.job.layout import JobLayout
from pipeline.medium.estimate import Observations
from pipeline.restore.views import lens_cameras
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import LensCamera, Sightings, View

log = logging.getLogger(__name__)

GEOMETRY = ("the photos and their restored files at the photo's own resolution and lens geometry; each sparse "
            "sighting (SfM's undistorted image) carried into the photo through its lens model, one pixel read")


def photo_positions(view: View, sightings: Sightings, lens: LensCamera) -> np.ndarray:
    """Where ``sightings`` (pixels in ``view``'s undistorted PINHOLE image, ``sightings.width`` wide) lie in the
    photo of camera ``lens``: [K, 2] pixel-centre coordinates (NaN where the lens model cannot place one)."""
    cam = view.camera
    xy = sightings.xy * (cam.width / sightings.width)
    rays = np.stack([(xy[:, 0] - cam.cx) / cam.fx, (xy[:, 1] - cam.cy) / cam.fy, np.ones(len(xy))], 1)
    if len(rays) == 0:
        return np.zeros((0, 2))
    out = lens.colmap().img_from_cam(np.ascontiguousarray(rays, dtype=np.float64))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def restored_consistency(job: Path, files: dict[str, str]) -> dict:
    """The score of a job's restored photos (``files``: view name -> its file in ``restored/``) against its
    photos at the sparse model's sightings; the dict of :func:`~pipeline.evaluate.consistency.colour_consistency`
    plus ``geometry`` (how sightings and photos were matched) and ``n_views``."""
    layout = JobLayout(job)
    scene = load_scene(layout.scene)
    lenses = lens_cameras(layout.scene)
    points = np.asarray(scene.points, np.float64)
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for v in scene.views:
        s = (scene.sightings or {}).get(v.name)
        if s is None or v.name not in files or v.name not in lenses or len(s.point) == 0:
            continue
        photo = read_image(layout.images / v.name)
        restored = read_image(layout.restored / files[v.name])
        if photo.shape != restored.shape:
            log.warning("consistency: %s and its restored file differ in size (%s, %s); skipped", v.name,
                        photo.shape, restored.shape)
            continue
        H, W = photo.shape[:2]
        uv = photo_positions(v, s, lenses[v.name])
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        ids, u, w = s.point[ok], uv[ok, 0].astype(np.int64), uv[ok, 1].astype(np.int64)
        conf_path = layout.confidence / f"{Path(v.name).stem}.png"
        if conf_path.is_file():
            restored_here = read_image(conf_path)[w, u, 0] > 0
            ids, u, w = ids[restored_here], u[restored_here], w[restored_here]
        rng = np.linalg.norm(points[ids] - v.center, axis=1)
        parts.append((ids, rng, photo[w, u].astype(np.float64), restored[w, u].astype(np.float64)))
    if parts:
        ids, rng, pc, rc = (np.concatenate(x) for x in zip(*parts, strict=True))
    else:
        ids, rng, pc, rc = np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    res = colour_consistency(Observations(ids, rng, pc), Observations(ids, rng, rc))
    res.update(geometry=GEOMETRY, n_views=len(parts))
    log.info("colour consistency across distances: %s", f"restored {res['restored_score']:.3f}, photos "
             f"{res['photo_score']:.3f} (share {res['share']:.2f})" if res["defined"] else res["reason"])
    return res
