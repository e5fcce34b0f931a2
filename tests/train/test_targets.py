"""Training targets held as packed integers (pipeline.train.targets): 8-bit photos give back bit for bit the float
targets they were decoded to, averages are within UINT16_TOLERANCE, and a run on packed targets is the run on
floats."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.config import TrainConfig, rescheduled
from pipeline.scene.images import read_image, write_image
from pipeline.scene.records import Camera, View
from pipeline.train.setup import load_training_images
from pipeline.train.targets import UINT16_TOLERANCE, AsNumpy, PackedImages, pack_image, take, unpack_image
from pipeline.train.trainer import Trainer


def _png_views(tmp_path, n=3, w=64, h=48, bits=8):
    rng = np.random.default_rng(1)
    views = []
    for k in range(n):
        img = rng.random((h, w, 3)).astype(np.float32)
        img[0, :3] = [[0, 0, 0], [1, 1, 1], [128 / 255] * 3]  # the ends of the range and a mid level
        path = tmp_path / f"v{k}.png"
        write_image(path, img, bits=bits)
        views.append(View(path.name, Camera(w, h, 50.0, 50.0, w / 2, h / 2), np.eye(3), np.zeros(3), path))
    return views


def test_every_8bit_level_round_trips_bit_for_bit(tmp_path):
    levels = np.repeat((np.arange(256, dtype=np.float32) / 255)[None, :, None], 3, axis=2)  # [1, 256, 3]
    write_image(tmp_path / "levels.png", np.repeat(levels, 2, axis=0), bits=8)
    decoded = torch.from_numpy(read_image(tmp_path / "levels.png"))
    q = pack_image(decoded)
    assert q.dtype == torch.uint8 and torch.equal(q[0, :, 0], torch.arange(256, dtype=torch.uint8))
    assert torch.equal(unpack_image(q), decoded)  # the decoder's k x float32(1/255), not k / 255


def test_training_size_8bit_photos_are_stored_as_uint8_and_unpack_to_the_decoded_floats(tmp_path):
    views = _png_views(tmp_path)
    packed = load_training_images(views, 1)
    assert isinstance(packed, PackedImages) and packed.dtypes() == {"uint8": 3}
    assert packed.nbytes == 3 * 64 * 48 * 3  # a quarter of float32
    for view, t in zip(views, packed, strict=True):
        assert t.dtype == torch.float32 and torch.equal(t, torch.from_numpy(read_image(view.image_path)))
    assert torch.equal(packed.subset([2, 0])[0], packed[2]) and len(take(packed, [1])) == 1
    assert np.array_equal(AsNumpy(packed)[1], packed[1].numpy())


def test_averaged_and_16bit_images_are_uint16_within_the_tolerance(tmp_path):
    views = _png_views(tmp_path, bits=16)
    exact = load_training_images(views, 1)  # 16-bit at its size: exact
    assert exact.dtypes() == {"uint16": 3}
    assert all(torch.equal(t, torch.from_numpy(read_image(v.image_path))) for v, t in zip(views, exact, strict=True))
    half = load_training_images(_png_views(tmp_path / "..", bits=8), 2)  # 8-bit averaged 2x2: not on the grid
    assert half.dtypes() == {"uint16": 3}
    x = torch.rand(20, 30, 3, generator=torch.Generator().manual_seed(0))
    err = float((unpack_image(pack_image(x)) - x).abs().max())
    assert 0 < err <= UINT16_TOLERANCE + 1e-7, err


def test_bad_images_are_refused():
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        pack_image(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="NaN"):
        pack_image(np.full((2, 2, 3), np.nan))
    with pytest.raises(ValueError, match="uint8/uint16"):
        PackedImages([torch.zeros(2, 2, 3)])
    with pytest.raises(TypeError, match="uint8 or uint16"):
        unpack_image(torch.zeros(2, 2, 3))


def test_a_run_on_packed_targets_is_the_run_on_floats(small_medium_scene):
    scene, images = small_medium_scene  # 8-bit PNGs, 96x72
    cfg = rescheduled(TrainConfig(mode="dualphys", sh_degree=1), 12, checkpoint_every=0, max_gaussians=0)
    packed = PackedImages.pack(images)
    assert packed.dtypes() == {"uint8": len(images)}
    runs = []
    for imgs in (images, packed):
        tr = Trainer(scene, imgs, cfg)
        for _ in range(12):  # the medium is on from iteration 4
            tr.step()
        runs.append(tr)
    floats, small = runs
    assert isinstance(small.targets, PackedImages) and not isinstance(floats.targets, PackedImages)
    assert small.targets.packed[0].dtype == torch.uint8  # the trainer holds uint8, one view made float per step
    for k in floats.gaussians:
        assert torch.equal(floats.gaussians[k], small.gaussians[k]), k
    assert small.medium is not None and small.medium.active(12)
    assert all(r is small.medium.ray[0] for r in small.medium.ray)  # one camera: one ray map
