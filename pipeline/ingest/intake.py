"""The ingest stage: an uploaded archive or a survey folder → ``job/images/`` (validated, EXIF-oriented).

Every candidate file is decoded (by content, not name). Readable images land in ``images/`` under a flat,
safe name (sub-folders become ``a__b__name``); JPEG/PNG files already in display orientation are copied
byte for byte, anything else (rotated by EXIF, TIFF, EXR, WebP, misnamed files) is written as PNG in display
orientation. Video files (:mod:`pipeline.ingest.video`) give their keyframes, written as
``<video>_<frame index>.jpg``, and an entry in ``videos``. Unreadable files (and videos that give no frame) are
skipped and listed with the reason; non-image files are ignored and listed, except CSV files, which are kept in
``records/`` as the survey's per-frame logs (the survey stage reads the one ``telemetry`` names).
Fewer than ``min_images`` usable images is an :class:`IngestError` (the caller maps it to a 4xx / exit 1).
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import unicodedata
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.ingest.archive import ArchiveLimits, extract_archive
from pipeline.ingest.video import VideoConfig, VideoError, extract_keyframes, is_video
from pipeline.job.layout import JobLayout
from pipeline.scene.images import ImageReadError, read_pixels, write_image

log = logging.getLogger(__name__)

MAX_RECORD_BYTES = 20_000_000  # a survey log of this size lists ~100k frames
NON_IMAGE_SUFFIXES = frozenset({".txt", ".md", ".csv", ".json", ".xml", ".yaml", ".yml", ".log", ".pdf", ".doc",
                                ".docx", ".html", ".py", ".sh", ".db", ".ini", ".cfg"})


class IngestError(ValueError):
    """A set that cannot become a job; ``code`` is stable, the message says why."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass
class IngestConfig:
    min_images: int = 3  # fewer usable images than this cannot make a reconstruction
    limits: ArchiveLimits = field(default_factory=ArchiveLimits)
    video: VideoConfig = field(default_factory=VideoConfig)  # keyframes from video files


@dataclass
class IngestResult:
    images: list[str]  # file names in job/images, sorted
    skipped: list[dict]  # {"file", "reason"}: looked like images but could not be decoded
    ignored: list[dict]  # {"file", "reason"}: not images (notes, hidden files ...)
    source: str
    videos: list[dict] = field(default_factory=list)  # per video file: pipeline.ingest.video.VideoReport

    def to_json(self) -> dict:
        return asdict(self)


def safe_name(rel: Path) -> str:
    """Flatten a relative path to one safe file name: NFC, sub-folders joined by '__', odd characters '_'."""
    parts = [unicodedata.normalize("NFC", p) for p in rel.parts]
    name = "__".join(parts)
    name = re.sub(r"[^\w.\-]", "_", name)
    return name.lstrip(".") or "image"


def _is_record(path: Path, rel: Path) -> bool:
    """A CSV beside the images, small enough to be a survey's per-frame log (``JobLayout.records``)."""
    return (path.suffix.lower() == ".csv" and not rel.name.startswith(".")
            and path.stat().st_size <= MAX_RECORD_BYTES)


def _probe(path: Path) -> tuple[str, int]:
    """(format name, EXIF orientation) from the header, by content; ("", 1) when OIIO does not know the file."""
    import OpenImageIO as oiio  # lazy: native image library, loaded only when a file is read or written

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        return "", 1
    try:
        return inp.format_name(), int(inp.spec().get_int_attribute("Orientation", 1))
    finally:
        inp.close()


