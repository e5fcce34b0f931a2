"""The Celery message contract the API (sender) and the workers (consumers) share: the broker connection,
serialisation, the exchange and the queues. ``worker.app`` adds the consumer's own settings (acks, prefetch,
pool children, the beat schedule) and the task modules.

Delivery (docs/SERVICE.md, "The worker"): the broker's visibility timeout redelivers a task that was never
acknowledged; the per-job lock plus stage markers make every redelivery harmless.
"""

from __future__ import annotations

from typing import Any

from celery import Celery
from kombu import Exchange, Queue

from .dispatch import CPU_QUEUE, GPU_QUEUE, SURVEY_QUEUE
from .settings import Settings

EXCHANGE = Exchange("dualphys", type="direct")
APP_NAME = "dualphys"


def broker_config(settings: Settings) -> dict[str, Any]:
    """Celery configuration both sides need to exchange messages."""
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
        "task_default_queue": CPU_QUEUE,
        "task_default_exchange": EXCHANGE.name,
        "task_default_routing_key": CPU_QUEUE,
        "task_create_missing_queues": False,
        # each queue has its own routing key: a message lands in exactly one queue
        "task_queues": tuple(Queue(q, EXCHANGE, routing_key=q) for q in (CPU_QUEUE, GPU_QUEUE, SURVEY_QUEUE)),
    }


def producer(settings: Settings) -> Celery:
    """A Celery app that only sends tasks (the API's): the message contract, no task modules, no worker settings.

    Building it connects to nothing; the first ``send_task`` does."""
    app = Celery(APP_NAME, set_as_current=False)
    app.conf.update(broker_config(settings))
    return app
