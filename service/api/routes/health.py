"""/health (the process answers) and /ready (Redis and the object store, if any, reachable; data disk writable
with room; with ``require_workers``, a live worker on every queue jobs need). No auth."""

from __future__ import annotations

import shutil
import tempfile

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.api.deps import ServicesDep
from service.api.errors import error_body
from service.api.schemas.responses import HealthOut, ReadyOut
from service.core.dispatch import CPU_QUEUE, GPU_QUEUE, SURVEY_QUEUE

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut, summary="Liveness")
def health() -> HealthOut:
    return HealthOut(status="ok")


def _workers(services) -> tuple[dict[str, int], list[str]]:
    """Live workers per queue, and a warning for each queue jobs need that nobody consumes. The API stays
    ready without workers (uploads are accepted and queued) unless ``require_workers`` says the operator started
    them (``dualphys serve``): then a queue without one makes it not ready."""
    live = services.coord.workers()
    per_queue = {q: sum(q in qs for qs in live.values()) for q in (CPU_QUEUE, GPU_QUEUE, SURVEY_QUEUE)}
    needed = [CPU_QUEUE, SURVEY_QUEUE] + ([GPU_QUEUE] if services.settings.train_queue == GPU_QUEUE else [])
    return per_queue, [f"no worker consumes the {q!r} queue" for q in needed if not per_queue[q]]


@router.get("/ready", response_model=ReadyOut, summary="Readiness",
            responses={503: {"description": "not ready: the error body plus the checks"}})
def ready(services: ServicesDep) -> JSONResponse:
    s = services.settings
    redis_ok = services.coord.ping()
    try:
        free = shutil.disk_usage(s.data_dir).free
        with tempfile.TemporaryFile(dir=s.data_dir):
            writable = True
    except OSError:
        free, writable = 0, False
    per_queue, warnings = _workers(services) if redis_ok else ({}, [])
    store_ok = services.jobs.store.reachable()
    body = ReadyOut(status="ready", redis=redis_ok, data_dir_writable=writable, disk_free_bytes=free,
                    min_free_bytes=s.min_free_bytes, workers=per_queue, workers_ok=redis_ok and not warnings,
                    warnings=warnings, object_store=store_ok)
    problems = [msg for bad, msg in ((not redis_ok, "Redis is not reachable"),
                                     (store_ok is False, "the object store is not reachable"),
                                     (not writable, "the data folder is not writable"),
                                     (free < s.min_free_bytes, "the data disk is nearly full"),
                                     (s.require_workers and bool(warnings), "; ".join(warnings))) if bad]
    if not problems:
        return JSONResponse(body.model_dump())
    body.status = "not_ready"
    return JSONResponse({**error_body("not_ready", "; ".join(problems)), **body.model_dump()}, status_code=503)
