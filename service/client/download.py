"""Downloading a job's artifacts: each into ``<out>/<path>.part``, resumed with an HTTP Range from what an earlier,
interrupted run left there, checked against the SHA-256 the artifact list gives, then renamed into place. A file
already in place with the right checksum is not fetched again, so re-running a download finishes it."""

from __future__ import annotations

import fnmatch
import hashlib
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING

from service.client.errors import ClientError

if TYPE_CHECKING:  # annotations only: this module itself needs no httpx
    from service.client.remote import Artifact, ServiceClient

log = logging.getLogger(__name__)

HASH_CHUNK = 1 << 20
NET_CHUNK = 64 << 10  # written (and counted) per piece received: an interruption loses at most this much


@dataclass
class FileResult:
    path: str
    size: int
    fetched: int = 0
    """Bytes received over HTTP for this file (a resumed file: only the remainder)."""
    resumed_from: int = 0
    """Bytes of an earlier ``.part`` kept and asked to continue after (``Range: bytes=<n>-``); 0: from the start."""
    skipped: bool = False
    """Already in place with the right checksum: nothing fetched."""
    verified: bool = False
    """The file's SHA-256 equals the artifact list's."""


@dataclass
class DownloadReport:
    files: list[FileResult] = field(default_factory=list)

    @property
    def fetched(self) -> int:
        return sum(f.fetched for f in self.files)

    @property
    def total(self) -> int:
        return sum(f.size for f in self.files)


def select(artifacts: Sequence[Artifact], patterns: Sequence[str]) -> list[Artifact]:
    """The artifacts any of ``patterns`` picks; all of them when none is given. A pattern is a glob over the
    path (``*`` crosses '/': ``*.ply``, ``output/restored/*``); one without '/' also matches the file's own name
    (``report.json``), that name without its extension (``reconstruction`` picks the .ply and the .spz) or any
    folder on its path (``restored`` picks ``output/restored/`` and ``output/renders/restored/``), so ``survey``
    picks the survey stage's ``survey.json`` and its products in ``output/survey/``; a trailing '/'
    (``output/restored/``) picks that folder."""
    if not patterns:
        return list(artifacts)

    def hit(path: str, pat: str) -> bool:
        parts = path.split("/")
        if pat.endswith("/"):
            return path.startswith(pat) or f"/{pat}" in f"/{path}"
        if fnmatch.fnmatchcase(path, pat):
            return True
        stem = PurePosixPath(parts[-1]).stem
        return "/" not in pat and any(fnmatch.fnmatchcase(p, pat) for p in (*parts, stem))

    return [a for a in artifacts if any(hit(a.path, p) for p in patterns)]


def local_path(out: Path, artifact_path: str) -> Path:
    """Where an artifact lands under ``out``; a path that would leave ``out`` is refused."""
    parts = artifact_path.split("/")
    if any(p in ("..", "", ".") or "\\" in p for p in parts):  # absolute ("/x" has an empty first part) too
        raise ClientError(0, "bad_response", f"the server listed an artifact path that is not safe: {artifact_path!r}")
    return out.joinpath(*parts)


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _content_range_start(value: str | None) -> int | None:
    """The first byte of ``Content-Range: bytes <first>-<last>/<size>``, or None."""
    if not value or not value.startswith("bytes "):
        return None
    first = value[6:].partition("-")[0]
    return int(first) if first.isdigit() else None


def _fetch(client: ServiceClient, art: Artifact, part: Path, on_bytes: Callable[[int], None] | None) -> FileResult:
    """Fill ``part`` up to the artifact's end: a Range from its current length when there is one. The hash covers
    the bytes already there and then each chunk as it arrives (no second read of the file)."""
    have = part.stat().st_size if part.exists() else 0
    if have > art.size:  # not a prefix of this file: start over
        part.unlink()
        have = 0
    res = FileResult(art.path, art.size, resumed_from=have)
    h = hashlib.sha256()
    if have:
        with open(part, "rb") as f:
            while chunk := f.read(HASH_CHUNK):
                h.update(chunk)
    if have < art.size or art.size == 0:
        headers = {"Range": f"bytes={have}-"} if have else {}
        with client.stream(art.url, headers) as r:
            if have and (r.status_code != 206 or _content_range_start(r.headers.get("content-range")) != have):
                log.info("%s: the server sent the whole file instead of the rest; starting over", art.path)
                have, res.resumed_from, h = 0, 0, hashlib.sha256()
            with open(part, "r+b" if have else "wb") as f:
                f.seek(have)
                f.truncate()
                for chunk in r.iter_bytes(NET_CHUNK):
                    f.write(chunk)
                    h.update(chunk)
                    res.fetched += len(chunk)
                    if on_bytes:
                        on_bytes(len(chunk))
    res.verified = h.hexdigest() == art.sha256
    return res


def download_artifact(client: ServiceClient, art: Artifact, out: Path,
                      on_bytes: Callable[[int], None] | None = None) -> FileResult:
    dest = local_path(out, art.path)
    if dest.is_file() and dest.stat().st_size == art.size and sha256_file(dest) == art.sha256:
        return FileResult(art.path, art.size, skipped=True, verified=True)
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    res = _fetch(client, art, part, on_bytes)
    if not res.verified and res.resumed_from:
        # the kept prefix was of another version of the file (the job re-ran since): once more, whole
        log.warning("%s: the resumed file did not verify; downloading it whole", art.path)
        part.unlink()
        fetched = res.fetched
        res = _fetch(client, art, part, on_bytes)
        res.fetched += fetched
    if not res.verified:
        part.unlink()
        raise ClientError(0, "checksum_mismatch", f"{art.path}: the downloaded bytes do not match the listed sha256")
    part.replace(dest)
    return res


def download_job(client: ServiceClient, job_id: str, out: Path, patterns: Sequence[str] = (),
                 on_bytes: Callable[[int], None] | None = None,
                 on_plan: Callable[[list[Artifact]], None] | None = None) -> DownloadReport:
    """Every artifact of the job (or those ``patterns`` select) into ``out``, verified. ``on_plan`` sees the
    selection before any byte moves (to size a progress bar); ``on_bytes`` every chunk received."""
    chosen = select(client.artifacts(job_id), patterns)
    if not chosen:
        raise ClientError(0, "nothing_selected", f"job {job_id} has no artifact matching {list(patterns)}"
                          if patterns else f"job {job_id} has no results yet")
    if on_plan:
        on_plan(chosen)
    report = DownloadReport()
    for art in chosen:
        report.files.append(download_artifact(client, art, out, on_bytes))
    return report


def download_bundle(client: ServiceClient, job_id: str, dest: Path,
                    on_bytes: Callable[[int], None] | None = None) -> int:
    """The job's results as one zip (the server writes it while streaming: no Range, no checksum). Returns its
    size."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    n = 0
    with client.stream(f"/v1/jobs/{job_id}/bundle") as r, open(part, "wb") as f:
        for chunk in r.iter_bytes(HASH_CHUNK):
            f.write(chunk)
            n += len(chunk)
            if on_bytes:
                on_bytes(len(chunk))
    part.replace(dest)
    return n
