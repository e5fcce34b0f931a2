"""The train stage's images: read one at a time at the training size, what the trainer made of the full-size
images before (bit for bit when kept at their size, within UINT16_TOLERANCE when averaged down), and decoded to
linear light for colour_space "linear"."""

import numpy as np
import torch

from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.images import write_image
from pipeline.scene.records import Camera, View
from pipeline.train.setup import load_training_images, prepare_images
from pipeline.train.targets import UINT16_TOLERANCE


def _views(tmp_path, n=3, w=64, h=48):
    rng = np.random.default_rng(0)
    views = []
    for k in range(n):
        img = rng.random((h, w, 3)).astype(np.float32)
        path = tmp_path / f"v{k}.png"
        write_image(path, img, bits=16)
        views.append(View(path.name, Camera(w, h, 50.0, 50.0, w / 2, h / 2), np.eye(3), np.zeros(3), path))
    return views


def test_loaded_at_training_size_equals_the_trainers_own_shrink(tmp_path):
    from pipeline.scene.loader import load_view_image

    views = _views(tmp_path)
    full = [load_view_image(v) for v in views]
    for down in (1, 2, 4):
        small = load_training_images(views, down)
        v1, t1 = prepare_images(views, full, down, torch.device("cpu"))
        v2, t2 = prepare_images(views, small, down, torch.device("cpu"))
        assert [v.camera for v in v1] == [v.camera for v in v2]
        if down == 1:  # the 16-bit files kept at their size: bit for bit
            assert all(torch.equal(a, b) for a, b in zip(t1, t2, strict=True))
        else:  # averages held as uint16 (pipeline.train.targets)
            err = max(float((a - b).abs().max()) for a, b in zip(t1, t2, strict=True))
            assert 0 < err <= UINT16_TOLERANCE + 1e-7, err


def test_linear_light_is_decoded_before_averaging(tmp_path):
    from pipeline.scene.loader import load_view_image

    views = _views(tmp_path, n=1)
    lin = load_training_images(views, 2, "linear")[0].numpy()
    full = srgb_to_linear(load_view_image(views[0]).astype(np.float64))
    expect = full.reshape(24, 2, 32, 2, 3).mean(axis=(1, 3))
    assert np.abs(lin - expect).max() < 1e-6 + UINT16_TOLERANCE  # held as uint16
    srgb = load_training_images(views, 2, "srgb")[0].numpy()
    assert lin.mean() < srgb.mean() - 0.1  # decoding darkens mid-tones (0.5 -> 0.21)


def test_the_probe_shrinks_training_size_images_further(tmp_path):
    """The mode probe trains at its own, smaller size: images loaded at the job's training size (here half) must
    shrink again to it (a 400x300 real set at max_width 200 failed the probe before)."""
    views = _views(tmp_path, n=2, w=96, h=72)
    half = load_training_images(views, 2)
    v, t = prepare_images(views, half, 4, torch.device("cpu"))
    assert [tuple(x.shape) for x in t] == [(18, 24, 3)] * 2 and v[0].camera.width == 24
    import pytest

    with pytest.raises(ValueError, match="camera says"):
        prepare_images(views, [np.zeros((10, 10, 3), np.float32)] * 2, 4, torch.device("cpu"))
