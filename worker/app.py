"""The Celery application (``celery -A worker.app worker|beat``).

Importing this module creates the app object and nothing else: the configuration is read from the
``DUALPHYS_*`` environment only when Celery first needs it, and no task module imports torch (the stage
functions load it inside the prefork child that runs them: a child forked after torch ran hangs; docs/DECISIONS.md,
"Numbers behind code comments").

Queues: ``cpu`` (every stage but train, and train unless ``DUALPHYS_TRAIN_QUEUE=gpu``), ``gpu`` (train on GPU
workers), ``surveys`` (folder scans from beat, webhook deliveries). The message contract (broker, serialisation,
exchange, queues) is ``service.core.broker``'s, shared with the API's producer; this module adds the consumer's side.
Delivery: acks_late + prefetch 1 + reject on worker loss, so a task whose worker dies is delivered again; the broker's
visibility timeout redelivers a task that was never acknowledged, and the per-job lock plus stage markers make
every redelivery harmless. The tasks hand this app to ``service.compose`` to queue the next stages.
"""

from __future__ import annotations

from celery import Celery

from service.core.broker import APP_NAME, broker_config
from service.core.dispatch import SCAN_SURVEYS_TASK, SURVEY_QUEUE
from service.core.settings import Settings, load_settings


def celery_config(settings: Settings) -> dict:
    return {
        **broker_config(settings),
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "worker_prefetch_multiplier": 1,
        "worker_max_tasks_per_child": settings.max_tasks_per_child or None,
        "worker_max_memory_per_child": settings.max_memory_per_child_mb * 1024 or None,  # KiB
        "worker_send_task_events": False,
        "beat_schedule": {
            "scan-survey-folders": {
                "task": SCAN_SURVEYS_TASK,
                "schedule": settings.survey_tick_s,
                # a tick nobody picked up before the next one is worthless
                "options": {"queue": SURVEY_QUEUE, "expires": settings.survey_tick_s},
            },
        },
    }


def create_celery(settings: Settings | None = None) -> Celery:
    """An app configured from ``settings``, or lazily from the environment when None."""
    app = Celery(APP_NAME, include=["worker.tasks"], set_as_current=False)
    if settings is not None:
        app.conf.update(celery_config(settings))
    else:
        app.add_defaults(lambda: celery_config(load_settings()))
    return app


app = create_celery()
