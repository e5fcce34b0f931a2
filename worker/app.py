"""The Celery application (``celery -A worker.app worker|beat``).

Importing this module creates the app object and nothing else: the configuration is read from the
``DUALPHYS_*`` environment only when Celery first needs it, and no task module imports torch (the stage
functions load it inside the prefork child that runs them: a child forked after torch ran hangs; docs/DECISIONS.md,
"Numbers behind code comments").

Queues: ``cpu`` (every stage but train, and train unless ``DUALPHYS_TRAIN_QUEUE=gpu``), ``gpu`` (train on GPU
workers), ``surveys`` (folder scans from beat). Delivery: acks_late + prefetch 1 + reject on worker loss, so
a task whose worker dies is delivered again; the broker's visibility timeout redelivers a task that was never
acknowledged, and the per-job lock plus stage markers make every redelivery harmless.
"""

from __future__ import annotations

from celery import Celery
from kombu import Exchange, Queue

from service.dispatch import CPU_QUEUE, GPU_QUEUE, SCAN_SURVEYS_TASK, SURVEY_QUEUE
from service.settings import Settings, load_settings

EXCHANGE = Exchange("dualphys", type="direct")


def celery_config(settings: Settings) -> dict:
    return {
        "broker_url": settings.redis_url,
        "broker_transport_options": {
            "global_keyprefix": f"{settings.redis_prefix}:",
            "visibility_timeout": settings.visibility_timeout_s,
            "unacked_restore_interval": settings.restore_interval_s,
            "unacked_restore_throttle": 1,
            "socket_timeout": 30,
            "socket_connect_timeout": 10,
        },
        "broker_connection_retry_on_startup": True,
        "result_backend": None,
        "task_ignore_result": True,
        "task_serializer": "json",
        "accept_content": ["json"],
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "worker_prefetch_multiplier": 1,
        "worker_max_tasks_per_child": settings.max_tasks_per_child or None,
        "worker_max_memory_per_child": settings.max_memory_per_child_mb * 1024 or None,  # KiB
        "worker_send_task_events": False,
        "task_default_queue": CPU_QUEUE,
        "task_default_exchange": EXCHANGE.name,
        "task_default_routing_key": CPU_QUEUE,
        "task_create_missing_queues": False,
        # each queue has its own routing key: a message lands in exactly one queue
        "task_queues": tuple(Queue(q, EXCHANGE, routing_key=q) for q in (CPU_QUEUE, GPU_QUEUE, SURVEY_QUEUE)),
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
    app = Celery("dualphys", include=["worker.tasks"], set_as_current=False)
    if settings is not None:
        app.conf.update(celery_config(settings))
    else:
        app.add_defaults(lambda: celery_config(load_settings()))
    return app


app = create_celery()
