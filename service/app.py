"""The FastAPI application factory: ``uvicorn --factory service.app:create_app``.

Nothing happens at import: settings are read and the objects built (``service.compose``, with the Celery app
that sends the tasks: the caller's, else a producer for the settings' broker) when the app is created; folders
are made, half-finished uploads swept and the watchdog (``service.jobs.watchdog``) started when it starts.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import redis
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from .api.deps import Services
from .api.errors import error_body, install_error_handlers
from .api.routes import artifacts, health, jobs, surveys
from .api.routes.web import mount_dashboard
from .compose import compose
from .core.broker import producer
from .core.dispatch import TaskSender
from .core.settings import Settings, load_settings
from .jobs.store import StoreUnavailable
from .jobs.watchdog import Watchdog, start_watchdog

log = logging.getLogger(__name__)

DESCRIPTION = """Underwater survey images in, a 3D Gaussian reconstruction out.

Authenticate with `Authorization: Bearer <API key>`. Errors are JSON `{"error": {"code", "message"}}` with a
4xx/5xx status; the codes are listed in docs/SERVICE.md."""


def create_app(settings: Settings | None = None, celery_app: TaskSender | None = None) -> FastAPI:
    """The API for ``settings`` (default: the environment). Stages and scans are queued through ``celery_app``
    (default: ``service.core.broker.producer(settings)``, which sends to the queues ``worker.app`` consumes)."""
    settings = settings or load_settings()
    services = Services.of(compose(settings, celery_app if celery_app is not None else producer(settings)))

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services.jobs.store.ensure()
        settings.surveys_dir.mkdir(parents=True, exist_ok=True)
        swept = services.jobs.store.sweep_incomplete()
        if swept:
            log.info("removed %d abandoned upload folder(s)", swept)
        services.intake.open()
        app.state.services = services
        # unfinished jobs nobody runs are re-queued from here (service/jobs/watchdog.py says why not from beat)
        stop_watchdog = start_watchdog(Watchdog(services.jobs, services.coord, settings.watchdog_grace_s),
                                       settings.watchdog_every_s)
        yield
        stop_watchdog.set()
        services.coord.close()

    app = FastAPI(title="dualphys", version="1", description=DESCRIPTION, lifespan=lifespan)
    app.state.services = services
    install_error_handlers(app)

    @app.exception_handler(redis.RedisError)
    async def _redis_down(request: Request, exc: redis.RedisError) -> JSONResponse:
        log.error("Redis error on %s %s: %s", request.method, request.url.path, exc)
        return JSONResponse(error_body("redis_unavailable", "the coordinator (Redis) is unavailable"), 503)

    @app.exception_handler(StoreUnavailable)
    async def _store_down(request: Request, exc: StoreUnavailable) -> JSONResponse:
        log.error("object store error on %s %s: %s", request.method, request.url.path, exc)
        return JSONResponse(error_body("object_store_unavailable", "the object store is unavailable"), 503)

    @app.exception_handler(TimeoutError)
    async def _busy(request: Request, exc: TimeoutError) -> JSONResponse:
        return JSONResponse(error_body("busy", str(exc) or "the job is busy; try again"), 503)

    for r in (health.router, jobs.router, artifacts.router, surveys.router):
        app.include_router(r)
    mount_dashboard(app)
    return app
