"""Safe extraction of uploaded zip/tar archives: hard limits, no path escapes, nothing outside the target.

Every refusal raises :class:`ArchiveError` with a machine-readable ``code`` and a sentence for the user; the
service turns it into a 4xx. Checks happen on the archive's table of contents *before* anything is written,
and again while streaming each member (declared sizes can lie), so a refused archive leaves no files behind.
"""

from __future__ import annotations

import errno
import lzma
import os
import shutil
import stat
import tarfile
import unicodedata
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

NESTED_ARCHIVE_SUFFIXES = (".zip", ".tar", ".tgz", ".tar.gz", ".tbz2", ".tar.bz2", ".txz", ".tar.xz", ".gz",
                           ".bz2", ".xz", ".7z", ".rar")
CHUNK = 1 << 20
NAME_MAX_BYTES = 255  # one path component, in UTF-8 bytes (Linux NAME_MAX; most file systems agree)
PATH_MAX_BYTES = 1024  # a whole member name (Linux allows 4096; no sane image set needs a quarter of it)
ZIP_ENCRYPTED = 0x1  # general purpose bit 0 of a zip entry: the data is encrypted


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


def _shown(name: str, limit: int = 120) -> str:
    """A member name as a message quotes it: repr, cut to ``limit`` characters (names can be 4 KiB long)."""
    text = repr(name)
    return text if len(text) <= limit else text[:limit - 5] + "...'"


def safe_member_path(name: str, is_dir: bool = False) -> PurePosixPath | None:
    """Validate a member name and return it as a relative POSIX path; refuse escapes, absolute paths and names
    too long for the file system. ``./`` prefixes are dropped (``tar -C dir .`` writes every member so); the
    archive's own root folder (``.`` or ``./``, a directory) gives None: nothing to create."""
    if "\x00" in name:
        raise ArchiveError("bad_name", f"archive member name contains a NUL byte: {_shown(name)}")
    norm = unicodedata.normalize("NFC", name.replace("\\", "/"))
    if norm.startswith("/") or (len(norm) > 1 and norm[1] == ":"):
        raise ArchiveError("absolute_path", f"archive member has an absolute path: {_shown(name)}")
    parts = [p for p in PurePosixPath(norm).parts if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise ArchiveError("path_escape", f"archive member escapes the upload folder: {_shown(name)}")
    if not parts:
        if is_dir:
            return None
        raise ArchiveError("bad_name", f"archive member has an empty name: {_shown(name)}")
    if any(len(p.encode("utf-8", "surrogateescape")) > NAME_MAX_BYTES for p in parts) \
            or len("/".join(parts).encode("utf-8", "surrogateescape")) > PATH_MAX_BYTES:
        raise ArchiveError("name_too_long", f"archive member name is too long (at most {NAME_MAX_BYTES} bytes "
                                            f"per folder or file name, {PATH_MAX_BYTES} in all): {_shown(name)}")
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
    except OSError as e:
        shutil.rmtree(target, ignore_errors=True)
        if e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EROFS):
            raise  # the server's disk, not the upload: an error of ours, not a refusal
        if e.errno == errno.ENAMETOOLONG:
            raise ArchiveError("name_too_long", "an archive member's name is too long for the file system") from e
        # e.strerror only: str(e) would quote the server-side path being written
        raise ArchiveError("corrupt_archive", f"the archive is damaged or truncated: {e.strerror or 'read error'}") \
            from e
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, zlib.error, lzma.LZMAError) as e:
        shutil.rmtree(target, ignore_errors=True)
        raise ArchiveError("corrupt_archive", f"the archive is damaged or truncated: {e}") from e
    except NotImplementedError as e:  # zipfile: a compression method it cannot decode (deflate64, AES ...)
        shutil.rmtree(target, ignore_errors=True)
        raise ArchiveError("unsupported_compression", f"the archive uses a compression method this server cannot "
                                                      f"read ({e}); use deflate, or a tar") from e


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
        rel = safe_member_path(name, is_dir)
        if is_dir or rel is None:
            plan.append(None)
            continue
        if size > limits.max_file_bytes:
            raise ArchiveError("file_too_large",
                               f"{_shown(name)} unpacks to {size} bytes; the limit is {limits.max_file_bytes}")
        if _is_nested_archive(rel):
            raise ArchiveError("nested_archive", f"archives inside the archive are not accepted: {_shown(name)}")
        key = str(rel).casefold()
        if key in seen:
            raise ArchiveError("duplicate_name",
                               f"the archive holds two files named {_shown(seen[key])} and {_shown(name)}")
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
            if i.flag_bits & ZIP_ENCRYPTED:  # zipfile would raise RuntimeError("... password required ...")
                raise ArchiveError("encrypted_archive", f"the archive is password-protected ({_shown(i.filename)} is "
                                                        f"encrypted); upload it without a password")
            mode = (i.external_attr >> 16) & 0xFFFF
            if stat.S_ISLNK(mode):
                raise ArchiveError("link", f"links are not accepted in uploads: {_shown(i.filename)}")
            if stat.S_IFMT(mode) and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # type bits are optional
                raise ArchiveError("special_file", f"special files are not accepted: {_shown(i.filename)}")
            if i.file_size > 1 << 16 and i.file_size / max(1, i.compress_size) > limits.max_ratio:
                raise ArchiveError("compression_bomb", f"{_shown(i.filename)} has an implausible compression ratio")
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
                raise ArchiveError("link", f"links are not accepted in uploads: {_shown(m.name)}")
            if not (m.isfile() or m.isdir()):
                raise ArchiveError("special_file", f"special files are not accepted: {_shown(m.name)}")
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
                raise ArchiveError("special_file", f"cannot read archive member {_shown(m.name)}")
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
