"""The job store of a deployment with an object store: the manifests, logs and job files live there
(``<prefix>/jobs/<id>/…``, the job folder's own layout), and each host's ``<data>/jobs/<id>/`` is its copy.

- The manifest is read from and written to the store on every access (under the Redis manifest mutex, as on a
  shared disk); a local copy is kept for the host's own readers.
- Every manifest write first pushes what changed in the local job folder: a stage's outputs and its marker
  are in the store before the manifest that says it is done (and before the next stage is queued); the
  progress writes (every 2 s) push the training checkpoints while the stage runs.
- A worker pulls the job before each stage (:meth:`pull`); the API mirrors what it serves (:meth:`mirror`),
  leaving out what only stages read (the upload, SfM's scene, checkpoints).
"""

from __future__ import annotations

import functools
import json
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from botocore.exceptions import BotoCoreError, ClientError
from pydantic import ValidationError

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_text
from service.jobs.manifest import Manifest
from service.jobs.store import JOB_ID_RE, JobNotFound, JobStore, StoreUnavailable

from .mirror import FolderMirror
from .objects import ObjectStore

log = logging.getLogger(__name__)

JOBS = "jobs/"
_JOB = JobLayout(Path("job"))  # the job folder's names, as JobLayout spells them
MANIFEST = _JOB.relative(_JOB.manifest)
LOG = _JOB.relative(_JOB.log)
INPUTS = tuple(_JOB.relative(p) + "/" for p in (_JOB.input, _JOB.unpacked))  # the upload, unpacked: ingest's only
API_SKIPS = (*INPUTS, _JOB.relative(_JOB.scene) + "/")  # read by stages only: never mirrored to the API


F = TypeVar("F", bound=Callable)


def answers(fn: F) -> F:
    """The store's client errors (no connection, a timeout, a 5xx after boto's retries) as StoreUnavailable, so
    callers tell "the store is away" from a bug without knowing boto (a missing object is not an error here)."""
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (BotoCoreError, ClientError) as e:
            raise StoreUnavailable(f"the object store does not answer: {e}") from e
    return wrapped  # type: ignore[return-value]


def served(rel: str) -> bool:
    """What the API's mirror holds: everything a client can ask for, not the stages' working files."""
    return rel != MANIFEST and not rel.startswith(API_SKIPS) and not rel.endswith(".pt")


def staged(rel: str) -> bool:
    return rel != MANIFEST  # the manifest is read and written through the store itself


class SyncedJobStore(JobStore):
    def __init__(self, jobs_dir: Path, objects: ObjectStore):
        super().__init__(jobs_dir)
        self.objects = objects
        self._mirrors: dict[str, FolderMirror] = {}
        self._mirrors_lock = threading.Lock()

    def _name(self, job_id: str, rel: str = "") -> str:
        self.job_dir(job_id)  # refuses an id we never hand out
        return f"{JOBS}{job_id}/{rel}"

    def _folder(self, job_id: str) -> FolderMirror:
        with self._mirrors_lock:
            if job_id not in self._mirrors:
                self._mirrors[job_id] = FolderMirror(self.objects, self._name(job_id), self.job_dir(job_id),
                                                     include=staged)
            return self._mirrors[job_id]

    def ensure(self) -> None:
        super().ensure()
        try:
            self.objects.ensure_bucket()
        except (BotoCoreError, ClientError) as e:  # the API starts anyway; /ready says what is missing
            log.error("object store %s: cannot reach or create the bucket: %s", self.objects.bucket, e)

    def reachable(self) -> bool:
        try:
            self.objects.ping()
            return True
        except (BotoCoreError, ClientError) as e:
            log.warning("object store unreachable: %s", e)
            return False

    # ---- the manifest
    @answers
    def exists(self, job_id: str) -> bool:
        try:
            return self.objects.exists(self._name(job_id, MANIFEST))
        except JobNotFound:
            return False

    @answers
    def read(self, job_id: str) -> Manifest:
        text = self.objects.get_bytes(self._name(job_id, MANIFEST))
        if text is None:
            raise JobNotFound(job_id)
        m = Manifest.model_validate_json(text)
        if self.job_dir(job_id).is_dir():
            atomic_write_text(self.manifest_path(job_id), text.decode("utf-8"))
        return m

    @answers
    def write(self, m: Manifest) -> None:
        self._folder(m.id).push()
        m.touch()
        text = m.model_dump_json(indent=2)
        atomic_write_text(self.manifest_path(m.id), text)
        self.objects.put_bytes(self._name(m.id, MANIFEST), text.encode("utf-8"))

    @answers
    def list(self) -> list[Manifest]:
        out = []
        for job_id in self.objects.folders(JOBS):
            if not JOB_ID_RE.match(job_id):
                continue
            try:
                out.append(self.read(job_id))
            except JobNotFound:
                continue  # an upload still streaming, or files left without a manifest
            except (ValidationError, json.JSONDecodeError, OSError) as err:
                log.error("unreadable manifest of %s in the object store: %s", job_id, err)
        out.sort(key=lambda m: (m.created_at, m.id), reverse=True)
        return out

    @answers
    def remove(self, job_id: str) -> None:
        self.objects.delete_prefix(self._name(job_id))
        if self.job_dir(job_id).exists():
            super().remove(job_id)
        with self._mirrors_lock:
            self._mirrors.pop(job_id, None)

    # ---- the job's files
    @answers
    def pull(self, job_id: str, stage: str | None = None) -> None:
        """Bring this host's job folder up to the store's state (a worker, before it runs ``stage``); the upload
        (``input/``, up to ``max_upload_bytes``) only for ingest, the one stage that reads it."""
        self._folder(job_id).pull(only=None if stage in (None, "ingest") else _not_input)

    @answers
    def mirror(self, job_id: str) -> Path:
        """The job folder with what the API serves brought up to date (unchanged files are not fetched)."""
        self._folder(job_id).pull(only=served)
        return self.job_dir(job_id)

    # ---- the log: whoever appends fetches the store's copy first
    @answers
    def append_log(self, job_id: str, line: str) -> None:
        folder = self._folder(job_id)
        folder.pull(only=_is_log)
        super().append_log(job_id, line)
        folder.push(only=_is_log)

    @answers
    def read_log(self, job_id: str, offset: int, limit: int) -> tuple[str, int, int]:
        self._folder(job_id).pull(only=_is_log)
        return super().read_log(job_id, offset, limit)

    @answers
    def last_checkpoint_iteration(self, job_id: str, tail_bytes: int = 256 << 10) -> int | None:
        self._folder(job_id).pull(only=_is_log)
        return super().last_checkpoint_iteration(job_id, tail_bytes)


def _not_input(rel: str) -> bool:
    return not rel.startswith(INPUTS)


def _is_log(rel: str) -> bool:
    return rel == LOG
