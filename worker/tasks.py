"""Thin Celery tasks: build the components from settings (``service.compose``, with this worker's Celery app),
call one function, report. The bodies live in ``worker.runner`` (stages) and ``service.surveys.scan`` (folder
scans) and are tested without Celery."""

from __future__ import annotations

import logging
import time

from celery.signals import worker_ready, worker_shutdown

from service.compose import compose
from service.core.dispatch import DELIVER_WEBHOOK_TASK, RUN_STAGE_TASK, SCAN_SURVEY_TASK, SCAN_SURVEYS_TASK
from service.core.settings import load_settings
from service.surveys.registry import SurveyNotFound
from service.surveys.scan import scan
from service.webhooks.deliver import deliver

from .app import app
from .heartbeat import on_worker_ready, on_worker_shutdown
from .process import prepare_stage_process
from .runner import execute_stage

log = logging.getLogger(__name__)

# the worker's main process announces itself in Redis for /ready (worker.heartbeat); weak=False: module functions
worker_ready.connect(on_worker_ready, weak=False)
worker_shutdown.connect(on_worker_shutdown, weak=False)


@app.task(name=RUN_STAGE_TASK, bind=True, acks_late=True, reject_on_worker_lost=True, max_retries=None,
          ignore_result=True)
def run_stage(self, job_id: str, stage: str, run_id: str) -> str:
    """Run ``stage`` of run ``run_id`` of job ``job_id`` (idempotent; see worker.runner)."""
    prepare_stage_process()
    rt = compose(load_settings(), self.app)
    try:
        out = execute_stage(rt, job_id, stage, run_id, hostname=self.request.hostname or "")
    finally:
        rt.close()
    log.info("job %s stage %s: %s %s", job_id, stage, out.status, out.detail)
    if out.retry_after is not None:
        raise self.retry(countdown=out.retry_after, queue=rt.jobs.dispatcher.queue_for(stage))
    return out.status


@app.task(name=SCAN_SURVEYS_TASK, ignore_result=True)
def scan_surveys() -> int:
    """Beat's tick: scan every survey whose interval has passed. Returns how many jobs were submitted."""
    rt = compose(load_settings(), app)
    n = 0
    try:
        now = time.time()
        for survey in rt.surveys.all():
            if now - rt.surveys.state(survey.id).last_scan_at < survey.interval_s:
                continue
            with rt.coord.scan_lock(survey.id) as got:
                if got:
                    n += len(scan(rt.surveys, survey, rt.jobs, rt.scan_config))
    finally:
        rt.close()
    return n


@app.task(name=SCAN_SURVEY_TASK, ignore_result=True)
def scan_survey(survey_id: str) -> int:
    """Scan one survey now (``POST /v1/surveys/{id}/scan``)."""
    rt = compose(load_settings(), app)
    try:
        try:
            survey = rt.surveys.get(survey_id)
        except SurveyNotFound:
            return 0
        with rt.coord.scan_lock(survey.id) as got:
            return len(scan(rt.surveys, survey, rt.jobs, rt.scan_config)) if got else 0
    finally:
        rt.close()


@app.task(name=DELIVER_WEBHOOK_TASK, bind=True, acks_late=True, max_retries=None, ignore_result=True)
def deliver_webhook(self, job_id: str, delivery_id: str) -> str:
    """One attempt at a webhook delivery (service.webhooks.deliver); a failed attempt comes back after its
    backoff until the job's record says it was delivered or given up. Never touches a stage."""
    rt = compose(load_settings(), self.app)
    try:
        out = deliver(rt, job_id, delivery_id)
    finally:
        rt.close()
    if out.retry_after is not None:
        # the manifest counts the attempts (not Celery's retries), so max_retries=None: give-up is its decision
        raise self.retry(countdown=out.retry_after)
    return out.status
