"""Video files in an upload or a survey set → keyframes written as images (PyAV, which ships its own FFmpeg).

The video is decoded frame by frame (never held whole); each frame is scaled by FFmpeg to a grey analysis frame
``analysis_width`` pixels wide for :class:`pipeline.ingest.keyframes.KeyframeSelector`, and only the frame that is
currently the best candidate is kept at full size, to be written as ``<stem>_<frame index, 6 digits>.jpg`` once
it is chosen (the name keeps the order and the source, so SfM's numbered-sequence rule matches the frames
sequentially). :class:`VideoReport` records what was decoded, kept (index, time, sharpness, overlap, why) and
rejected (counts by reason).

A file FFmpeg cannot open, one without a video stream (audio only) or without a decodable frame is a
:class:`VideoError` (the caller lists it as skipped); a stream that breaks off part way keeps the keyframes before
the break and records the error.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from pipeline.ingest.keyframes import REJECT_REASONS, Keyframe, KeyframeConfig, KeyframeSelector
from pipeline.scene.images import write_image

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = frozenset({".mp4", ".mov", ".m4v", ".avi", ".mkv", ".mts", ".m2ts"})
INDEX_DIGITS = 6  # frame indices in the written names: 10^6 frames is 9 hours at 30 fps
TICK_FRAMES = 250  # on_frames is called every this many decoded frames (progress, cancellation)


@dataclass(frozen=True)
class VideoConfig:
    """How videos are read (docs/DECISIONS.md, "Video keyframes")."""

    analysis_width: int = 320  # grey frames this wide (or the video's width, if smaller) for the selection maths
    max_frames: int = 18_000  # decode at most this many frames per video (10 min at 30 fps); the rest is unread
    max_keyframes: int = 400  # keep at most this many frames per video; decoding stops there
    jpeg_quality: int = 95
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)

    def __post_init__(self) -> None:
        if self.analysis_width < 16 or self.max_frames < 1 or self.max_keyframes < 1:
            raise ValueError("VideoConfig: analysis_width >= 16, max_frames >= 1 and max_keyframes >= 1 are needed")


class VideoError(ValueError):
    """A video that gives no frames; ``code`` is stable, the message says why (without server paths)."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass
class VideoReport:
    """One video's entry in ingest.json's ``videos`` block."""

    file: str  # as the user named it (relative to the upload or set)
    frames_decoded: int = 0
    fps: float = 0.0
    duration_s: float | None = None  # as the container declares it
    size: tuple[int, int] = (0, 0)  # width, height
    codec: str = ""
    creation_time: str | None = None  # the container's, ISO 8601 UTC, when it has one
    rotation: int = 0  # display rotation (degrees counter-clockwise) applied to the written frames
    kept: list[dict] = field(default_factory=list)  # {image, index, time, capture_time, sharpness, overlap, why}
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECT_REASONS, 0))
    stopped: str | None = None  # why decoding ended before the stream's end (a cap)
    error: str | None = None  # the decode error that cut the stream short, or why the video was skipped

    def to_json(self) -> dict:
        return asdict(self)


