"""Small JPEG previews of a job's photos and of their restored versions, for the dashboard's gallery.

The photos are not results (nobody downloads back what they uploaded) and a restored photo may be 27 MP or a
16-bit TIFF no browser shows, so the dashboard asks for a preview instead: at most ``MAX_SIDE`` pixels on the
long side, area-averaged, 8-bit JPEG. Each is made on first request and kept in ``JobLayout.previews`` (a hidden
folder: never listed as an artifact); a source newer than its preview makes it again.
"""

from __future__ import annotations

import logging
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.scene.images import list_images, read_image, resize_area, write_image

log = logging.getLogger(__name__)

MAX_SIDE = 640
QUALITY = 85
KINDS = ("original", "restored")


def _source(layout: JobLayout, kind: str, stem: str) -> Path | None:
    """The file behind a preview: the job's photo (once ingest is done) or its restored version (once restore is)."""
    folder, stage = (layout.images, "ingest") if kind == "original" else (layout.restored, "restore")
    if not layout.marker(stage).is_file() or not folder.is_dir():
        return None
    return next((p for p in list_images(folder) if p.stem == stem and not p.is_symlink()), None)


def preview(job_dir: Path, kind: str, stem: str) -> Path | None:
    """The preview JPEG of photo ``stem`` (its file name without the extension), made if missing or stale;
    None when the job has no such photo (yet)."""
    if kind not in KINDS or not stem or "/" in stem or "\\" in stem or stem.startswith("."):
        return None
    layout = JobLayout(job_dir)
    src = _source(layout, kind, stem)
    if src is None:
        return None
    out = layout.previews / kind / f"{stem}.jpg"
    if out.is_file() and out.stat().st_mtime >= src.stat().st_mtime:
        return out
    img = read_image(src)
    scale = MAX_SIDE / max(img.shape[:2])
    if scale < 1.0:
        img = resize_area(img, scale)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_image(out, img, bits=8, quality=QUALITY)
    log.info("preview of %s (%s): %dx%d", src.name, kind, img.shape[1], img.shape[0])
    return out
