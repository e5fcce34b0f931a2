"""Sending stage tasks: one message per (job, stage, run). The API and the workers both send through this, each
with its own Celery app (the API's producer from ``service.core.broker``, the worker's own app), handed in by
whoever builds the dispatcher (``service.compose``)."""

from __future__ import annotations

import logging
from typing import Any, Protocol

from kombu.exceptions import KombuError
from redis.exceptions import RedisError

from pipeline.job.table import stage as table_stage

log = logging.getLogger(__name__)

RUN_STAGE_TASK = "dualphys.run_stage"
SCAN_SURVEYS_TASK = "dualphys.scan_surveys"
SCAN_SURVEY_TASK = "dualphys.scan_survey"
DELIVER_WEBHOOK_TASK = "dualphys.deliver_webhook"
CPU_QUEUE, GPU_QUEUE, SURVEY_QUEUE = "cpu", "gpu", "surveys"
# Webhook deliveries share the light queue of the folder scans: every worker that scans also delivers (no new
# -Q to forget in a deployment), and neither waits behind a stage on a worker that has a spare process for it.
WEBHOOK_QUEUE = SURVEY_QUEUE


class DispatchError(RuntimeError):
    """The broker did not take the message (Redis down)."""


class TaskSender(Protocol):
    """What the dispatcher sends through: a Celery app (``celery.Celery.send_task``)."""

    def send_task(self, name: str, args: Any = None, **options: Any) -> Any: ...


class Dispatcher:
    def __init__(self, celery_app: TaskSender, train_queue: str = CPU_QUEUE):
        self.app = celery_app
        self.train_queue = train_queue

    def queue_for(self, stage: str) -> str:
        """The stage table's queue (``pipeline.job.table``): training on this deployment's train queue (cpu or
        gpu), every other stage on the cpu queue."""
        return self.train_queue if table_stage(stage).queue == "train" else CPU_QUEUE

    def send_stage(self, job_id: str, stage: str, run_id: str) -> str:
        try:
            res = self.app.send_task(RUN_STAGE_TASK, args=[job_id, stage, run_id], queue=self.queue_for(stage))
        except (KombuError, RedisError, OSError) as e:
            raise DispatchError(f"could not queue stage {stage} of job {job_id}: {e}") from e
        log.info("queued %s of job %s (run %s) on %s as %s", stage, job_id, run_id, self.queue_for(stage), res.id)
        return res.id

    def send_webhook(self, job_id: str, delivery_id: str, countdown: float | None = None) -> str:
        try:
            return self.app.send_task(DELIVER_WEBHOOK_TASK, args=[job_id, delivery_id], queue=WEBHOOK_QUEUE,
                                      countdown=countdown).id
        except (KombuError, RedisError, OSError) as e:
            raise DispatchError(f"could not queue webhook {delivery_id} of job {job_id}: {e}") from e

    def send_scan(self, survey_id: str) -> str:
        try:
            return self.app.send_task(SCAN_SURVEY_TASK, args=[survey_id], queue=SURVEY_QUEUE).id
        except (KombuError, RedisError, OSError) as e:
            raise DispatchError(f"could not queue a scan of survey {survey_id}: {e}") from e
