"""The truth of a generated video (:mod:`pipeline.synth.video`), written beside it as a generated scene folder.

The folder that holds ``transect.mp4`` gets the layout of :mod:`pipeline.synth.procedural`, one entry per frame
of the video::

    images/      the frame as encoded (before the codec), 8-bit PNG   transect_000123.png
    clean/       its clean radiance J, 8-bit PNG                      transect_000123.png
    depth/       its camera-space z in metres, float32 .npy           transect_000123.npy
    sparse_gt/   COLMAP text model of the true PINHOLE cameras (no points: tracks would need every depth map at
                 once, and nothing that scores a job reads them)
    water.json   the true water, the generator's config (``generator``) and the video's file name (``video``)

Frame ``i`` is named ``<stem>_<i, 6 digits>``, with ``<stem>`` what ingest makes of the video's file name, so the
keyframe ingest writes for frame ``i`` (``transect_000123.jpg``) has the stem of its truth; the ground truth
(:mod:`pipeline.synth.ground_truth`) matches a job's views to true views by stem. Frames are written as they
are rendered: only the poses are kept (bounded memory).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.config import to_dict
from pipeline.ingest.intake import safe_name
from pipeline.ingest.video import INDEX_DIGITS
from pipeline.scene.records import View
from pipeline.synth.procedural import NO_DISTORTION, SynthView, lens_and_space_meta, write_colmap_text, write_views
from pipeline.synth.water import TRUE_WATER_FILE, WATER_PRESETS

if TYPE_CHECKING:
    from pipeline.synth.video import VideoSynthConfig

log = logging.getLogger(__name__)


def frame_stem(video: str | Path) -> str:
    """The stem of the frames' truth files: the prefix ingest gives the keyframes of ``video`` when the video is
    the job's source or sits at the top of the source folder (``pipeline.ingest.intake.safe_name``)."""
    return Path(safe_name(Path(Path(video).name))).stem


def frame_name(stem: str, index: int) -> str:
    """Frame ``index``'s truth file name; the same digits as ingest's keyframe names, so the stems agree."""
    return f"{stem}_{index:0{INDEX_DIGITS}d}.png"


class VideoTruthWriter:
    """Writes each frame's truth as it passes (:meth:`passing`), then the cameras and the water (:meth:`finish`)."""

    def __init__(self, out: str | Path, cfg: VideoSynthConfig):
        self.out, self.cfg = Path(out), cfg
        self.views: list[View] = []  # poses only: the frames' pixels are on disk once written

    def passing(self, frames: Iterable[SynthView]) -> Iterator[SynthView]:
        """``frames`` unchanged, each written to images/, clean/, depth/ before it is handed on."""
        for sv in frames:
            write_views(self.out, [sv])
            self.views.append(sv.view)
            yield sv

    def finish(self, video: Path) -> Path:
        """sparse_gt/ and water.json for the frames written; returns the truth folder."""
        if not self.views:
            raise ValueError("VideoTruthWriter.finish: no frame was written")
        write_colmap_text(self.out / "sparse_gt", self.views, np.zeros((0, 3)), np.zeros((0, 3)), [])
        scene = self.cfg.scene
        centres = np.stack([v.center for v in self.views])
        meta = {
            "preset": scene.preset,
            **WATER_PRESETS[scene.preset].to_json(),
            "model": "I = J*exp(-beta_D*r) + B_inf*(1-exp(-beta_B*r)), r = depth * ray_length_factor",
            **lens_and_space_meta(NO_DISTORTION, scene.water_space, max(1, scene.supersample)),
            "depth": "camera-space z in metres (depth/*.npy); r is the distance along the pixel's ray",
            "world": "metres, z up, seabed near z = 0; poses in sparse_gt are cam_from_world",
            "video": {"file": video.name, "frames": len(self.views),
                      "names": "frame i is <stem>_<i, 6 digits> in images/, clean/, depth/ and sparse_gt/; "
                               "ingest names its keyframe <stem>_<i, 6 digits>.jpg"},
            "generator": to_dict(self.cfg),
            "path_length_m": float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()),
        }
        (self.out / TRUE_WATER_FILE).write_text(json.dumps(meta, indent=2))
        log.info("wrote the truth of %d frames of %s to %s", len(self.views), video.name, self.out)
        return self.out


__all__ = ["VideoTruthWriter", "frame_name", "frame_stem"]
