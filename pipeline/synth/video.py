"""A generated survey video: the procedural seabed (:mod:`.procedural`) filmed along a dense, smooth transect and
encoded with PyAV (H.264 through libx264 when the wheel has it, else MPEG-4 part 2), the library ingest decodes
with.

Path (world: metres, z up): the camera looks straight down from ``scene.altitude`` and flies along +x at ``step``
metres per frame, centred on the seabed the scene's world covers, with a slow sideways sway (±``sway`` m) and
yaw (±4°) so that consecutive frames are not pure translations. Frames are rendered one at a time and encoded as
they come (bounded memory). With ``truth`` the folder of the video also gets every frame's truth (clean radiance,
depth, true camera, water: :mod:`.video_truth`), so a job on the video is scored like one on a generated scene.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.config import SynthConfig
from pipeline.scene.records import View
from pipeline.synth.lens import pixel_ray_factor
from pipeline.synth.path import look_rotation
from pipeline.synth.procedural import NO_DISTORTION, SynthView, build_world, make_camera, render, to_u8, water_image
from pipeline.synth.video_truth import VideoTruthWriter, frame_name, frame_stem
from pipeline.synth.water import WATER_PRESETS

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


def render_transect(cfg: VideoSynthConfig, stem: str = "frame") -> Iterator[SynthView]:
    """The frames along the transect, one at a time: view ``<stem>_<index, 6 digits>.png``, J, depth and the
    underwater image (float, unquantised; :func:`~pipeline.synth.procedural.to_u8` gives what is encoded)."""
    scene = cfg.scene
    world, cam = build_world(scene), make_camera(scene)
    ray = pixel_ray_factor(cam, NO_DISTORTION)
    water, rng = WATER_PRESETS[scene.preset], np.random.default_rng(scene.seed + 7919)
    for i, (R, c) in enumerate(transect_poses(cfg)):
        view = View(name=frame_name(stem, i), camera=cam, R=R, t=-R @ c)
        J, z = render(world, view, max(1, scene.supersample))
        yield SynthView(view, J, z, water_image(J, z * ray, water, scene.water_space, scene.noise_std, rng))


def encode_video(frames: Iterable[np.ndarray], path: str | Path, fps: int, codec: str = "auto") -> Path:
    """Encode uint8 RGB frames [H, W, 3] (even H and W) to ``path`` (MP4 / MOV by its extension); returns it."""
    import av  # lazy: PyAV loads FFmpeg only when a video is decoded or encoded

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
                # near-lossless: the frames are test data, compression artefacts are not what is tested.
                # Reproducible: the same frames must give the same file, or a test video's keyframes and their SfM
                # change from run to run. x264's frame threads broke that (one thread now), and so did its
                # rate control: with crf, even one thread, 5 encodes of the same 40 frames gave 5 different files
                # (its lookahead/mbtree); a constant quantiser gave the same bytes every time.
                stream.options = {"qp": "16", "threads": "1"} if codec == "libx264" else {}
                stream.codec_context.thread_count = 1
                if codec != "libx264":
                    stream.bit_rate = 8 * arr.shape[0] * arr.shape[1] * fps
            for packet in stream.encode(av.VideoFrame.from_ndarray(arr, format="rgb24")):
                out.mux(packet)
        if stream is None:
            raise ValueError("encode_video: no frames")
        for packet in stream.encode():
            out.mux(packet)
    return path


def generate_video(cfg: VideoSynthConfig, path: str | Path, truth: bool = False) -> Path:
    """Render the transect and encode it to ``path``; with ``truth``, also write each frame's truth into the
    video's folder as it is rendered (:mod:`.video_truth`). The video is the same either way."""
    path = Path(path)
    frames = render_transect(cfg, frame_stem(path))
    writer = VideoTruthWriter(path.parent, cfg) if truth else None
    if writer is not None:
        frames = writer.passing(frames)
    out = encode_video((to_u8(sv.image) for sv in frames), path, cfg.fps, cfg.codec)
    if writer is not None:
        writer.finish(out)
    log.info("wrote a %d-frame survey video to %s%s", cfg.frames, out, " with its truth" if truth else "")
    return out
