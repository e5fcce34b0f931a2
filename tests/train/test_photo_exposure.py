"""Every photo's exposure measured against the trained model (pipeline.train.photo_exposure): a plane of Gaussians
rendered as the model, photos of it taken at known gains, and the gains read back from the photos alone; a
training view's gains are corrected on top of what training used, and what the model gets wrong everywhere is not
exposure."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.scene.exposure import exposed
from pipeline.scene.records import Camera, View
from pipeline.splat.gaussians import init_from_points
from pipeline.train.model import TrainedModel
from pipeline.train.photo_exposure import MIN_PIXELS, measure_photo_exposure
from pipeline.train.render import render_outputs


def plane_model() -> tuple[TrainedModel, list[View]]:
    """A textured plane of opaque Gaussians at z = 3 filling two 48x36 views (plain splatting, no water)."""
    rng = np.random.default_rng(0)
    xs, ys = np.meshgrid(np.linspace(-2.5, 2.5, 60), np.linspace(-2, 2, 48))
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 3.0)], 1)
    g = init_from_points(pts, rng.uniform(0.15, 0.85, pts.shape), sh_degree=0, init_opacity=0.99, init_scale=1.5)
    cam = Camera(48, 36, 40.0, 40.0, 24.0, 18.0)
    views = [View(f"v{k}.png", cam, np.eye(3), np.array([0.1 * k, 0.0, 0.0])) for k in range(3)]
    return TrainedModel("3dgs", {k: p.detach() for k, p in g.items()}, None, 0, (0.0, 0.0, 0.0)), views


def render(model: TrainedModel, view: View) -> np.ndarray:
    with torch.no_grad():
        return render_outputs(model.gaussians, view, None, 0, "auto", model.background).I.astype(np.float64)


def test_gains_read_back_from_the_photos():
    model, views = plane_model()
    assert all(v.camera.width * v.camera.height >= MIN_PIXELS for v in views)
    true = np.log([[1.2, 1.1, 1.3], [0.85, 0.9, 0.8], [1.05, 1.0, 0.95]])
    photos = [np.clip(exposed(render(model, v), lg, "srgb"), 0, 1) for v, lg in zip(views, true, strict=True)]
    # training used 1.15 for v0 (5 % short) and 0.85 for v1; v2 was held out
    trained = {"v0.png": np.log([1.15, 1.1, 1.3]), "v1.png": np.log([0.85, 0.9, 0.8])}
    gains, info = measure_photo_exposure(model, views, photos, trained)
    # v0's correction (+4.3 %) and v1's (0) share an offset: what the model got wrong on both is not exposure
    offset = np.array([np.log(1.2 / 1.15) / 2, 0, 0])
    for v, lg in zip(views, true, strict=True):
        np.testing.assert_allclose(gains[v.name], lg - offset, atol=2e-3)
    assert info["not_measured"] == [] and 0.015 < info["max_correction"] < 0.03


def test_a_photo_the_model_does_not_cover_keeps_its_gains():
    model, views = plane_model()
    away = View("away.png", views[0].camera, np.eye(3), np.array([0.0, 0.0, 10.0]))  # behind the plane
    trained = {"v0.png": np.log([1.1, 1.0, 0.9])}
    gains, info = measure_photo_exposure(model, [views[0], away], [render(model, views[0]), np.full((36, 48, 3), 0.5)],
                                         trained)
    assert info["not_measured"] == ["away.png"]
    np.testing.assert_allclose(gains["away.png"], 0.0)
    np.testing.assert_allclose(gains["v0.png"], trained["v0.png"], atol=1e-9)  # its own offset is its correction
