"""Reading a survey folder without following links, whatever happens to it between two looks.

A survey folder is checked when it is registered and again at every scan, but a check by path is only good
for the moment it is made: the folder (or any folder inside it, or a file) can be swapped for a link right
after. :class:`FolderTree` therefore opens the folder once, component by component from the allowed root
with ``O_NOFOLLOW``, and reaches everything below it through directory file descriptors (``openat``), again
with ``O_NOFOLLOW`` at every step. A link anywhere on the way is an ``OSError`` (``ELOOP``/``ENOTDIR``), never
a file outside the root.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path, PurePosixPath
from typing import BinaryIO

DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
FILE_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK  # NONBLOCK: a FIFO must not hang us


class NotARegularFile(OSError):
    pass


def _open_dir_at(parent_fd: int, parts: tuple[str, ...]) -> int:
    fd = os.dup(parent_fd)
    try:
        for part in parts:
            if part in ("", ".", ".."):
                raise OSError(f"refusing path component {part!r}")
            nxt = os.open(part, DIR_FLAGS, dir_fd=fd)
            os.close(fd)
            fd = nxt
    except BaseException:
        os.close(fd)
        raise
    return fd


class FolderTree:
    """A folder opened without following links: ``FolderTree(root, folder)`` where ``root`` is a trusted
    (configured) folder and ``folder`` lies below it. Use as a context manager."""

    def __init__(self, root: Path, folder: Path):
        rel = Path(folder).relative_to(root)  # ValueError when it is not below the root
        root_fd = os.open(root, DIR_FLAGS & ~os.O_NOFOLLOW)  # the configured root itself may be a mount link
        try:
            self.fd = _open_dir_at(root_fd, rel.parts)
        finally:
            os.close(root_fd)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def __enter__(self) -> FolderTree:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self, rel: str) -> BinaryIO:
        """A regular file below the folder, for reading (``NotARegularFile`` / ``OSError`` otherwise)."""
        parts = PurePosixPath(rel).parts
        if not parts:
            raise NotARegularFile(f"not a file: {rel!r}")
        dir_fd = _open_dir_at(self.fd, parts[:-1])
        try:
            fd = os.open(parts[-1], FILE_FLAGS, dir_fd=dir_fd)
        finally:
            os.close(dir_fd)
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise NotARegularFile(f"not a regular file: {rel!r}")
            os.set_blocking(fd, True)
            return os.fdopen(fd, "rb")
        except BaseException:
            os.close(fd)
            raise

    def walk(self) -> Iterator[tuple[str, list[str], list[tuple[str, os.stat_result]]]]:
        """(relative folder, sub-folder names, [(file name, lstat)]) top-down; hidden entries and links are
        left out and never entered. The caller may prune the sub-folder list in place."""
        yield from self._walk(self.fd, "")

    def _walk(self, fd: int, rel: str):
        dirs: list[str] = []
        files: list[tuple[str, os.stat_result]] = []
        for name in sorted(os.listdir(fd)):
            if name.startswith("."):
                continue
            try:
                st = os.stat(name, dir_fd=fd, follow_symlinks=False)
            except FileNotFoundError:
                continue
            if stat.S_ISDIR(st.st_mode):
                dirs.append(name)
            elif stat.S_ISREG(st.st_mode):
                files.append((name, st))
        yield rel, dirs, files
        for name in dirs:
            try:
                sub = os.open(name, DIR_FLAGS, dir_fd=fd)
            except OSError:  # gone, or swapped for a link since it was listed
                continue
            try:
                yield from self._walk(sub, f"{rel}/{name}" if rel else name)
            finally:
                os.close(sub)
