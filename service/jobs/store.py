"""Job folders on disk: ``<data>/jobs/<id>/`` holding the manifest (the truth, atomic writes), the pipeline
options, the log (append-only), the input (the uploaded archive or a survey set's copied images) and everything
the stages write; every path in it is :class:`pipeline.job.layout.JobLayout`'s. A folder without a manifest is
an upload still streaming (or one whose API process died mid-upload; swept after a day).
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import shutil
import time
from pathlib import Path

from pydantic import ValidationError

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_text

from .manifest import Manifest

log = logging.getLogger(__name__)

JOB_ID_RE = re.compile(r"^[a-z][a-z0-9]{7,63}$")
INCOMPLETE_UPLOAD_AGE_S = 24 * 3600
CHECKPOINT_RE = re.compile(r"checkpoint written: \S+ \(iteration (\d+)\)")  # pipeline.train.checkpoint's log line


class JobNotFound(LookupError):
    pass


class StoreUnavailable(OSError):
    """The job store does not answer (an object store away: service.storage); the local folder never raises it.
    A runner waits it out like a Redis outage (worker.runner); the API answers 503 ``object_store_unavailable``."""


def new_job_id() -> str:
    """Time-ordered: 'j' + milliseconds (hex) + 40 random bits."""
    return f"j{int(time.time() * 1000):011x}{secrets.token_hex(5)}"


class JobStore:
    def __init__(self, jobs_dir: Path):
        self.root = Path(jobs_dir)

    def ensure(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)

    def job_dir(self, job_id: str) -> Path:
        if not JOB_ID_RE.match(job_id):
            raise JobNotFound(job_id)  # not a name we ever hand out: never touch the file system with it
        return self.root / job_id

    def layout(self, job_id: str) -> JobLayout:
        return JobLayout(self.job_dir(job_id))

    def pull(self, job_id: str, stage: str | None = None) -> None:
        """Bring this host's job folder up to date before ``stage`` runs: here it is the truth, so nothing to do
        (``service.storage.jobs.SyncedJobStore`` fetches from the object store)."""

    def reachable(self) -> bool | None:
        """Whether the job store's backing service answers (None: there is none, the folder is the store)."""
        return None

    def mirror(self, job_id: str) -> Path:
        """The job folder with the files the API serves up to date (here: as it is)."""
        return self.job_dir(job_id)

    def manifest_path(self, job_id: str) -> Path:
        return self.layout(job_id).manifest

    def exists(self, job_id: str) -> bool:
        try:
            return self.manifest_path(job_id).is_file()
        except JobNotFound:
            return False

    def read(self, job_id: str) -> Manifest:
        try:
            text = self.manifest_path(job_id).read_text(encoding="utf-8")
        except (FileNotFoundError, NotADirectoryError) as e:
            raise JobNotFound(job_id) from e
        return Manifest.model_validate_json(text)

    def write(self, m: Manifest) -> None:
        m.touch()
        atomic_write_text(self.manifest_path(m.id), m.model_dump_json(indent=2))

    def list(self) -> list[Manifest]:
        """Every readable manifest, newest first (a damaged one is logged and left out)."""
        out = []
        try:
            entries = list(os.scandir(self.root))
        except FileNotFoundError:
            return []
        for e in entries:
            if not e.is_dir() or not JOB_ID_RE.match(e.name):
                continue
            try:
                out.append(self.read(e.name))
            except JobNotFound:
                continue
            except (ValidationError, json.JSONDecodeError, OSError) as err:
                log.error("unreadable manifest in %s: %s", e.path, err)
        out.sort(key=lambda m: (m.created_at, m.id), reverse=True)
        return out

    def remove(self, job_id: str) -> None:
        """Move the folder aside atomically (readers see it gone at once), then delete it."""
        src = self.job_dir(job_id)
        trash = self.root.parent / "trash" / f"{job_id}.{secrets.token_hex(4)}"
        trash.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, trash)
        shutil.rmtree(trash, ignore_errors=True)

    # ---- log
    def append_log(self, job_id: str, line: str) -> None:
        stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        with open(self.layout(job_id).log, "a", encoding="utf-8") as f:
            f.write(f"{stamp} {line.rstrip()}\n")

    def read_log(self, job_id: str, offset: int, limit: int) -> tuple[str, int, int]:
        """(text, next_offset, size) from byte ``offset``: whole lines only, unless one line exceeds ``limit``."""
        path = self.layout(job_id).log
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            return "", offset, 0
        if offset >= size:
            return "", offset, size
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read(limit)
        cut = data.rfind(b"\n") + 1
        if cut == 0 and len(data) >= limit:
            cut = len(data)  # one line longer than a page: hand it out in pieces
        # (cut == 0 otherwise: a line still being written; the next poll gets it whole)
        return data[:cut].decode("utf-8", errors="replace"), offset + cut, size

    def last_checkpoint_iteration(self, job_id: str, tail_bytes: int = 256 << 10) -> int | None:
        """The iteration of the last training checkpoint the job's log reports (``checkpoint written``)."""
        path = self.layout(job_id).log
        try:
            with open(path, "rb") as f:
                f.seek(max(0, path.stat().st_size - tail_bytes))
                text = f.read().decode("utf-8", "replace")
        except OSError:
            return None
        found = CHECKPOINT_RE.findall(text)
        return int(found[-1]) if found else None

    # ---- housekeeping
    def sweep_incomplete(self, max_age_s: float = INCOMPLETE_UPLOAD_AGE_S) -> int:
        """Remove job folders that never got a manifest (an API process died mid-upload) and old trash."""
        n = 0
        now = time.time()
        for base in (self.root, self.root.parent / "trash"):
            if not base.is_dir():
                continue
            for e in os.scandir(base):
                p = Path(e.path)
                if not e.is_dir() or (base == self.root and JobLayout(p).manifest.exists()):
                    continue
                if now - e.stat().st_mtime > max_age_s:
                    shutil.rmtree(p, ignore_errors=True)
                    n += 1
        return n
