"""A generated transect video (the procedural seabed, rendered along a dense path and encoded with PyAV) through
ingest and SfM: the keyframes register. The longer run (160 frames, 240x180) is bench/video.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pipeline.config import SynthConfig
from pipeline.ingest.intake import ingest
from pipeline.job.layout import JobLayout
from pipeline.sfm.config import SfmConfig
from pipeline.sfm.recipe import run_sfm
from pipeline.synth.video import VideoSynthConfig, generate_video, transect_poses


@pytest.fixture()
def one_torch_thread():
    """The ray caster's many small torch ops: on 2 shared cores, threads cost more than they give."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_transect_poses_are_smooth() -> None:
    cfg = VideoSynthConfig(frames=30, step=0.1)
    poses = transect_poses(cfg)
    centres = [c for _, c in poses]
    steps = [float(((b - a) ** 2).sum() ** 0.5) for a, b in zip(centres, centres[1:])]
    assert len(poses) == 30 and all(0.1 <= s < 0.12 for s in steps)  # 0.1 m along x plus the sway
    assert all(abs(c[2] - cfg.scene.altitude) < 1e-12 for c in centres)


@pytest.mark.slow
def test_a_generated_video_registers_in_sfm(tmp_path: Path, one_torch_thread) -> None:
    upload = tmp_path / "upload"
    upload.mkdir()
    cfg = VideoSynthConfig(scene=SynthConfig(width=240, height=180, supersample=1, views=80), frames=40, fps=10,
                           step=0.1)
    # 240x180, not 160x120: at 160x120 the last keyframe (one neighbour, ~270 SIFT features) saw too few
    # triangulated points to be tried, at qp 16 and 20 alike; at 240x180 all 9 register at qp 12, 16 and 20
    generate_video(cfg, upload / "transect.mp4")
    res = ingest(upload, tmp_path / "job")
    v = res.videos[0]
    assert v["frames_decoded"] == 40 and v["rejected"]["blur"] <= 2, v["rejected"]
    # 4 m flown over a 1.73 m footprint, a keyframe per 30 % of it: 8-9 frames
    assert 7 <= len(res.images) <= 11
    summary = run_sfm(JobLayout(tmp_path / "job").images, tmp_path / "scene", SfmConfig())
    assert summary.registered >= 0.9 * len(res.images), summary
    assert summary.mean_reproj_error_px < 1.0
