"""A job from an upload (``POST /v1/jobs``): stream the archive into a new job folder, run the pipeline's ingest
stage on it with this deployment's limits (hostile archives, undecodable images and too-small sets are refused
here), then create the job and queue its remaining stages.

``Idempotency-Key``: a repeat of a request (same archive bytes, same options) gets the first job back; the key is
claimed in Redis while the first request uploads and recorded on disk (``service.jobs.idempotency``) once its job
exists. Refusals are :class:`service.jobs.uploads.UploadError` (HTTP status, stable code, message); a broker that does
not take the first stage is a :class:`service.core.dispatch.DispatchError` after the job was created (failed with
``broker_unavailable``; a retry re-sends it). Whatever else goes wrong, nothing is left on disk.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import anyio
from pydantic import ValidationError

from pipeline.ingest.archive import ArchiveError
from pipeline.ingest.intake import IngestConfig, IngestError
from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions, StageContext
from pipeline.job.runner import run_stage
from service.core.coord import Coordinator
from service.core.dispatch import DispatchError
from service.core.settings import Settings
from service.webhooks.callback import CallbackRefused, check_callback_url

from .idempotency import IdempotencyIndex
from .manifest import Manifest
from .ops import JobOps
from .options import JobOptionsIn
from .redact import redact_paths
from .store import JobNotFound, new_job_id
from .uploads import UploadError, check_declared_length, receive_upload

log = logging.getLogger(__name__)

# HTTP status of each ingest refusal code (pipeline.ingest.archive / pipeline.ingest.intake); anything else is 422.
REFUSAL_STATUS = {"not_an_archive": 415, "too_large": 413, "file_too_large": 413, "too_many_entries": 413,
                  "compression_bomb": 413}


@dataclass(frozen=True)
class UploadRequest:
    """What the route hands over: the caller, the body and the headers that matter."""

    owner: str
    body: AsyncIterator[bytes]
    content_type: str
    content_length: str | None
    query: dict[str, str]
    idempotency_key: str | None = None


@dataclass(frozen=True)
class Submitted:
    manifest: Manifest
    created: bool  # False: a repeat (same Idempotency-Key, archive and options) answered with the first job


class UploadIntake:
    def __init__(self, settings: Settings, jobs: JobOps, coord: Coordinator, idempotency: IdempotencyIndex):
        self.settings, self.jobs, self.coord, self.idempotency = settings, jobs, coord, idempotency
        self.slots: anyio.Semaphore | None = None  # ingest_concurrency; made inside the running loop (open)

    def open(self) -> None:
        """Called by the app's lifespan, inside the event loop that will serve the uploads."""
        self.slots = anyio.Semaphore(self.settings.ingest_concurrency)

    async def submit(self, req: UploadRequest) -> Submitted:
        settings, jobs, owner, key = self.settings, self.jobs, req.owner, req.idempotency_key
        job_id = new_job_id()
        first: Manifest | None = None
        if key is not None:
            held = await anyio.to_thread.run_sync(self._claim_key, owner, key, job_id)
            if held is not None:
                if held.startswith("pending:"):
                    raise UploadError(409, "idempotency_in_progress",
                                      "a request with this Idempotency-Key is in progress")
                try:
                    first = await anyio.to_thread.run_sync(jobs.get, held, owner)
                except JobNotFound:
                    raise UploadError(409, "idempotency_key_used",
                                      "this Idempotency-Key belonged to a deleted job") from None
        job_dir = jobs.job_dir(job_id)
        created = False
        try:
            declared = check_declared_length(req.content_length, settings.max_upload_bytes)
            free = shutil.disk_usage(settings.data_dir).free
            if free - (declared or 0) < settings.min_free_bytes:
                raise UploadError(507, "insufficient_storage", "the server's data disk is too full for this upload")
            job_dir.mkdir(parents=True)
            up = await receive_upload(req.body, req.content_type, req.query, JobLayout(job_dir).upload,
                                      settings.max_upload_bytes)
            fields = {k: v for k, v in up.fields.items() if k != "filename"}
            callback_url = self._callback(owner, fields.pop("callback_url", None))
            options = self._options(fields)
            if first is not None:  # a repeat: the same request gets the first job, another request an error
                if not _same_request(first, up.sha256, options.model_dump(), callback_url):
                    raise UploadError(422, "idempotency_key_reused",
                                      f"this Idempotency-Key was used for job {first.id} with a different archive "
                                      f"or other options; use a new key for a new job")
                return Submitted(first, created=False)
            opts = {**options.model_dump(), "source": str(up.path)}
            async with self.slots:  # type: ignore[union-attr]
                result, seconds = await anyio.to_thread.run_sync(self._ingest, job_dir, opts)
            source = {"kind": "upload", "filename": up.filename, "bytes": up.bytes, "sha256": up.sha256}
            m = await anyio.to_thread.run_sync(lambda: jobs.create(job_id, owner, opts, source, ingest=result,
                                                                   ingest_seconds=seconds,
                                                                   callback_url=callback_url))
            created = True
            if key is not None:
                await anyio.to_thread.run_sync(self._confirm_key, owner, key, job_id)
        except DispatchError as e:
            created = True  # the job exists, failed with broker_unavailable; POST .../retry re-sends it
            if key is not None:
                try:
                    self._confirm_key(owner, key, job_id)
                except Exception as err:  # Redis is likely down too; the key then expires by itself
                    log.warning("could not record idempotency key: %s", err)
            raise DispatchError(f"{e} (job {job_id} was created; retry it later)") from None
        finally:
            if not created:
                shutil.rmtree(job_dir, ignore_errors=True)
                if key is not None and first is None:
                    try:
                        self.coord.release_idempotency(owner, key, job_id)
                    except Exception as e:  # the key expires by itself
                        log.warning("could not release idempotency key: %s", e)
        return Submitted(m, created=True)

    def _options(self, fields: dict[str, str]) -> JobOptionsIn:
        try:
            options = JobOptionsIn(**fields)
        except ValidationError as e:
            msg = "; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())
            raise UploadError(422, "invalid_options", msg) from None
        if (why := options.over_limit(self.settings.max_iterations)) is not None:
            raise UploadError(422, "invalid_options", why)
        return options

    def _callback(self, owner: str, url: str | None) -> str | None:
        """The job's callback URL if this server may call it for ``owner`` (service.webhooks.callback), else 422."""
        if url is None or url == "":
            return None
        s = self.settings
        try:
            return check_callback_url(url, s.webhook_allowed_hosts, s.webhook_secret(owner) is not None)
        except CallbackRefused as e:
            raise UploadError(422, e.code, str(e)) from None

    def _claim_key(self, owner: str, key: str, job_id: str) -> str | None:
        """None when ``key`` is new (claimed for ``job_id``), else what holds it: a job id, or ``pending:<id>``.
        The record on disk is asked first: it survives a Redis that lost its data (service.jobs.idempotency)."""
        rec = self.idempotency.lookup(owner, key)
        if rec is not None:
            return rec.job_id
        return self.coord.claim_idempotency(owner, key, job_id)

    def _confirm_key(self, owner: str, key: str, job_id: str) -> None:
        self.idempotency.record(owner, key, job_id)
        self.coord.confirm_idempotency(owner, key, job_id)

    def _ingest(self, job_dir: Path, opts: dict) -> tuple[dict, float]:
        """The pipeline's ingest stage (``pipeline.job.runner.run_stage``) with this deployment's limits; its completion
        marker makes the worker skip it. Refusals become UploadError."""
        s = self.settings
        t0 = time.time()
        ctx = StageContext(ingest=IngestConfig(min_images=s.min_images, limits=s.archive_limits()))
        try:
            result, _ = run_stage(job_dir, "ingest", JobOptions.from_json(opts), ctx)
        except (ArchiveError, IngestError) as e:  # messages name members as in the archive; redacting is a safety net
            raise UploadError(REFUSAL_STATUS.get(e.code, 422), e.code,
                              redact_paths(str(e), job_dir, s.data_dir)) from None
        return result, round(time.time() - t0, 3)


def _same_request(first: Manifest, sha256: str, options: dict, callback_url: str | None) -> bool:
    """A repeat of the request that made ``first``: the same archive bytes, options and callback URL."""
    kept = {k: v for k, v in first.options.items() if k != "source"}
    return first.source.get("sha256") == sha256 and kept == options and first.callback_url == callback_url
