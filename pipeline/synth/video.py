"""A generated survey video: the procedural seabed (:mod:`.procedural`) filmed along a dense, smooth transect and
encoded with PyAV (H.264 through libx264 when the wheel has it, else MPEG-4 part 2), the library ingest decodes
with.

Path (world: metres, z up): the camera looks straight down from ``scene.altitude`` and flies along +x at ``step``
metres per frame, centred on the seabed the scene's world covers, with a slow sideways sway (±``sway`` m) and
yaw (±4°) so that consecutive frames are not pure translations. Frames are rendered one at a time and encoded as
they come (bounded memory).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.config import SynthConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoSynthConfig:
    scene: SynthConfig = field(default_factory=lambda: SynthConfig(width=320, height=240, supersample=1))
    frames: int = 120  # frames in the video
    fps: int = 10
    step: float = 0.03  # m flown per frame (0.3 m/s at 10 fps: a slow ROV)
    sway: float = 0.1  # m, amplitude of the sideways sway
    codec: str = "auto"  # auto: libx264 when available, else mpeg4


def transect_poses(cfg: VideoSynthConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R cam_from_world, centre) per frame along the module docstring's transect."""
    from pipeline.synth.path import look_rotation

    length = cfg.step * (cfg.frames - 1)
    poses = []
    for i in range(cfg.frames):
        u = i / max(1, cfg.frames - 1)
        x = -length / 2 + cfg.step * i
        y = cfg.sway * math.sin(2 * math.pi * u)
        yaw = math.radians(4.0) * math.sin(3 * math.pi * u)
        heading = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        r = look_rotation(np.array([0.0, 0.0, -1.0]), heading)
        poses.append((r, np.array([x, y, cfg.scene.altitude])))
    return poses


def render_frames(cfg: VideoSynthConfig) -> Iterator[np.ndarray]:
    """The underwater frames (uint8 [H, W, 3]) along the transect, one at a time."""
    from pipeline.scene.records import View
    from pipeline.synth.lens import pixel_ray_factor
    from pipeline.synth.procedural import NO_DISTORTION, build_world, make_camera, render, water_image
    from pipeline.synth.water import WATER_PRESETS

    scene = cfg.scene
    world, cam = build_world(scene), make_camera(scene)
    ray = pixel_ray_factor(cam, NO_DISTORTION)
    water, rng = WATER_PRESETS[scene.preset], np.random.default_rng(scene.seed + 7919)
    for i, (R, c) in enumerate(transect_poses(cfg)):
        view = View(name=f"frame_{i:06d}.png", camera=cam, R=R, t=-R @ c)
        J, z = render(world, view, max(1, scene.supersample))
        img = water_image(J, z * ray, water, scene.water_space, scene.noise_std, rng)
        yield np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


def encode_video(frames: Iterable[np.ndarray], path: str | Path, fps: int, codec: str = "auto") -> Path:
    """Encode uint8 RGB frames [H, W, 3] (even H and W) to ``path`` (MP4 / MOV by its extension); returns it."""
    import av

    if codec == "auto":
        codec = "libx264" if "libx264" in av.codecs_available else "mpeg4"
    path = Path(path)
    with av.open(str(path), mode="w") as out:
        stream = None
        for arr in frames:
            if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] % 2 or arr.shape[1] % 2:
                raise ValueError(f"encode_video needs uint8 [H, W, 3] frames with even H and W, got "
                                 f"{arr.dtype} {arr.shape}")
            if stream is None:
                stream = out.add_stream(codec, rate=fps)
                stream.width, stream.height, stream.pix_fmt = arr.shape[1], arr.shape[0], "yuv420p"
                # near-lossless: the frames are test data, compression artefacts are not what is tested
                stream.options = {"crf": "16"} if codec == "libx264" else {}
                if codec != "libx264":
                    stream.bit_rate = 8 * arr.shape[0] * arr.shape[1] * fps
            for packet in stream.encode(av.VideoFrame.from_ndarray(arr, format="rgb24")):
                out.mux(packet)
        if stream is None:
            raise ValueError("encode_video: no frames")
        for packet in stream.encode():
            out.mux(packet)
    return path


def generate_video(cfg: VideoSynthConfig, path: str | Path) -> Path:
    """Render the transect and encode it to ``path``."""
    out = encode_video(render_frames(cfg), path, cfg.fps, cfg.codec)
    log.info("wrote a %d-frame survey video to %s", cfg.frames, out)
    return out
