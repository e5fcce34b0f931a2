"""A job's downloadable results: which files, their sizes and SHA-256, and a streamed zip of them all.

A file is listed only once the stage that writes it has its completion marker (so a half-written file is
never offered): what each stage ``publishes`` in :data:`pipeline.job.table.STAGE_TABLE` (ingest's result after
ingest, train's after train, everything in the output folder after export; the paths in
:class:`pipeline.job.layout.JobLayout`). Checksums are cached in ``JobLayout.artifacts_cache`` keyed by size and
mtime.
"""

from __future__ import annotations

import hashlib
import json
import mimetypes
import os
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from pipeline.job.table import STAGE_TABLE

# artifact (a JobLayout attribute: a file, or a folder whose files are all listed) -> the stage whose marker
# makes it final
ARTIFACT_SOURCES: dict[str, str] = {name: s.name for s in STAGE_TABLE for name in s.publishes}
STORED_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".webp", ".zip", ".gz", ".exr", ".jxl", ".spz"})


@dataclass(frozen=True)
class Artifact:
    path: str  # POSIX, relative to the job folder
    size: int
    sha256: str
    media_type: str


def _candidates(job_dir: Path) -> list[Path]:
    out: list[Path] = []
    layout = JobLayout(job_dir)
    for name, stage in ARTIFACT_SOURCES.items():
        if not layout.marker(stage).is_file():
            continue
        p = getattr(layout, name)
        if p.is_dir():
            out += sorted(f for f in p.rglob("*")
                          if f.is_file() and not f.is_symlink()
                          and not any(part.startswith(".") for part in f.relative_to(job_dir).parts))
        elif p.is_file() and not p.is_symlink():
            out.append(p)
    return out


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def list_artifacts(job_dir: Path) -> list[Artifact]:
    cache_path = JobLayout(job_dir).artifacts_cache
    try:
        cache = json.loads(cache_path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        cache = {}
    out, fresh = [], {}
    for p in _candidates(job_dir):
        rel = p.relative_to(job_dir).as_posix()
        st = p.stat()
        key = [st.st_size, st.st_mtime_ns]
        hit = cache.get(rel)
        digest = hit[2] if hit and hit[:2] == key else sha256_file(p)
        fresh[rel] = [*key, digest]
        out.append(Artifact(rel, st.st_size, digest, media_type(rel)))
    if fresh != cache:
        try:
            atomic_write_json(cache_path, fresh)
        except OSError:
            pass  # the cache is an optimisation (e.g. a read-only data volume)
    return out


def media_type(name: str) -> str:
    if name.endswith(".ply"):
        return "application/x-ply"
    if name.endswith(".spz"):  # no registered type; the x- form as for PLY
        return "application/x-spz"
    return mimetypes.guess_type(name)[0] or "application/octet-stream"


def find_artifact(job_dir: Path, rel: str) -> Path | None:
    """The file for ``rel`` if it is one of the listed artifacts (so no path outside them is ever served)."""
    for p in _candidates(job_dir):
        if p.relative_to(job_dir).as_posix() == rel:
            real, root = os.path.realpath(p), os.path.realpath(job_dir)
            return p if os.path.commonpath([real, root]) == root else None
    return None


class _Pipe:
    """A write-only file object whose written bytes are collected and handed out by the zip generator."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.pos = 0

    def write(self, b: bytes) -> int:
        self.buf += b
        self.pos += len(b)
        return len(b)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        out = bytes(self.buf)
        self.buf.clear()
        return out


def zip_stream(job_dir: Path, artifacts: list[Artifact], chunk: int = 1 << 20) -> Iterator[bytes]:
    """Yield a zip of ``artifacts`` as it is written (no temp file; ZIP64 where needed)."""
    pipe = _Pipe()
    with zipfile.ZipFile(pipe, "w", allowZip64=True, compresslevel=1) as zf:  # type: ignore[arg-type]
        for a in artifacts:
            method = zipfile.ZIP_STORED if Path(a.path).suffix.lower() in STORED_SUFFIXES else zipfile.ZIP_DEFLATED
            info = zipfile.ZipInfo.from_file(job_dir / a.path, arcname=a.path)
            info.compress_type = method
            with open(job_dir / a.path, "rb") as src, zf.open(info, "w", force_zip64=a.size > 0x7FFFFFFF) as dst:
                while data := src.read(chunk):
                    dst.write(data)
                    if len(pipe.buf) >= chunk:
                        yield pipe.take()
            yield pipe.take()
    yield pipe.take()
