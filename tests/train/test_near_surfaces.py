"""In camera-like turbid water no surface may be drawn in front of the seabed (the near side of
``depth_band_loss``; docs/DECISIONS.md, "A surface in front of the seabed").

A surface at 0.4-0.8 of the seabed's range shows a veiled photo as well as the true one once its colour takes
up the veil no longer in front of it, and the restored view then has grey patches over dark seabed. The job's
photo-textured turbid scenes (320x240, through SfM) rendered 10-58 % of each training view so. Here the same
kind of scene at test size, trained on its true cameras and points (no SfM, so the test measures training
alone), in linear light as the job does by default.

Measured when written (16 views 200x150, seed 0, 1,500 iterations, homogeneous; share of a training view's
covered pixels rendered nearer than 0.8 of the true depth, mean over views / worst view), in both of numba's
cache states (freshly compiled rasterizer kernels train a slightly different model than cached ones: docs/RESULTS.md,
"The demo"):
with the near side 0.7 % / 8.0 % (cached), 3.6 % / 21.8 % (fresh, as on CI); switched off (``near`` 1e9)
14.5 % / 53.9 % (cached), 10.1 % / 40.7 % (fresh). About 2 min on a loaded 2-core machine.

Why the cut is now 0.7 of the true depth, not 0.8 (session 24): the band lets a surface lie at 1/``NEAR_BAND``
= 0.91 of the points' range map, and that map is itself 0.89-1.13 of the true range, so a surface at ~0.81 of
the truth is one the loss permits. With the near side on, the oblique views' foregrounds spread over 0.8-0.95,
and the share under 0.8 swung with float rounding: 1.4 % / 6.1 % (cached kernels) and 2.5 % / 10.3 % (fresh)
on one machine, 6.7 % / 27 % in a CI run of the same code (which failed this test's old floors, 6 % / 32 %), and
6.4 % / 24 % with freshly compiled kernels for a generic CPU (``NUMBA_CPU_NAME=generic``: other machine code,
other rounding), which reproduces the CI run. The failure guarded against lies well in front: with the near
side off, 17-41 % of an oblique view's pixels are nearer than 0.5 of the truth.

Under 0.7 (mean / worst view), seed 0: near side on 0.06 % / 0.6 % (cached), 0.6 % / 2.2 % (fresh), 4.0 % /
18.0 % (fresh, generic CPU: the worst state seen; 8 % of one view still nearer than 0.5); seeds 1-3 cached at
most 0.3 % / 3.5 %. Near side off: 17.0 % / 66.6 % (cached), 18.9 % / 68.9 % (fresh, generic CPU). The floors
sit about 2x from both. That the near side holds the foreground only loosely in some float states is a
weakness of the loss, recorded in docs/DECISIONS.md ("A surface in front of the seabed").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.job.options import JobOptions
from pipeline.scene.loader import load_scene
from pipeline.scene.split import split_views
from pipeline.synth.photo import PhotoSynthConfig, default_textures_dir, generate_photo_scene
from pipeline.train.render import render_view
from pipeline.train.resolve import resolve_train_config
from pipeline.train.setup import load_training_images
from pipeline.train.trainer import train

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not default_textures_dir().is_dir(),
                                 reason="shared/data/textures/euvp-gtr-a is not beside the repository")]

NEAR = 0.7  # a covered pixel nearer than this share of the true depth counts as drawn in front of the seabed
#            (outside what the near band permits: module docstring)
EDGE = 0.8  # the old cut, at the band's own tolerance: its share is recorded, not asserted
MEAN_SHARE, WORST_SHARE = 0.09, 0.4  # measured up to 0.040 and 0.180; without the near side >= 0.170 and 0.666


def test_turbid_water_draws_no_surface_in_front_of_the_seabed(tmp_path, record_property):
    W, H = 200, 150
    root = generate_photo_scene(PhotoSynthConfig(views=16, width=W, height=H, preset="turbid", seed=0,
                                                 water_space="linear"), tmp_path / "scene")
    scene = load_scene(root)  # the generator's true cameras and points (sparse_gt)
    train_views, _ = split_views(scene.views)
    ts = scene.subset(train_views)
    opts = JobOptions(source=str(root / "images"), iterations=1500, mode="homogeneous", colour_space="linear")
    cfg = resolve_train_config(opts, W, None, None, len(scene.views))
    res = train(ts, load_training_images(ts.views, 1, "linear"), cfg)
    shares, edge = [], []
    for v in ts.views:
        with torch.no_grad():
            out = render_view(res.gaussians, v, sh_degree=0, render_mode="RGB+ED")
        z, alpha = out.depth[..., 0].numpy(), out.alpha[..., 0].numpy()
        truth = np.load(root / "depth" / f"{Path(v.name).stem}.npy")
        seen = (alpha > 0.5) & (truth < 50)  # covered pixels on the seabed
        assert seen.mean() > 0.5, (v.name, float(seen.mean()))  # the scene is there (oblique views: its near half)
        zs, ts_ = z[seen], truth[seen]
        shares.append(float(np.mean(zs < NEAR * ts_)))
        edge.append(float(np.mean(zs < EDGE * ts_)))
    mean, worst = float(np.mean(shares)), max(shares)
    result = {"mean": round(mean, 4), "worst": round(worst, 4), "shares": [round(x, 3) for x in shares],
              "under_edge": [round(x, 3) for x in edge], "gaussians": int(res.gaussians["means"].shape[0])}
    record_property("result", result)
    assert mean <= MEAN_SHARE and worst <= WORST_SHARE, result
