"""/v1/jobs: create (upload), list, status, log, cancel, retry, delete."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Request, Response

from service.api.deps import JobDep, JobsDep, OwnerDep, ServicesDep
from service.api.errors import api_error
from service.api.schemas.inputs import JobCreateOptions
from service.api.schemas.responses import ErrorOut, JobList, JobOut, LogOut
from service.core.dispatch import DispatchError
from service.jobs.intake import UploadRequest
from service.jobs.ops import JobConflict, JobOps
from service.jobs.uploads import UploadError

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

ERRORS = {s: {"model": ErrorOut} for s in (400, 401, 404, 409, 413, 415, 422, 503, 507)}

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
    upload = UploadRequest(owner=owner, body=request.stream(), content_type=request.headers.get("content-type", ""),
                           content_length=request.headers.get("content-length"), query=dict(request.query_params),
                           idempotency_key=idempotency_key)
    try:
        done = await services.intake.submit(upload)
    except UploadError as e:
        raise api_error(e.status, e.code, str(e)) from None
    except DispatchError as e:
        raise api_error(503, "broker_unavailable", str(e)) from None
    if not done.created:
        response.status_code = 200
    else:
        response.headers["Location"] = f"/v1/jobs/{done.manifest.id}"
    return _view(services.jobs, done.manifest)


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