def is_video(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_EXTENSIONS


def extract_keyframes(path: Path, shown: str, images_dir: Path, stem: str, taken: dict[str, str],
                      cfg: VideoConfig = VideoConfig(), on_frames: Callable[[int], None] | None = None
                      ) -> VideoReport:
    """Decode ``path``, write its keyframes to ``images_dir`` as ``<stem>_<index>.jpg`` (names recorded in
    ``taken``: name → source), return the report. ``shown`` names the file in messages; ``on_frames(n)`` is
    called every TICK_FRAMES frames (it may raise to stop: a cancelled job). Raises VideoError when the video
    gives no frame at all."""
    import av  # lazy: PyAV loads FFmpeg only when a video is decoded or encoded

    report = VideoReport(file=shown)
    try:
        container = av.open(str(path), mode="r")
    except (av.FFmpegError, OSError, ValueError) as e:
        raise VideoError("unreadable_video", f"not a readable video: {_reason(e, path, shown)}") from None
    with container:
        if not container.streams.video:
            kinds = sorted({s.type for s in container.streams}) or ["no streams"]
            raise VideoError("no_video_stream", f"the file has no video stream ({', '.join(kinds)})")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"  # FFmpeg's frame threads: decoding is most of a video's ingest time
        rate = stream.average_rate or stream.guessed_rate
        report.fps = round(float(rate), 3) if rate else 0.0
        report.codec = stream.codec_context.name
        report.size = (stream.codec_context.width, stream.codec_context.height)
        if container.duration is not None:
            report.duration_s = round(container.duration / 1e6, 3)  # AV_TIME_BASE microseconds
        created = _creation_time({**container.metadata, **stream.metadata})
        report.creation_time = created.isoformat().replace("+00:00", "Z") if created else None
        _select(container, stream, report, images_dir, stem, taken, cfg, created, path, shown, on_frames)
    if report.frames_decoded == 0:
        raise VideoError("no_frames", f"no frame could be decoded{': ' + report.error if report.error else ''}")
    log.info("video %s: %d frames decoded, %d kept, rejected %s", shown, report.frames_decoded, len(report.kept),
             report.rejected)
    return report


def _select(container, stream, report: VideoReport, images_dir: Path, stem: str, taken: dict[str, str],
            cfg: VideoConfig, created: datetime | None, path: Path, shown: str,
            on_frames: Callable[[int], None] | None) -> None:
    import av  # lazy: PyAV loads FFmpeg only when a video is decoded or encoded

    selector = KeyframeSelector(cfg.keyframes, report.fps or 30.0)
    held = None  # (index, frame) of the best candidate so far, at full size

    def write(k: Keyframe, frame) -> None:
        name, n = f"{stem}_{k.index:0{INDEX_DIGITS}d}.jpg", 2
        while name in taken:  # a photo of the set already has this name
            name, n = f"{stem}_{k.index:0{INDEX_DIGITS}d}_{n}.jpg", n + 1
        _write_jpeg(images_dir / name, frame, cfg.jpeg_quality)
        taken[name] = f"{shown}#{k.index}"
        entry = {"image": name, "index": k.index, "time": round(k.time, 4), "capture_time": None,
                 "sharpness": round(k.sharpness, 4), "overlap": round(k.overlap, 4), "why": k.why}
        if created is not None:
            entry["capture_time"] = (created + timedelta(seconds=k.time)).isoformat().replace("+00:00", "Z")
        report.kept.append(entry)

    index = -1
    try:
        for frame in container.decode(stream):
            index += 1
            if index >= cfg.max_frames:
                report.stopped = f"max_frames: decoding stopped after {cfg.max_frames} frames"
                break
            report.frames_decoded = index + 1
            if on_frames is not None and report.frames_decoded % TICK_FRAMES == 0:
                on_frames(report.frames_decoded)
            t = float(frame.time) if frame.time is not None else index / (report.fps or 30.0)
            if index == 0:
                report.rotation = round(frame.rotation or 0) % 360
            grey = _analysis_grey(frame, cfg.analysis_width)
            offer = selector.offer(index, t, grey)
            if offer.kept is not None:
                write(offer.kept, frame if offer.kept.index == index else held[1])
                held = None
                if len(report.kept) >= cfg.max_keyframes:
                    report.stopped = f"max_keyframes: {cfg.max_keyframes} frames kept"
                    break
            if offer.hold and offer.kept is None:
                held = (index, frame)
    except (av.FFmpegError, OSError, ValueError, EOFError) as e:  # a broken stream: keep what came before
        report.error = f"decoding stopped after {index + 1} frame(s): {_reason(e, path, shown)}"
        log.warning("video %s: %s", shown, report.error)
    last = selector.finish() if report.stopped is None else None
    if last is not None and held is not None and held[0] == last.index:
        write(last, held[1])
    report.rejected = dict(selector.counts)


def _analysis_grey(frame, width: int) -> np.ndarray:
    """The frame as grey uint8 [h, w], ``width`` wide (never upscaled), scaled by FFmpeg's swscale (area)."""
    w = min(width, frame.width)
    h = max(2, round(frame.height * w / frame.width))
    return frame.reformat(width=w, height=h, format="gray", interpolation="AREA").to_ndarray()


def _write_jpeg(path: Path, frame, quality: int) -> None:
    """The frame upright: a phone's display matrix (``frame.rotation``, degrees counter-clockwise, as FFmpeg's
    av_display_rotation_get) is applied, as players and ``ffmpeg`` (autorotate) do; GoPro-style cameras record 0."""
    rgb = frame.to_ndarray(format="rgb24")  # [H, W, 3] uint8
    k = round((frame.rotation or 0) / 90) % 4
    write_image(path, np.ascontiguousarray(np.rot90(rgb, k)) if k else rgb, quality=quality)


def _creation_time(meta: dict) -> datetime | None:
    """The container's creation_time (MP4 'mvhd', as FFmpeg reports it) as an aware UTC datetime, else None."""
    text = meta.get("creation_time")
    if not text:
        return None
    try:
        t = datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        return None
    t = t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)
    return None if t.year < 1971 else t  # MP4's zero date (1904) or 1970: the camera's clock was not set


def _reason(e: Exception, path: Path, shown: str) -> str:
    """An FFmpeg error as a user reads it: its message, the server-side path replaced by the user's name."""
    text = getattr(e, "strerror", None) or str(e)
    return str(text).replace(str(path), shown)
