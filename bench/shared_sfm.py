"""Two jobs on one SfM model: the benches' way of comparing what differs in the photos alone.

Between two SfM runs of a 320x240 generated scene the restoration moves by 2-3 dB (the model's scale, the points,
the split of the views); an effect smaller than that is only seen when both arms share the cameras and points.
:func:`share_sfm` makes a job that is another job after SfM, with other photos of the same views (same names) in
its ``images/`` and undistorted through the same model. The copy keeps the first job's options' source, so its
ingest and SfM markers still match; give it its own ``ground_truth``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.sfm.config import SfmConfig
from pipeline.sfm.recipe import undistort_model


def share_sfm(job: Path, other: Path, photos: Path) -> None:
    """Make ``other`` a copy of ``job`` (ingest and SfM done) whose photos are ``photos``' files of the same names.
    Nothing is done when ``other`` already holds its SfM marker (a resumed bench)."""
    if JobLayout(other).marker("sfm").is_file():
        return
    shutil.rmtree(other, ignore_errors=True)
    shutil.copytree(job, other)
    lay = JobLayout(other)
    for photo in lay.images.iterdir():  # ingest keeps a generated scene's names and PNGs
        shutil.copyfile(photos / photo.name, photo)
    scene = lay.scene  # the undistorted model is rewritten as the SfM stage writes it (the same cameras)
    shutil.rmtree(scene / "images")
    shutil.rmtree(scene / "sparse")
    undistort_model(scene / "distorted" / "sparse" / "0", lay.images, scene, lay.root / "_undistort", SfmConfig())
