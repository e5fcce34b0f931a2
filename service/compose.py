"""The composition root: the objects the API and the worker's tasks build from the settings, built in one place.

:func:`compose` is called once per API process (``service.app.create_app``) and once per task (``worker.tasks``:
the stage task and both survey scans). The Celery app that queues the next stages is the caller's and is handed
in: the API's producer (``service.core.broker.producer``) or the worker's own app. So nothing under ``service``
imports ``worker``; the worker imports the service (tests/service/test_boundaries.py).

Building connects to nothing and creates no folder: Redis is reached on first use, and the API's lifespan makes
the folders.
"""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import SecretStr

from .core.coord import Coordinator
from .core.dispatch import Dispatcher, TaskSender
from .core.settings import Settings
from .jobs.idempotency import IdempotencyIndex
from .jobs.ops import JobOps
from .jobs.store import JobStore
from .storage.jobs import SyncedJobStore
from .storage.objects import ObjectStore
from .surveys.registry import SurveyRegistry
from .surveys.scan import ScanConfig


@dataclass
class Components:
    settings: Settings
    store: JobStore
    coord: Coordinator
    jobs: JobOps
    surveys: SurveyRegistry
    scan_config: ScanConfig
    idempotency: IdempotencyIndex

    def close(self) -> None:
        """Release the Redis connections (the API at shutdown, a task when it ends)."""
        self.coord.close()


def compose(settings: Settings, celery_app: TaskSender | None) -> Components:
    """Everything derived from ``settings``; stages and scans are queued through ``celery_app`` (None: a set that
    cannot queue anything, for callers that only read or that put their own dispatcher on ``jobs``)."""
    store = job_store(settings)
    coord = Coordinator.from_url(settings.redis_url, settings.redis_prefix)
    dispatcher = Dispatcher(celery_app, settings.train_queue) if celery_app is not None else None
    return Components(
        settings=settings,
        store=store,
        coord=coord,
        jobs=JobOps(store, coord, dispatcher),
        surveys=SurveyRegistry(settings.surveys_dir, settings.survey_roots, settings.surveys_file,
                               settings.survey_min_interval_s, settings.max_iterations, settings.survey_owner_roots),
        scan_config=scan_config(settings),
        idempotency=IdempotencyIndex(settings.data_dir / "idempotency"),
    )


def job_store(settings: Settings) -> JobStore:
    """The data folder's job store, or with ``object_store_url`` the object store's (this host's folder its copy)."""
    if settings.object_store_url is None:
        return JobStore(settings.jobs_dir)
    return SyncedJobStore(settings.jobs_dir, ObjectStore(
        settings.object_store_url, settings.object_store_bucket, settings.object_store_prefix,
        _secret(settings.object_store_access_key), _secret(settings.object_store_secret_key),
        settings.object_store_region))


def _secret(value: SecretStr | None) -> str | None:
    return value.get_secret_value() if value is not None else None


def scan_config(settings: Settings) -> ScanConfig:
    """Survey sets are submitted from ``survey_min_images`` images (never below the upload minimum)."""
    return ScanConfig(min_images=max(settings.min_images, settings.survey_min_images),
                      settle_s=settings.survey_settle_s, gap_s=settings.survey_gap_s)
