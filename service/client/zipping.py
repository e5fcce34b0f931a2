"""A folder as a zip archive written while it is sent: no temporary copy of a survey's gigabytes on disk.

zipfile writes to a stream it cannot seek by putting each member's sizes and CRC in a data descriptor after its
data; the server reads members through the central directory, so such a zip is as good as any. Images are
stored (JPEG, PNG, HEIC ... are compressed already: deflating them costs CPU and saves ~1 %); other files are
deflated at level 1.
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

CHUNK = 1 << 20
STORED_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".webp", ".heic", ".heif", ".avif", ".jxl", ".gif"})
ARCHIVE_TYPES = {".zip": "application/zip", ".tar": "application/x-tar", ".tgz": "application/gzip",
                 ".gz": "application/gzip", ".bz2": "application/x-bzip2", ".tbz2": "application/x-bzip2",
                 ".xz": "application/x-xz", ".txz": "application/x-xz"}


@dataclass(frozen=True)
class FolderEntry:
    path: Path
    name: str  # the member name: the path relative to the folder, with '/'
    size: int


def folder_entries(folder: Path) -> list[FolderEntry]:
    """The regular, non-hidden files under ``folder`` (sub-folders included, hidden ones skipped), sorted by name.
    Links to files are sent as the file they point to; links to folders are not followed (pathlib's ``rglob``
    does not descend into them)."""
    out = []
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder)
        if any(part.startswith(".") for part in rel.parts) or not p.is_file():
            continue
        out.append(FolderEntry(p, rel.as_posix(), p.stat().st_size))
    return out


def archive_content_type(path: Path) -> str | None:
    """The Content-Type of an archive file by its suffix, or None when it does not look like one."""
    return ARCHIVE_TYPES.get(path.suffix.lower())


class _Sink:
    """A write-only, unseekable file object: what zipfile writes piles up until the generator hands it on."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def write(self, b: bytes) -> int:
        self.parts.append(bytes(b))
        return len(b)

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        data = b"".join(self.parts)
        self.parts.clear()
        return data


def zip_stream(entries: list[FolderEntry], on_read: Callable[[int], None] | None = None) -> Iterator[bytes]:
    """The zip of ``entries`` in pieces of about a MiB, produced as they are consumed. ``on_read(n)`` is told
    every n source bytes read (upload progress over the sum of the entries' sizes)."""
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", allowZip64=True, compresslevel=1) as zf:  # type: ignore[arg-type]
        for e in entries:
            info = zipfile.ZipInfo.from_file(e.path, e.name)
            stored = e.path.suffix.lower() in STORED_SUFFIXES
            info.compress_type = zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED
            info.file_size = e.size  # decides zip64 up front: the header cannot be patched in a stream
            with open(e.path, "rb") as src, zf.open(info, "w") as dst:
                while chunk := src.read(CHUNK):
                    dst.write(chunk)
                    if on_read:
                        on_read(len(chunk))
                    if data := sink.take():
                        yield data
            if data := sink.take():
                yield data
    if data := sink.take():  # the central directory
        yield data


def file_stream(path: Path, on_read: Callable[[int], None] | None = None) -> Iterator[bytes]:
    """An archive file as it is, in pieces of a MiB."""
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            if on_read:
                on_read(len(chunk))
            yield chunk
