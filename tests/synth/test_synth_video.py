"""A generated video's truth (``generate_video(..., truth=True)``, :mod:`pipeline.synth.video_truth`): one truth
per frame that matches the encoded frame and the camera path, found from the video as a job's source, and found
again by the names ingest gives the keyframes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.config import SynthConfig
from pipeline.ops.metrics import pooled_psnr
from pipeline.scene.images import read_image, write_image
from pipeline.scene.records import LensCamera, ray_length_factor
from pipeline.synth.ground_truth import find_ground_truth, is_generated_scene, load_ground_truth
from pipeline.synth.procedural import to_u8
from pipeline.synth.video import VideoSynthConfig, encode_video, generate_video, transect_poses
from pipeline.synth.water import WATER_PRESETS, underwater_image

FRAMES = 40
CFG = VideoSynthConfig(scene=SynthConfig(width=160, height=120, supersample=1, views=80, noise_std=0.0),
                       frames=FRAMES, fps=10, step=0.1)


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    """40 frames at 160x120 without sensor noise (so the water model can be checked to 8-bit rounding)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the ray caster's small torch ops: threads cost more than they give on 2 cores
    try:
        return generate_video(CFG, tmp_path_factory.mktemp("video-truth") / "transect.mp4", truth=True)
    finally:
        torch.set_num_threads(before)


def _decoded(path: Path) -> list[np.ndarray]:
    import av

    with av.open(str(path)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]


def test_every_frame_has_its_truth_at_the_path_pose(video: Path) -> None:
    root = video.parent
    names = [f"transect_{i:06d}" for i in range(FRAMES)]
    for sub, suffix in (("images", ".png"), ("clean", ".png"), ("depth", ".npy")):
        assert sorted(p.name for p in (root / sub).iterdir()) == [n + suffix for n in names], sub
    assert is_generated_scene(root)
    meta = json.loads((root / "water.json").read_text())
    assert meta["video"]["file"] == "transect.mp4" and meta["video"]["frames"] == FRAMES
    assert meta["beta_D"] == list(WATER_PRESETS["medium"].beta_D) and meta["camera_model"] == "PINHOLE"
    gt = load_ground_truth(root)
    assert [v.name for v in gt.scene.views] == [n + ".png" for n in names]
    for v, (R, c) in zip(gt.scene.views, transect_poses(CFG), strict=True):
        np.testing.assert_allclose(v.R, R, atol=1e-12)
        np.testing.assert_allclose(v.center, c, atol=1e-12)
    cam = gt.scene.views[0].camera
    assert (cam.width, cam.height, cam.cx, cam.cy) == (160, 120, 80.0, 60.0)


def test_written_frames_obey_the_water_model(video: Path) -> None:
    """images/ = the water model applied to clean/ at depth/ (distance along each pixel's ray), to the 8-bit
    rounding of both files (0.5 / 255 each)."""
    gt = load_ground_truth(video.parent)
    water = WATER_PRESETS["medium"]
    worst = 0.0
    for v in gt.scene.views[::7]:
        r = gt.depth_original(v.name) * ray_length_factor(v.camera)
        expected = underwater_image(gt.clean_original(v.name).astype(np.float64), r, water)
        worst = max(worst, float(np.abs(gt.photo(v) - expected).max()))
    assert worst <= 1.0 / 255 + 1e-6, worst * 255


def test_the_video_decodes_to_its_truth_frames(video: Path) -> None:
    """Frame i of the video is images/<stem>_i.png up to the codec (crf 16), and unlike its neighbours."""
    gt = load_ground_truth(video.parent)
    decoded = _decoded(video)
    assert len(decoded) == FRAMES
    own = [pooled_psnr([(f / 255.0, gt.photo(v))]) for f, v in zip(decoded, gt.scene.views, strict=True)]
    assert min(own) > 33.0, own
    neighbour = [pooled_psnr([(f / 255.0, gt.photo(v))]) for f, v in zip(decoded[:-1], gt.scene.views[1:])]
    assert max(neighbour) < min(own) - 8.0, (max(neighbour), min(own))


def test_the_truth_is_found_from_the_video(video: Path, tmp_path: Path) -> None:
    assert find_ground_truth(video) == video.parent
    assert find_ground_truth(video.parent / "images") == video.parent
    assert find_ground_truth(video.parent / "clean") is None  # only images/ or a video is a job's source
    elsewhere = tmp_path / "transect.mp4"
    shutil.copyfile(video, elsewhere)
    assert find_ground_truth(elsewhere) is None
    assert find_ground_truth(elsewhere, explicit=video.parent) == video.parent


def test_keyframes_are_scored_against_their_own_frames(video: Path, tmp_path: Path) -> None:
    """Ingest the video; each keyframe (``transect_<i>.jpg``) takes its frame's truth by name, and the
    full-resolution restoration score compares it with that frame: a perfect restoration (the clean frame)
    scores far above the photo."""
    from pipeline.ingest.intake import ingest
    from pipeline.job.layout import JobLayout
    from pipeline.restore.truth import score_restored

    job = tmp_path / "job"
    res = ingest(video, job)
    names = res.images
    assert 7 <= len(names) <= 11 and all(n.startswith("transect_") and n.endswith(".jpg") for n in names), names
    gt = load_ground_truth(video.parent, names)
    views = [v for v in gt.scene.views if v.name in set(names)]
    assert [v.name for v in views] == names  # every keyframe found its truth by its name
    layout = JobLayout(job)
    for v in views:  # the keyframe JPEG is its frame's photo, through the codec and JPEG q95
        assert pooled_psnr([(read_image(layout.images / v.name), gt.photo(v))]) > 30.0, v.name
    layout.restored.mkdir(parents=True)
    for v in views:
        write_image(layout.restored / f"{Path(v.name).stem}.png", gt.clean_original(v.name))
    cam = views[0].camera
    lens = LensCamera("PINHOLE", cam.width, cam.height, (cam.fx, cam.fy, cam.cx, cam.cy))
    scores = score_restored(job, video.parent, views, {v.name: lens for v in views},
                            {v.name: f"{Path(v.name).stem}.png" for v in views},
                            {v.name: gt.clean_original(v.name) for v in views})
    assert scores["test"]["n"] + scores["train"]["n"] == len(names)
    for split in ("test", "train"):
        assert scores[split]["restored_psnr"] == float("inf")  # the clean frame of the same index
        assert scores[split]["photo_psnr"] < 25.0, scores[split]  # the water is still in the photo


def test_encoding_the_same_frames_twice_gives_the_same_file(video: Path, tmp_path: Path) -> None:
    """A test video's keyframes, and the SfM run on them, must not change from run to run: with x264's rate control
    (crf, even on one thread) 5 encodes of these frames gave 5 different files, and a CI run lost a keyframe."""
    frames = [to_u8(read_image(p)) for p in sorted((video.parent / "images").iterdir())]
    assert len(frames) == FRAMES
    files = [encode_video(frames, tmp_path / f"again{k}.mp4", CFG.fps).read_bytes() for k in range(3)]
    assert files[0] == files[1] == files[2]
