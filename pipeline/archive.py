"""Safe extraction of uploaded zip/tar archives: hard limits, no path escapes, nothing outside the target.

Every refusal raises :class:`ArchiveError` with a machine-readable ``code`` and a sentence for the user; the
service turns it into a 4xx. Checks happen on the archive's table of contents *before* anything is written,
and again while streaming each member (declared sizes can lie), so a refused archive leaves no files behind.
"""

from __future__ import annotations

import os
import shutil
import stat
import tarfile
import unicodedata
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

NESTED_ARCHIVE_SUFFIXES = (".zip", ".tar", ".tgz", ".tar.gz", ".tbz2", ".tar.bz2", ".txz", ".tar.xz", ".gz",
                           ".bz2", ".xz", ".7z", ".rar")
CHUNK = 1 << 20


@dataclass(frozen=True)
class ArchiveLimits:
    """Hard caps for one upload."""

    max_entries: int = 5000  # files + folders in the archive
    max_total_bytes: int = 4 << 30  # uncompressed total
    max_file_bytes: int = 512 << 20  # one uncompressed member
    max_ratio: float = 200.0  # uncompressed / compressed, per member and overall (zip bombs)


class ArchiveError(ValueError):
    """A refused archive. ``code`` is stable (API clients switch on it); the message says why."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass
class Extracted:
    files: list[Path]  # written files, relative to the target folder
    ignored: list[tuple[str, str]]  # (member name, why) for members skipped without refusing the archive


def safe_member_path(name: str) -> PurePosixPath:
    """Validate a member name and return it as a relative POSIX path; refuse escapes and absolute paths."""
    if "\x00" in name:
        raise ArchiveError("bad_name", f"archive member name contains a NUL byte: {name!r}")
    norm = unicodedata.normalize("NFC", name.replace("\\", "/"))
    if norm.startswith("/") or (len(norm) > 1 and norm[1] == ":"):
        raise ArchiveError("absolute_path", f"archive member has an absolute path: {name!r}")
    parts = [p for p in PurePosixPath(norm).parts if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise ArchiveError("path_escape", f"archive member escapes the upload folder: {name!r}")
    if not parts:
        raise ArchiveError("bad_name", f"archive member has an empty name: {name!r}")
    return PurePosixPath(*parts)


def _is_nested_archive(path: PurePosixPath) -> bool:
    return path.name.lower().endswith(NESTED_ARCHIVE_SUFFIXES)


def detect_format(path: Path) -> str:
    """'zip' or 'tar' by content (not by file name); ArchiveError('not_an_archive') otherwise."""
    if zipfile.is_zipfile(path):
        return "zip"
    try:
        if tarfile.is_tarfile(path):
            return "tar"
    except OSError:
        pass
    raise ArchiveError("not_an_archive", "the upload is not a zip or tar archive")


def extract_archive(archive: Path, target: Path, limits: ArchiveLimits = ArchiveLimits()) -> Extracted:
    """Extract ``archive`` into ``target`` (created; must be empty) under ``limits``. On refusal ``target`` is
    removed again, so nothing of a bad upload stays on disk."""
    fmt = detect_format(archive)
    target.mkdir(parents=True, exist_ok=True)
    if any(target.iterdir()):
        raise ValueError(f"extraction target {target} is not empty")
    try:
        if fmt == "zip":
            return _extract_zip(archive, target, limits)
        return _extract_tar(archive, target, limits)
    except ArchiveError:
        shutil.rmtree(target, ignore_errors=True)
        raise
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, OSError) as e:
        shutil.rmtree(target, ignore_errors=True)
        raise ArchiveError("corrupt_archive", f"the archive is damaged or truncated: {e}") from e


def _check_counts(n: int, total: int, limits: ArchiveLimits) -> None:
    if n > limits.max_entries:
        raise ArchiveError("too_many_entries", f"the archive has {n} entries; the limit is {limits.max_entries}")
    if total > limits.max_total_bytes:
        raise ArchiveError("too_large", f"the archive unpacks to {total} bytes; the limit is {limits.max_total_bytes}")


def _plan(names_sizes: list[tuple[str, int, bool]], limits: ArchiveLimits, ignored) -> list[PurePosixPath | None]:
    """Validate names and sizes; returns the destination per member (None = skip), refusing on hard errors."""
    seen: dict[str, str] = {}
    plan: list[PurePosixPath | None] = []
    for name, size, is_dir in names_sizes:
        rel = safe_member_path(name)
        if is_dir:
            plan.append(None)
            continue
        if size > limits.max_file_bytes:
            raise ArchiveError("file_too_large",
                               f"{name!r} unpacks to {size} bytes; the limit is {limits.max_file_bytes}")
        if _is_nested_archive(rel):
            raise ArchiveError("nested_archive", f"archives inside the archive are not accepted: {name!r}")
        key = str(rel).casefold()
        if key in seen:
            raise ArchiveError("duplicate_name", f"the archive holds two files named {seen[key]!r} and {name!r}")
        seen[key] = name
        if rel.name.startswith(".") or "__MACOSX" in rel.parts:
            ignored.append((name, "hidden or system file"))
            plan.append(None)
            continue
        plan.append(rel)
    return plan


def _copy_limited(src, dst: Path, declared: int, limits: ArchiveLimits, budget: list[int]) -> None:
    """Stream one member, counting real bytes against the per-file and total caps."""
    written = 0
    with open(dst, "xb") as out:
        while chunk := src.read(CHUNK):
            written += len(chunk)
            budget[0] += len(chunk)
            if written > limits.max_file_bytes or written > max(declared, 0) + CHUNK:
                raise ArchiveError("file_too_large", f"{dst.name!r} is larger than its archive entry says")
            if budget[0] > limits.max_total_bytes:
                raise ArchiveError("too_large", "the archive unpacks to more than the size limit")
            out.write(chunk)


def _extract_zip(archive: Path, target: Path, limits: ArchiveLimits) -> Extracted:
    ignored: list[tuple[str, str]] = []
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        _check_counts(len(infos), sum(i.file_size for i in infos), limits)
        compressed = max(1, sum(i.compress_size for i in infos))
        if sum(i.file_size for i in infos) / compressed > limits.max_ratio:
            raise ArchiveError("compression_bomb", "the archive's compression ratio is implausibly high")
        for i in infos:
            mode = (i.external_attr >> 16) & 0xFFFF
            if stat.S_ISLNK(mode):
                raise ArchiveError("link", f"links are not accepted in uploads: {i.filename!r}")
            if stat.S_IFMT(mode) and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # type bits are optional
                raise ArchiveError("special_file", f"special files are not accepted: {i.filename!r}")
            if i.file_size > 1 << 16 and i.file_size / max(1, i.compress_size) > limits.max_ratio:
                raise ArchiveError("compression_bomb", f"{i.filename!r} has an implausible compression ratio")
        plan = _plan([(i.filename, i.file_size, i.is_dir()) for i in infos], limits, ignored)
        files, budget = [], [0]
        for info, rel in zip(infos, plan):
            if rel is None:
                continue
            dst = _destination(target, rel)
            with zf.open(info) as src:
                _copy_limited(src, dst, info.file_size, limits, budget)
            files.append(rel)
    return Extracted([Path(p) for p in files], ignored)


def _extract_tar(archive: Path, target: Path, limits: ArchiveLimits) -> Extracted:
    ignored: list[tuple[str, str]] = []
    with tarfile.open(archive, mode="r:*") as tf:
        members = tf.getmembers()
        _check_counts(len(members), sum(m.size for m in members if m.isfile()), limits)
        for m in members:
            if m.issym() or m.islnk():
                raise ArchiveError("link", f"links are not accepted in uploads: {m.name!r}")
            if not (m.isfile() or m.isdir()):
                raise ArchiveError("special_file", f"special files are not accepted: {m.name!r}")
        compressed = max(1, archive.stat().st_size)
        total = sum(m.size for m in members if m.isfile())
        if total > 1 << 20 and total / compressed > limits.max_ratio:
            raise ArchiveError("compression_bomb", "the archive's compression ratio is implausibly high")
        plan = _plan([(m.name, m.size, m.isdir()) for m in members], limits, ignored)
        files, budget = [], [0]
        for m, rel in zip(members, plan):
            if rel is None:
                continue
            src = tf.extractfile(m)
            if src is None:
                raise ArchiveError("special_file", f"cannot read archive member {m.name!r}")
            with src:
                _copy_limited(src, _destination(target, rel), m.size, limits, budget)
            files.append(rel)
    return Extracted([Path(p) for p in files], ignored)


def _destination(target: Path, rel: PurePosixPath) -> Path:
    dst = target.joinpath(*rel.parts)
    root = os.path.realpath(target)
    if os.path.commonpath([root, os.path.realpath(dst.parent)]) != root:  # defence in depth
        raise ArchiveError("path_escape", f"archive member escapes the upload folder: {str(rel)!r}")
    dst.parent.mkdir(parents=True, exist_ok=True)
    return dst
