"""/v1/jobs: create (upload), list, status, log, cancel, retry, delete."""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path
from typing import Annotated, Literal

import anyio
from fastapi import APIRouter, Header, Query, Request, Response
from pydantic import ValidationError

from pipeline.job.layout import JobLayout
from service.api.deps import JobDep, JobsDep, OwnerDep, ServicesDep
from service.api.errors import api_error
from service.api.schemas.requests import JobCreateOptions
from service.api.schemas.responses import ErrorOut, JobList, JobOut, LogOut
from service.dispatch import DispatchError
from service.jobs import JobConflict, JobOps
from service.manifest import Manifest
from service.redact import redact_paths
from service.settings import Settings
from service.store import JobNotFound, new_job_id
from service.uploads import UploadError, check_declared_length, receive_upload

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

ERRORS = {s: {"model": ErrorOut} for s in (400, 401, 404, 409, 413, 415, 422, 503, 507)}

# HTTP status of each ingest refusal code (pipeline.ingest.archive / pipeline.ingest.intake); anything else is 422.
REFUSAL_STATUS = {"not_an_archive": 415, "too_large": 413, "file_too_large": 413, "too_many_entries": 413,
                  "compression_bomb": 413}

UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {"schema": {
                "type": "object", "required": ["archive"],
                "properties": {"archive": {"type": "string", "format": "binary",
                                           "description": "zip or tar (optionally gz/bz2/xz) of the images"},
                               **{k: {"type": "string"} for k in JobCreateOptions.model_fields}},
            }},
            "application/zip": {"schema": {"type": "string", "format": "binary"}},
            "application/x-tar": {"schema": {"type": "string", "format": "binary"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        },
    },
}


def _conflict(e: JobConflict):
    return api_error(409, e.code, str(e))


def _view(jobs: JobOps, m) -> JobOut:
    return JobOut.from_view(jobs.view(m))


@router.post("", status_code=201, response_model=JobOut, responses=ERRORS, openapi_extra=UPLOAD_BODY,
             summary="Upload an image archive and start a job")
async def create_job(
    request: Request,
    response: Response,
    owner: OwnerDep,
    services: ServicesDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key", min_length=1, max_length=200)] = None,
) -> JobOut:
    """Streams the archive into a new job folder (byte cap), validates and unpacks it by running the ingest
    stage (hostile archives, undecodable images and too-small sets are refused here with a 4xx), then queues
    the remaining stages. With ``Idempotency-Key``, repeating the request (same archive, same options) returns
    the first job (200); the same key with another archive or other options is a 422."""
    settings, jobs, coord = services.settings, services.jobs, services.coord
    job_id = new_job_id()
    first: Manifest | None = None
    if idempotency_key is not None:
        held = await anyio.to_thread.run_sync(_claim_key, services, owner, idempotency_key, job_id)
        if held is not None:
            if held.startswith("pending:"):
                raise api_error(409, "idempotency_in_progress", "a request with this Idempotency-Key is in progress")
            try:
                first = await anyio.to_thread.run_sync(jobs.get, held, owner)
            except JobNotFound:
                raise api_error(409, "idempotency_key_used", "this Idempotency-Key belonged to a deleted job") from None
    job_dir = jobs.job_dir(job_id)
    created = False
    try:
        declared = check_declared_length(request.headers.get("content-length"), settings.max_upload_bytes)
        free = shutil.disk_usage(settings.data_dir).free
        if free - (declared or 0) < settings.min_free_bytes:
            raise UploadError(507, "insufficient_storage", "the server's data disk is too full for this upload")
        job_dir.mkdir(parents=True)
        up = await receive_upload(request.stream(), request.headers.get("content-type", ""),
                                  dict(request.query_params), JobLayout(job_dir).upload,
                                  settings.max_upload_bytes)
        fields = {k: v for k, v in up.fields.items() if k != "filename"}
        try:
            options = JobCreateOptions(**fields)
        except ValidationError as e:
            msg = "; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())
            raise UploadError(422, "invalid_options", msg) from None
        if (why := options.over_limit(settings.max_iterations)) is not None:
            raise UploadError(422, "invalid_options", why)
        if first is not None:  # a repeat: the same request gets the first job, another request an error
            if not _same_request(first, up.sha256, options.model_dump()):
                raise UploadError(422, "idempotency_key_reused",
                                  f"this Idempotency-Key was used for job {first.id} with a different archive or "
                                  f"other options; use a new key for a new job")
            response.status_code = 200
            return _view(jobs, first)
        opts = {**options.model_dump(), "source": str(up.path)}
        async with services.ingest_slots:  # type: ignore[attr-defined]
            result, seconds = await anyio.to_thread.run_sync(_run_ingest, settings, job_dir, up.path, opts)
        source = {"kind": "upload", "filename": up.filename, "bytes": up.bytes, "sha256": up.sha256}
        m = await anyio.to_thread.run_sync(lambda: jobs.create(job_id, owner, opts, source, ingest=result,
                                                               ingest_seconds=seconds))
        created = True
        if idempotency_key is not None:
            await anyio.to_thread.run_sync(_confirm_key, services, owner, idempotency_key, job_id)
    except UploadError as e:
        raise api_error(e.status, e.code, str(e)) from None
    except DispatchError as e:
        created = True  # the job exists, failed with broker_unavailable; POST .../retry re-sends it
        if idempotency_key is not None:
            try:
                _confirm_key(services, owner, idempotency_key, job_id)
            except Exception as err:  # Redis is likely down too; the key then expires by itself
                log.warning("could not record idempotency key: %s", err)
        raise api_error(503, "broker_unavailable", f"{e} (job {job_id} was created; retry it later)") from None
    finally:
        if not created:
            shutil.rmtree(job_dir, ignore_errors=True)
            if idempotency_key is not None and first is None:
                try:
                    coord.release_idempotency(owner, idempotency_key, job_id)
                except Exception as e:  # the key expires by itself
                    log.warning("could not release idempotency key: %s", e)
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    return _view(jobs, m)


