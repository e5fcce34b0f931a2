"""Incremental mapping for the SfM recipe: COLMAP's thresholds, the relaxed ones of the retry ladder, and the
continuation of a kept model (``pipeline.sfm.recipe``; the ladder: docs/DECISIONS.md, "Registering the survey").

The mapper is seeded and runs on ``cfg.num_threads`` (1 by default: the model repeats bit for bit).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

from pipeline.sfm.config import SfmConfig

log = logging.getLogger(__name__)

MIN_MODEL_IMAGES = 3  # pycolmap never built a model from 2 views (docs/DECISIONS.md, "Numbers behind code comments")

# The retry ladder's mapper thresholds (COLMAP's defaults in the comments). A frame seen by few features, or
# matched across a large viewpoint change, has fewer 2D-3D inliers than COLMAP asks for before it adds a frame
# (30 and a quarter of the matches) or starts a model (100 inliers, 16 degrees between the first two views).
# Halved, a dropped frame may enter; the reprojection filter (4 px) is unchanged, so a wrong pose still loses its
# points. More tries per frame, since each tried frame costs only a RANSAC.
RELAXED_MAPPER = {
    "init_min_num_inliers": 50,  # 100
    "init_min_tri_angle": 8.0,  # 16 degrees
    "abs_pose_min_num_inliers": 15,  # 30
    "abs_pose_min_inlier_ratio": 0.15,  # 0.25
    "max_reg_trials": 6,  # 3
}
RELAXED_MIN_NUM_MATCHES = 10  # pairs with fewer verified matches are not used by the mapper (COLMAP: 15)


def mapper_options(cfg: SfmConfig, *, relaxed: bool = False) -> Any:
    """Seeded ``IncrementalPipelineOptions``: COLMAP's thresholds, or the ladder's :data:`RELAXED_MAPPER` ones."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.mapper.random_seed = cfg.seed
    opts.triangulation.random_seed = cfg.seed
    # Default 10 would discard every model of a small set; we pick the largest model ourselves anyway.
    opts.min_model_size = max(MIN_MODEL_IMAGES, min(opts.min_model_size, cfg.min_registered))
    if relaxed:
        for k, v in RELAXED_MAPPER.items():
            setattr(opts.mapper, k, v)
        opts.min_num_matches = RELAXED_MIN_NUM_MATCHES
    return opts


def map_models(
    db_path: Path, image_dir: Path, work: Path, cfg: SfmConfig, token: Any, *, relaxed: bool = False,
    start_from: Path | None = None,
) -> list:
    """Incremental mapping: the models with registered images, largest first (ties: the first built).

    ``start_from`` (a model folder) continues that model instead of starting from nothing: the mapper tries to
    register the database's other images into it (and may start further models from what remains)."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    opts = mapper_options(cfg, relaxed=relaxed)
    tmp = work / "_models"
    tmp.mkdir()
    try:
        recs = pycolmap.incremental_mapping(db_path, image_dir, tmp, options=opts,
                                            input_path=str(start_from) if start_from else "",
                                            cancellation_token=token)  # fmt: skip
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    recs = [recs[k] for k in sorted(recs) if recs[k].num_reg_images() > 0]
    recs.sort(key=lambda r: -r.num_reg_images())  # stable: equal sizes keep the mapper's order
    if len(recs) > 1:
        log.info("sfm: %d separate models (%s images); keeping the largest", len(recs),
                 ", ".join(str(r.num_reg_images()) for r in recs))  # fmt: skip
    return recs
