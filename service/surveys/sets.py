"""A survey folder's images and the sets they form (pure: no job, no survey state but the caches handed in).

Grouping rule (also in docs/SERVICE.md):

- Every immediate sub-folder of the survey folder is one set (all images below it, at any depth).
- Images lying directly in the survey folder are ordered by capture time and split into sets wherever two
  consecutive images are more than ``survey_gap_s`` apart; a set is named after its first capture time
  (``%Y%m%dT%H%M%SZ``, UTC). The capture time is the image's EXIF capture time (:mod:`.exif`; a set name may then
  be the camera's local time labelled ``Z``; gaps are unaffected). An image without a usable EXIF time uses its
  file modification time instead. Only the file's header is read, once per (path, size, mtime_ns): the result
  is cached in the survey's scan state.
- Identity is content: a set's hash (:func:`set_hash`) covers every image's relative path and SHA-256.

Video files (:data:`pipeline.ingest.video.VIDEO_EXTENSIONS`: MP4, MOV ...) belong to sets like images; ingest
takes their keyframes. Hidden files and folders, symbolic links and other suffixes are ignored.
"""

from __future__ import annotations

import hashlib
import os
import stat
import time
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from pipeline.ingest.video import VIDEO_EXTENSIONS
from pipeline.scene.images import DECODABLE_EXTENSIONS

from .exif import read_exif_time
from .safe_fs import FolderTree

IMAGE_SUFFIXES = DECODABLE_EXTENSIONS | VIDEO_EXTENSIONS  # what a set is made of: photos and videos
HASH_CHUNK = 1 << 20


@dataclass(frozen=True)
class ImageFile:
    rel: str  # POSIX path relative to the survey folder
    size: int
    mtime: float
    mtime_ns: int
    exif_time: float | None = None  # EXIF capture time (Unix seconds); None: not read, or the file has none

    @property
    def is_video(self) -> bool:
        return PurePosixPath(self.rel).suffix.lower() in VIDEO_EXTENSIONS

    @property
    def capture_time(self) -> float:
        """When the image was taken: its EXIF time when it has one, else its modification time."""
        return self.mtime if self.exif_time is None else self.exif_time


@dataclass
class ImageSet:
    name: str
    files: list[ImageFile]

    @property
    def videos(self) -> int:
        return sum(f.is_video for f in self.files)

    @property
    def newest(self) -> float:
        """The newest modification time (the settle rule is about the ROV still writing, not capture time)."""
        return max(f.mtime for f in self.files)


def list_images(root: Path) -> list[ImageFile]:
    """Regular, non-hidden image files under ``root``; links and hidden entries are skipped, never followed."""
    out: list[ImageFile] = []
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".")
                             and not os.path.islink(os.path.join(dirpath, d)))
        for name in sorted(filenames):
            if name.startswith(".") or Path(name).suffix.lower() not in IMAGE_SUFFIXES:
                continue
            p = os.path.join(dirpath, name)
            try:
                st = os.lstat(p)
            except FileNotFoundError:
                continue
            if not _is_regular(st.st_mode):
                continue
            rel = PurePosixPath(Path(p).relative_to(root).as_posix())
            out.append(ImageFile(str(rel), st.st_size, st.st_mtime, st.st_mtime_ns))
    return out


def list_tree(tree: FolderTree) -> list[ImageFile]:
    """:func:`list_images` through an opened :class:`FolderTree` (what scans use: no link is ever entered)."""
    out: list[ImageFile] = []
    for rel_dir, _dirs, files in tree.walk():
        for name, st in files:
            if Path(name).suffix.lower() not in IMAGE_SUFFIXES:
                continue
            rel = f"{rel_dir}/{name}" if rel_dir else name
            out.append(ImageFile(rel, st.st_size, st.st_mtime, st.st_mtime_ns))
    return out


def _is_regular(mode: int) -> bool:
    return stat.S_ISREG(mode)


def group_images(files: list[ImageFile], gap_s: float) -> list[ImageSet]:
    """Sub-folders -> one set each; top-level images -> split by capture-time gaps (module docstring)."""
    by_folder: dict[str, list[ImageFile]] = {}
    top: list[ImageFile] = []
    for f in files:
        parts = PurePosixPath(f.rel).parts
        if len(parts) == 1:
            top.append(f)
        else:
            by_folder.setdefault(parts[0], []).append(f)
    sets = [ImageSet(name, sorted(fs, key=lambda f: f.rel)) for name, fs in sorted(by_folder.items())]
    top.sort(key=lambda f: (f.capture_time, f.rel))
    group: list[ImageFile] = []
    for f in top:
        if group and f.capture_time - group[-1].capture_time > gap_s:
            sets.append(_time_set(group))
            group = []
        group.append(f)
    if group:
        sets.append(_time_set(group))
    return sets


def _time_set(files: list[ImageFile]) -> ImageSet:
    """A set of loose images named after its first capture time (UTC)."""
    first = min(f.capture_time for f in files)
    return ImageSet(time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(first)), sorted(files, key=lambda f: f.rel))


def with_exif_times(root: Path, files: list[ImageFile], cache: dict[str, tuple[int, int, float | None]],
                    tree: FolderTree | None = None) -> list[ImageFile]:
    """``files`` with ``exif_time`` filled in for the loose images (those directly in ``root``).

    ``cache`` (the survey state's ``exif_times``) is updated in place: a file whose size and mtime_ns match its
    entry is not opened again, and entries of files that are gone are dropped."""
    out: list[ImageFile] = []
    loose: set[str] = set()
    for f in files:
        if "/" in f.rel:
            out.append(f)
            continue
        loose.add(f.rel)
        known = cache.get(f.rel)
        if known is None or known[0] != f.size or known[1] != f.mtime_ns:
            known = cache[f.rel] = (f.size, f.mtime_ns,
                                    read_exif_time(root / f.rel, tree.open(f.rel) if tree is not None else None))
        out.append(replace(f, exif_time=known[2]))
    for rel in [k for k in cache if k not in loose]:
        del cache[rel]
    return out


def file_sha256(path: Path, opened: BinaryIO | None = None) -> str:
    h = hashlib.sha256()
    with opened if opened is not None else open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def set_hash(files: list[ImageFile], digests: dict[str, tuple[int, int, str]]) -> str:
    h = hashlib.sha256()
    for f in sorted(files, key=lambda f: f.rel):
        h.update(f"{f.rel}\0{digests[f.rel][2]}\n".encode())
    return h.hexdigest()