def _claim_key(services, owner: str, key: str, job_id: str) -> str | None:
    """None when ``key`` is new (claimed for ``job_id``), else what holds it: a job id, or ``pending:<id>``.
    The record on disk is asked first: it survives a Redis that lost its data (service.idempotency)."""
    rec = services.idempotency.lookup(owner, key)
    if rec is not None:
        return rec.job_id
    return services.coord.claim_idempotency(owner, key, job_id)


def _confirm_key(services, owner: str, key: str, job_id: str) -> None:
    services.idempotency.record(owner, key, job_id)
    services.coord.confirm_idempotency(owner, key, job_id)


def _same_request(first: Manifest, sha256: str, options: dict) -> bool:
    """A repeat of the request that made ``first``: the same archive bytes and the same options."""
    kept = {k: v for k, v in first.options.items() if k != "source"}
    return first.source.get("sha256") == sha256 and kept == options


def _run_ingest(settings: Settings, job_dir: Path, archive: Path, opts: dict) -> tuple[dict, float]:
    """The pipeline's ingest stage with this deployment's archive limits; its marker makes the worker skip it.

    (``pipeline.job.runner.run_stage`` would use the default limits; see docs/SERVICE.md.) Refusals become UploadError.
    """
    from pipeline.ingest.archive import ArchiveError
    from pipeline.ingest.intake import IngestConfig, IngestError, ingest
    from pipeline.job.markers import run_marked
    from pipeline.job.options import JobOptions
    from pipeline.job.runner import stage_config

    t0 = time.time()
    cfg = IngestConfig(min_images=settings.min_images, limits=settings.archive_limits())
    try:
        result, _ = run_marked(job_dir, "ingest", stage_config(JobOptions.from_json(opts), "ingest"),
                               lambda: ingest(archive, job_dir, cfg).to_json())
    except (ArchiveError, IngestError) as e:  # messages name members as in the archive; redacting is a safety net
        raise UploadError(REFUSAL_STATUS.get(e.code, 422), e.code,
                          redact_paths(str(e), job_dir, settings.data_dir)) from None
    return result, round(time.time() - t0, 3)


@router.get("", response_model=JobList, responses=ERRORS, summary="List your jobs, newest first")
def list_jobs(
    owner: OwnerDep,
    jobs: JobsDep,
    status: Annotated[Literal["queued", "running", "done", "failed", "cancelled"] | None, Query()] = None,
    survey: Annotated[str | None, Query(max_length=64)] = None,
    offset: Annotated[int, Query(ge=0)] = 0,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
) -> JobList:
    found = jobs.list(owner, status, survey)
    page = found[offset:offset + limit]
    nxt = offset + limit if offset + limit < len(found) else None
    return JobList(jobs=[_view(jobs, m) for m in page], total=len(found), offset=offset, limit=limit, next_offset=nxt)


@router.get("/{job_id}", response_model=JobOut, responses=ERRORS, summary="Job status")
def get_job(job: JobDep, jobs: JobsDep) -> JobOut:
    return _view(jobs, job)


@router.get("/{job_id}/log", response_model=LogOut, responses=ERRORS, summary="The job's log from a byte offset")
def get_log(job: JobDep, jobs: JobsDep, offset: Annotated[int, Query(ge=0)] = 0,
            limit: Annotated[int, Query(ge=1, le=1 << 20)] = 64 << 10) -> LogOut:
    text, nxt, size = jobs.store.read_log(job.id, offset, limit)
    return LogOut(offset=offset, next_offset=nxt, size=size, text=text)


@router.post("/{job_id}/cancel", status_code=202, response_model=JobOut, responses=ERRORS, summary="Cancel a job")
def cancel_job(job: JobDep, owner: OwnerDep, jobs: JobsDep) -> JobOut:
    """A queued job is cancelled at once; a running one stops at its next cancel check (every training
    iteration; SfM and export finish their current step first), keeping finished stages and checkpoints."""
    try:
        return _view(jobs, jobs.cancel(job.id, owner))
    except JobConflict as e:
        raise _conflict(e) from None


@router.post("/{job_id}/retry", status_code=202, response_model=JobOut, responses=ERRORS,
             summary="Run a failed or cancelled job again from its first unfinished stage")
def retry_job(job: JobDep, owner: OwnerDep, jobs: JobsDep) -> JobOut:
    try:
        return _view(jobs, jobs.retry(job.id, owner))
    except JobConflict as e:
        raise _conflict(e) from None
    except DispatchError as e:
        raise api_error(503, "broker_unavailable", str(e)) from None


@router.delete("/{job_id}", status_code=204, responses=ERRORS, summary="Delete a job and its files")
def delete_job(job: JobDep, owner: OwnerDep, jobs: JobsDep) -> Response:
    try:
        jobs.delete(job.id, owner)
    except JobConflict as e:
        raise _conflict(e) from None
    return Response(status_code=204)