def _candidates(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


def ingest(source: str | Path, job_dir: str | Path, cfg: IngestConfig | None = None,
           tick: Callable[[float, str], None] | None = None) -> IngestResult:
    """Run the stage: ``source`` is a folder of images (and videos), a zip/tar archive of them, or one video.
    Writes the job's images and ``JobLayout.ingest``; returns the result. Raises IngestError or
    pipeline.ingest.archive.ArchiveError. ``tick(fraction of files done, message)`` is called per video and while
    one decodes (it may raise to stop)."""
    cfg = cfg or IngestConfig()
    source, job_dir = Path(source), Path(job_dir)
    layout = JobLayout(job_dir)
    images_dir = layout.images
    for folder in (images_dir, layout.records):
        if folder.exists():
            shutil.rmtree(folder)  # a re-run starts clean: the marker was not written, so this is partial
    images_dir.mkdir(parents=True)
    ignored: list[dict] = []
    root, candidates = _gather(source, layout.unpacked, cfg.limits, ignored)
    written: dict[str, str] = {}
    skipped: list[dict] = []
    videos: list[dict] = []
    for i, path in enumerate(candidates):
        rel = path.relative_to(root)
        if _is_record(path, rel):  # a survey's telemetry log, for the survey stage's --telemetry
            layout.records.mkdir(exist_ok=True)
            shutil.copyfile(path, layout.records / safe_name(rel))
            ignored.append({"file": str(rel), "reason": f"not an image: kept as a survey record ({safe_name(rel)})"})
        elif rel.name.startswith(".") or path.suffix.lower() in NON_IMAGE_SUFFIXES:
            ignored.append({"file": str(rel), "reason": "not an image file"})
        elif is_video(path):
            say = None if tick is None else partial(tick, i / len(candidates))
            videos.append(_take_video(path, rel, images_dir, written, cfg.video, skipped, say))
        else:
            _take_image(path, rel, root, images_dir, written, skipped)
    if layout.unpacked.exists():
        shutil.rmtree(layout.unpacked)
    result = IngestResult(sorted(written), skipped, ignored, shown_source(source, job_dir), videos)
    if len(written) < cfg.min_images:
        why = f"{len(written)} usable image(s) found; at least {cfg.min_images} are needed"
        if skipped:
            why += f" ({len(skipped)} file(s) could not be decoded)"
        raise IngestError("too_few_images", why)
    layout.ingest.write_text(json.dumps(result.to_json(), indent=2))
    log.info("ingest: %d images (%d from %d videos), %d skipped, %d ignored", len(written),
             sum(len(v.get("kept", ())) for v in videos), len(videos), len(skipped), len(ignored))
    return result


def _gather(source: Path, unpacked: Path, limits: ArchiveLimits, ignored: list[dict]) -> tuple[Path, list[Path]]:
    """(the folder the input's files are named from, the files): a folder's files, one video, or an archive's
    files extracted to ``unpacked`` (its non-image members listed in ``ignored``). Raises IngestError."""
    if source.is_dir():
        return source, _candidates(source)
    if source.is_file() and is_video(source):  # one video as the whole input (`dualphys run dive.mp4`)
        return source.parent, [source]
    if source.is_file():
        if unpacked.exists():
            shutil.rmtree(unpacked)
        extracted = extract_archive(source, unpacked, limits)
        ignored += [{"file": n, "reason": why} for n, why in extracted.ignored]
        return unpacked, _candidates(unpacked)
    raise IngestError("no_input", f"no such file or folder: {source}")


def _take_video(path: Path, rel: Path, images_dir: Path, written: dict[str, str], cfg: VideoConfig,
                skipped: list[dict], say: Callable[[str], None] | None) -> dict:
    """Write the video's keyframes to ``images_dir`` (named in ``written``); returns its report, or its error
    (the video then also listed in ``skipped``). ``say(message)`` is the progress tick (it may raise to stop)."""
    on_frames = None
    if say is not None:
        say(f"video {rel}")
        on_frames = lambda n: say(f"video {rel}: {n} frames")  # noqa: E731
    try:
        report = extract_keyframes(path, str(rel), images_dir, Path(safe_name(rel)).stem, written, cfg, on_frames)
    except VideoError as e:
        skipped.append({"file": str(rel), "reason": str(e)})
        return {"file": str(rel), "error": str(e), "code": e.code}
    return report.to_json()


def _take_image(path: Path, rel: Path, root: Path, images_dir: Path, written: dict[str, str],
                skipped: list[dict]) -> None:
    """Decode the image whole; copy a JPEG/PNG in display orientation byte for byte, write anything else upright
    as PNG, and name it in ``written``; or list it in ``skipped`` with the decoder's reason."""
    try:
        px = read_pixels(path)  # full decode: catches truncated and corrupt files
    except ImageReadError as e:  # the decoder's message may quote the server-side path: name it as the user did
        skipped.append({"file": str(rel), "reason": _without_paths(e.reason, {path: rel, root: None})})
        return
    fmt, orientation = _probe(path)
    stem = Path(safe_name(rel)).stem
    if orientation == 1 and fmt in ("jpeg", "png"):
        name = _unique(f"{stem}.{'jpg' if fmt == 'jpeg' else 'png'}", written)
        shutil.copyfile(path, images_dir / name)
    else:
        name = _unique(f"{stem}.png", written)
        bits = 16 if px.dtype != np.uint8 and fmt in ("tiff", "png", "openexr") else 8
        rgb = px[:, :, :3] if px.shape[2] >= 3 else np.repeat(px[:, :, :1], 3, axis=2)
        write_image(images_dir / name, np.clip(rgb, 0, 1), bits=bits)
    written[name] = str(rel)


def shown_source(source: Path, job_dir: Path) -> str:
    """How ``ingest.json`` names the input: relative to the job folder when it lies inside (an upload, a survey
    set's copy), else its own name. Never an absolute path: ingest.json is handed to the service's clients."""
    try:
        return Path(source).resolve().relative_to(Path(job_dir).resolve()).as_posix()
    except ValueError:
        return Path(source).name


def _without_paths(text: str, paths: dict[Path, Path | None]) -> str:
    """``text`` with each absolute path in ``paths`` replaced by its relative name (or removed, for None)."""
    for path, rel in paths.items():
        text = text.replace(str(path) + "/", "" if rel is None else f"{rel}/").replace(str(path), str(rel or "."))
    return text


def _unique(name: str, taken: dict[str, str]) -> str:
    if name not in taken:
        return name
    stem, suffix = name.rsplit(".", 1)
    k = 2
    while f"{stem}_{k}.{suffix}" in taken:
        k += 1
    return f"{stem}_{k}.{suffix}"
