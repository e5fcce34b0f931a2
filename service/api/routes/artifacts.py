"""/v1/jobs/{id}/artifacts and /bundle: list with sizes and SHA-256, one file (HTTP Range), or all as a zip;
/previews: small JPEGs of the photos and their restored versions (the dashboard's gallery)."""

from __future__ import annotations

from typing import Annotated, Literal
from urllib.parse import quote

from fastapi import APIRouter, Header
from fastapi.responses import FileResponse, StreamingResponse

from service.api.deps import JobDep, JobsDep
from service.api.errors import api_error
from service.api.schemas.responses import ArtifactList, ArtifactOut, ErrorOut
from service.jobs.artifacts import find_artifact, list_artifacts, media_type, zip_stream
from service.jobs.previews import preview

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["artifacts"])
ERRORS = {s: {"model": ErrorOut} for s in (401, 404, 409, 416)}


@router.get("/artifacts", response_model=ArtifactList, responses=ERRORS, summary="List the job's results")
def get_artifacts(job: JobDep, jobs: JobsDep) -> ArtifactList:
    items = list_artifacts(jobs.job_dir(job.id))
    return ArtifactList(job_id=job.id, artifacts=[
        ArtifactOut(path=a.path, size=a.size, sha256=a.sha256, media_type=a.media_type,
                    url=f"/v1/jobs/{job.id}/artifacts/{quote(a.path)}") for a in items])


@router.get("/artifacts/{path:path}", responses={**ERRORS, 206: {"description": "partial content (Range)"}},
            response_class=FileResponse, summary="Download one result (supports Range)")
def get_artifact(job: JobDep, jobs: JobsDep, path: str,
                 range_header: Annotated[str | None, Header(alias="Range")] = None) -> FileResponse:
    p = find_artifact(jobs.job_dir(job.id), path)
    if p is None:
        raise api_error(404, "artifact_not_found", f"job {job.id} has no artifact {path!r}")
    _check_range(range_header, p.stat().st_size)
    return FileResponse(p, media_type=media_type(path), filename=p.name, content_disposition_type="attachment")


def _check_range(header: str | None, size: int) -> None:
    """Refuse a malformed or unsatisfiable Range with a JSON error (FileResponse would answer in plain text)."""
    if header is None:
        return
    unit, _, spec = header.partition("=")
    bad = api_error(400, "bad_range", f"cannot parse Range {header!r}")
    if unit.strip().lower() != "bytes" or not spec.strip():
        raise bad
    for part in spec.split(","):
        first, sep, last = part.strip().partition("-")
        if not sep or not (first or last) or not (first or "0").isdigit() or not (last or "0").isdigit():
            raise bad
        if first and int(first) >= size:
            raise api_error(416, "range_not_satisfiable", f"the file has {size} bytes",
                            headers={"Content-Range": f"bytes */{size}"})


@router.get("/bundle", responses={**ERRORS, 200: {"content": {"application/zip": {}}}},
            response_class=StreamingResponse, summary="Download every result as one zip")
def get_bundle(job: JobDep, jobs: JobsDep) -> StreamingResponse:
    job_dir = jobs.job_dir(job.id)
    items = list_artifacts(job_dir)
    if not items:
        raise api_error(409, "no_artifacts", "the job has no results yet")
    return StreamingResponse(zip_stream(job_dir, items), media_type="application/zip",
                             headers={"Content-Disposition": f'attachment; filename="{job.id}.zip"'})


@router.get("/previews/{kind}/{stem}", responses={**ERRORS, 200: {"content": {"image/jpeg": {}}}},
            response_class=FileResponse, summary="A photo or its restored version, small (JPEG, long side <= 640)")
def get_preview(job: JobDep, jobs: JobsDep, kind: Literal["original", "restored"], stem: str) -> FileResponse:
    """``stem`` is the photo's file name without its extension (``output/restored/<stem>.*`` names it too)."""
    p = preview(jobs.job_dir(job.id), kind, stem)
    if p is None:
        raise api_error(404, "preview_not_found", f"job {job.id} has no {kind} photo {stem!r} (yet)")
    return FileResponse(p, media_type="image/jpeg", headers={"Cache-Control": "private, max-age=300"})
