"""Lens distortion, pinhole companions and linear-light water of the scene generator (``pipeline.synth.lens``,
``pipeline.synth.procedural``, ``pipeline.synth.photo``), and the default output unchanged byte for byte.

Measured on the fixture scene (240x180, k1 = -0.15, 2 views; 3 views gave the same): sampling the pinhole
companion's clean image bilinearly at the undistorted position of each distorted pixel matches the distorted
clean image to a mean absolute difference of 0.0096-0.0121 (median 0.0020-0.0029; p99 0.09 at texture edges),
against 0.028-0.031 for the same comparison misregistered by one pixel; depth agrees to a median relative
difference of 2-6e-6. The tolerances below sit about 1.6x above the measured values.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from pipeline.config import SynthConfig
from pipeline.scene.colmap import qvec_to_rotmat
from pipeline.scene.colour import linear_to_srgb, srgb_to_linear
from pipeline.scene.images import read_image, read_pixels
from pipeline.scene.loader import default_undistort_cache, load_scene
from pipeline.synth.ground_truth import is_generated_scene, load_ground_truth
from pipeline.synth.lens import pixel_ray_factor, undistort_normalized
from pipeline.synth.photo import PhotoSynthConfig, default_textures_dir, generate_photo_scene
from pipeline.synth.procedural import generate_scene, make_camera
from pipeline.synth.water import WATER_PRESETS

K = (-0.15, 0.0)
CFG = SynthConfig(views=2, width=240, height=180, distortion=K, water_space="linear", noise_std=0.0, n_points=300)
NAMES = ("frame_0000.png", "frame_0001.png")


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return generate_scene(CFG, tmp_path_factory.mktemp("lens"))


def _read_model(sparse: Path):
    """(camera fields, {image name: (R, t, [(x, y, point id)])}, {point id: xyz}) of a generator text model."""
    cam = next(ln.split() for ln in (sparse / "cameras.txt").read_text().splitlines() if not ln.startswith("#"))
    lines = [ln for ln in (sparse / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    images = {}
    for head, obs in zip(lines[0::2], lines[1::2]):
        f = head.split()
        q, t = np.array(f[1:5], float), np.array(f[5:8], float)
        o = obs.split()
        obs_list = [(float(o[i]), float(o[i + 1]), int(o[i + 2])) for i in range(0, len(o), 3)]
        images[f[9]] = (qvec_to_rotmat(q), t, obs_list)
    points = {int(f[0]): np.array(f[1:4], float) for f in
              (ln.split() for ln in (sparse / "points3D.txt").read_text().splitlines() if not ln.startswith("#"))}
    return cam, images, points


def test_observations_are_projections_through_the_distortion(scene):
    cam, images, points = _read_model(scene / "sparse_gt")
    assert cam[1] == "RADIAL" and [float(x) for x in cam[4:]][3:] == list(K)
    colmap_cam = pycolmap.Camera(model="RADIAL", width=int(cam[2]), height=int(cam[3]),
                                 params=[float(x) for x in cam[4:]])
    n = 0
    for R, t, obs in images.values():
        xy = np.array([(x, y) for x, y, _ in obs])
        xc = np.stack([R @ points[p] + t for _, _, p in obs])
        assert np.abs(colmap_cam.img_from_cam(xc) - xy).max() < 1e-3  # text keeps 4 decimals
        n += len(obs)
    assert n > 200
    # the pinhole companion's model: same poses and points, observations through the ideal lens
    pcam, pimages, ppoints = _read_model(scene / "pinhole" / "sparse")
    assert pcam[1] == "PINHOLE" and set(ppoints) <= set(points)
    fx, fy, cx, cy = (float(x) for x in pcam[4:8])
    for name, (R, t, obs) in pimages.items():
        assert np.allclose(R, images[name][0]) and np.allclose(t, images[name][1])
        xc = np.stack([R @ ppoints[p] + t for _, _, p in obs])
        uv = np.stack([fx * xc[:, 0] / xc[:, 2] + cx, fy * xc[:, 1] / xc[:, 2] + cy], 1)
        assert np.abs(uv - np.array([(x, y) for x, y, _ in obs])).max() < 1e-3


def _bilinear(a: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample ``a`` at pixel-centre-convention positions (u, v) (top-left pixel centre at (0.5, 0.5))."""
    x, y = u - 0.5, v - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, a.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, a.shape[0] - 2)
    fx, fy = x - x0, y - y0
    if a.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    top = a[y0, x0] * (1 - fx) + a[y0, x0 + 1] * fx
    bottom = a[y0 + 1, x0] * (1 - fx) + a[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def test_pinhole_companion_resampled_matches_the_distorted_render(scene):
    cam = make_camera(CFG)
    v, u = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
    xn, yn = undistort_normalized(torch.as_tensor((u - cam.cx) / cam.fx), torch.as_tensor((v - cam.cy) / cam.fy), K)
    pu, pv = cam.fx * xn.numpy() + cam.cx, cam.fy * yn.numpy() + cam.cy  # where the pinhole image sees that ray
    inside = (pu >= 1.5) & (pu <= cam.width - 1.5) & (pv >= 1.5) & (pv <= cam.height - 1.5)
    assert 0.8 < inside.mean() < 0.95  # barrel: the distorted frame sees beyond the pinhole frame at the corners
    for name in NAMES:
        dist, pin = read_image(scene / "clean" / name), read_image(scene / "pinhole" / "clean" / name)
        err = np.abs(_bilinear(pin, pu, pv) - dist)[inside]
        shifted = np.abs(_bilinear(np.roll(pin, 1, axis=1), pu, pv) - dist)[inside]  # 1 px misregistered
        assert err.mean() < 0.02 and np.median(err) < 0.005, (err.mean(), np.median(err))
        assert err.mean() < 0.5 * shifted.mean()
        stem = Path(name).stem
        zd, zp = np.load(scene / "depth" / f"{stem}.npy"), np.load(scene / "pinhole" / "depth" / f"{stem}.npy")
        rel = (np.abs(_bilinear(zp, pu, pv) - zd) / zd)[inside]
        assert np.median(rel) < 1e-4 and rel.mean() < 1e-3


def test_load_scene_and_ground_truth_on_a_distorted_scene(scene):
    s = load_scene(scene)  # RADIAL: undistorted through pycolmap into the user's cache, not the scene folder
    assert [v.name for v in s.views] == list(NAMES)
    cache = default_undistort_cache(scene / "sparse_gt")
    assert all(v.image_path is not None and v.image_path.is_file() and v.image_path.parent == cache / "images"
               for v in s.views)
    assert not (scene / "_undistorted").exists()
    assert is_generated_scene(scene)
    gt = load_ground_truth(scene)
    v0 = gt.scene.views[0]
    assert gt.root == scene / "pinhole" and gt.original_root == scene
    assert (v0.camera.width, v0.camera.height, v0.camera.fx) == (240, 180, make_camera(CFG).fx)
    assert np.array_equal(gt.depth(v0), np.load(scene / "pinhole" / "depth" / "frame_0000.npy"))
    oc = gt.original_camera(v0.name)
    assert (oc.model, oc.width, oc.height) == ("RADIAL", 240, 180) and oc.params[3:] == K
    assert gt.clean_original(v0.name).shape == (180, 240, 3)
    assert np.array_equal(gt.depth_original(v0.name), np.load(scene / "depth" / "frame_0000.npy"))
    assert gt.water["water_space"] == "linear" and gt.water["camera_model"] == "RADIAL"


def test_linear_water_holds_in_linear_light(scene):
    water = WATER_PRESETS[CFG.preset]
    bd, bb, binf = (np.asarray(x) for x in (water.beta_D, water.beta_B, water.B_inf))
    ray = pixel_ray_factor(make_camera(CFG), K)
    for name in NAMES:
        I = read_image(scene / "images" / name).astype(np.float64)
        J = read_image(scene / "clean" / name).astype(np.float64)
        r = (np.load(scene / "depth" / f"{Path(name).stem}.npy") * ray)[..., None]
        predicted = srgb_to_linear(J) * np.exp(-bd * r) + binf * (1 - np.exp(-bb * r))
        err = np.abs(linear_to_srgb(predicted) - I)
        # 8-bit rounding of I and of J; measured max 0.85 DN, mean 0.28 DN (the sRGB-space model: ~31 DN off)
        assert err.max() < 1.0 / 255, err.max() * 255
        # the same in linear light: not the sRGB-space model
        wrong = np.abs(np.clip(J * np.exp(-bd * r) + binf * (1 - np.exp(-bb * r)), 0, 1) - I)
        assert wrong.mean() > 10 * err.mean()


_FLOAT = re.compile(rb"-?\d+\.\d+(?:[eE][-+]?\d+)?")


def _rounded(x: np.ndarray) -> np.ndarray:
    """Floats to 6 significant digits: what the generator computes, not the last bits of this CPU's arithmetic."""
    return np.asarray([float(f"{v:.6g}") for v in np.ravel(x)]) if x.dtype.kind == "f" else x


def _tree_hash(root: Path) -> str:
    """The scene's content: PNGs as their decoded 8-bit pixels (the encoded bytes carry the writer's version in a
    text chunk and its zlib's choices, which change with OpenImageIO releases); text and .npy files with every
    float to 6 significant digits (printed in full, their last digits differ between machines: the same code
    gave another hash on an AMD EPYC machine, while its files there equal 7b02e83's byte for byte)."""
    d = hashlib.sha256()
    for p in sorted(q for q in root.rglob("*") if q.is_file() and q.name not in SINCE):
        d.update(str(p.relative_to(root)).encode())
        if p.suffix == ".png":
            data = np.round(read_pixels(p) * 255).astype(np.uint8).tobytes()
        elif p.suffix == ".npy":
            data = _rounded(np.load(p)).tobytes()
        else:
            data = _FLOAT.sub(lambda m: f"{float(m.group()):.6g}".encode(), p.read_bytes())
        d.update(hashlib.sha256(data).digest())
    return d.hexdigest()


SINCE = {"water.json", "records.csv"}  # files that gained keys, or came, after BEFORE's hashes were taken

# Hashes of images/, clean/, depth/, sparse_gt/ (water.json left out: it gained keys) of 3-view 96x72 scenes made
# by the generator before distortion and water_space existed (commit 7b02e83, run again on 2026-11-27 to take
# these hashes of its output), repeated identically here.
BEFORE = {"procedural": "bc4995ead7213c404716e688556bd8f72d6740e0078ce3e33bece1f5f33a8e06",
          "photo": "84398a4afe346b961ce4d50f904c7eea779dd8f814b642c592036617e166aff5"}


def test_default_output_is_identical_to_before(tmp_path):
    generate_scene(SynthConfig(views=3, width=96, height=72), tmp_path / "p")
    assert _tree_hash(tmp_path / "p") == BEFORE["procedural"]
    assert not (tmp_path / "p" / "pinhole").exists()
    if default_textures_dir().is_dir():
        generate_photo_scene(PhotoSynthConfig(views=3, width=96, height=72), tmp_path / "f")
        assert _tree_hash(tmp_path / "f") == BEFORE["photo"]


def test_undistortion_matches_pycolmap():
    cam = make_camera(CFG)
    pc = pycolmap.Camera(model="RADIAL", width=cam.width, height=cam.height,
                         params=[cam.fx, cam.cx, cam.cy, -0.15, 0.03])
    uv = np.random.default_rng(0).uniform([0, 0], [cam.width, cam.height], (500, 2))
    xn, yn = undistort_normalized(torch.as_tensor((uv[:, 0] - cam.cx) / cam.fx),
                                  torch.as_tensor((uv[:, 1] - cam.cy) / cam.fy), (-0.15, 0.03))
    assert np.abs(np.stack([xn.numpy(), yn.numpy()], 1) - pc.cam_from_img(uv)).max() < 1e-9


def test_a_lens_that_folds_over_is_refused():
    with pytest.raises(ValueError, match="folds over"):
        generate_scene(SynthConfig(views=1, width=64, height=48, fov_deg=120.0, distortion=(-0.6, 0.0)), "/nonexistent")
