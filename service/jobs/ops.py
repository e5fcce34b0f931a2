"""Job operations shared by the API, the worker and the survey scanner: create and dispatch, cancel, retry,
delete, the status view. Every manifest change is a read-modify-write under the job's Redis mutex; domain
errors here carry a stable ``code`` and the routes turn them into HTTP responses.
"""

from __future__ import annotations

import logging
import secrets
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.job.markers import atomic_write_json
from pipeline.job.options import JobOptions
from pipeline.job.runner import first_unfinished
from pipeline.job.table import STAGES
from service.core.coord import Coordinator
from service.core.dispatch import Dispatcher, DispatchError
from service.webhooks.events import plan_event

from .manifest import TERMINAL_STATES, JobError, Manifest, RunRecord, StageRecord, WebhookDelivery, overall_progress
from .store import JobNotFound, JobStore

log = logging.getLogger(__name__)


class JobConflict(RuntimeError):
    """The job is in a state where the operation makes no sense (code says which)."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def new_run_id() -> str:
    return secrets.token_hex(6)


def pipeline_stages() -> tuple[str, ...]:
    return tuple(STAGES)


@dataclass
class StatusView:
    """A manifest with the live progress cache folded in (what GET /jobs/{id} shows)."""

    manifest: Manifest
    state: str
    stage: str | None
    progress: float
    message: str
    worker_lost: bool = False


class JobOps:
    def __init__(self, store: JobStore, coord: Coordinator, dispatcher: Dispatcher | None):
        self.store = store
        self.coord = coord
        self.dispatcher = dispatcher

    # ---- create
    def create(self, job_id: str, owner: str, options: dict, source: dict, *, survey_id: str | None = None,
               ingest: dict | None = None, ingest_seconds: float | None = None,
               callback_url: str | None = None) -> Manifest:
        """Write job.json and the manifest of a job whose folder exists, then queue its first unfinished stage."""
        now = time.time()
        stages = pipeline_stages()
        run_id = new_run_id()
        m = Manifest(id=job_id, owner=owner, created_at=now, updated_at=now, run_id=run_id, options=options,
                     source=source, survey_id=survey_id, ingest=ingest, callback_url=callback_url,
                     stages={s: StageRecord() for s in stages})
        if ingest is not None:  # the API validated the upload by running the ingest stage itself
            m.stages["ingest"] = StageRecord(status="done", started_at=now - (ingest_seconds or 0), finished_at=now,
                                             seconds=ingest_seconds, attempts=1)
        first = m.next_stage(stages)
        m.runs.append(RunRecord(run_id=run_id, from_stage=first, queued_at=now))
        m.progress = self._done_progress(m)
        atomic_write_json(self.store.layout(job_id).options, options)
        # the input's name as the client knows it (the report shows it; the folder only has input/archive)
        atomic_write_json(self.store.layout(job_id).source_name,
                          {"name": source.get("filename") or source.get("set") or source.get("kind")})
        self.store.write(m)
        self.store.append_log(job_id, f"INFO service: job created by {owner} ({source.get('kind')}); "
                                      f"first stage {first}")
        if ingest is not None:
            skipped = ", ".join(f"{s['file']} ({s['reason']})" for s in ingest.get("skipped", [])) or "none"
            self.store.append_log(job_id, f"INFO service: upload checked: {len(ingest.get('images', []))} images, "
                                          f"{len(ingest.get('ignored', []))} non-image files ignored, "
                                          f"undecodable files skipped: {skipped}")
        return self.dispatch(job_id, run_id, first)

    def _done_progress(self, m: Manifest) -> float:
        stages = pipeline_stages()
        return overall_progress(stages, {s for s in stages if m.stage(s).status == "done"}, None, 0.0)

    def dispatch(self, job_id: str, run_id: str, stage: str | None, fail_job: bool = True) -> Manifest:
        """Send ``stage`` of run ``run_id`` and record it; a broker failure fails the job (retry re-sends) unless
        ``fail_job`` is False (a worker handing over to the next stage: it waits for Redis, then the watchdog)."""
        if stage is None:
            return self.store.read(job_id)
        assert self.dispatcher is not None
        try:
            self.dispatcher.send_stage(job_id, stage, run_id)
        except DispatchError as e:
            log.error("%s", e)
            if not fail_job:
                raise
            planned = None
            with self.coord.manifest_mutex(job_id):
                m = self.store.read(job_id)
                if m.run_id == run_id and m.state not in TERMINAL_STATES:
                    m.state = "failed"
                    m.error = JobError(stage=stage, code="broker_unavailable", message=str(e))
                    planned = plan_event(m)
                    self.store.write(m)
            self.announce(job_id, planned)  # most likely refused by the same broker: the delivery stays pending
            raise
        with self.coord.manifest_mutex(job_id):
            m = self.store.read(job_id)
            if m.run_id == run_id and stage not in m.dispatched:
                m.dispatched.append(stage)
                self.store.write(m)
        return m

    def announce(self, job_id: str, planned: WebhookDelivery | None) -> None:
        """Queue the delivery of a run's end event that ``plan_event`` recorded (None: nothing to send). A broker
        that refuses it leaves the delivery ``pending`` in the manifest, with the reason; the job is unaffected."""
        if planned is None or self.dispatcher is None:
            return
        try:
            self.dispatcher.send_webhook(job_id, planned.id)
        except DispatchError as e:
            log.error("%s", e)
            try:
                with self.coord.manifest_mutex(job_id):
                    m = self.store.read(job_id)
                    for d in m.webhooks:
                        if d.id == planned.id and d.status == "pending":
                            d.last_error = f"not queued: {e}"[:300]
                    self.store.write(m)
            except Exception as err:  # Redis is likely down too; the log has it
                log.warning("could not record the unqueued webhook %s: %s", planned.id, err)

    # ---- read
    def get(self, job_id: str, owner: str) -> Manifest:
        """The job if it exists and belongs to ``owner``; JobNotFound otherwise (others' jobs do not exist)."""
        m = self.store.read(job_id)
        if m.owner != owner:
            raise JobNotFound(job_id)
        return m

    def view(self, m: Manifest) -> StatusView:
        state, stage, progress, message = m.state, m.current_stage, m.progress, m.message
        try:
            live = self.coord.read_progress(m.id)
        except Exception as e:  # a status read must not fail because the cache is away
            log.warning("progress cache unavailable: %s", e)
            live = None
        if live is not None:
            progress = max(progress, live["progress"])  # never below what a poller may already have seen
            if m.state == "running" and live["run_id"] == m.run_id:
                stage, message = live["stage"] or stage, live["message"] or message
        if m.state == "done":
            progress = 100.0
        if m.state == "running" and m.cancel_requested:
            state = "cancelling"
        lost = self._worker_lost(m)
        if lost:
            message = self._lost_message(m, message)
        return StatusView(m, state, stage, round(progress, 2), message, lost)

    def _worker_lost(self, m: Manifest) -> bool:
        """A stage recorded as running whose runner is gone: the runner holds the lock from before it records
        ``running`` until after it records the end, and the lock names it; its worker's heartbeat (every 2 s)
        says whether it still lives (``Coordinator.holder_state``), so a dead one shows within seconds."""
        if m.state != "running" or m.current_stage is None or m.stage(m.current_stage).status != "running":
            return False
        try:
            return self.coord.holder_state(m.id)[0] in ("none", "dead")
        except Exception as e:  # the cache is away: say nothing rather than something wrong
            log.warning("cannot read the run lock: %s", e)
            return False

    def _lost_message(self, m: Manifest, last: str) -> str:
        stage = m.current_stage
        rec = m.stage(stage)
        ckpt = self.store.last_checkpoint_iteration(m.id) if stage == "train" else None
        resume = f"from checkpoint {ckpt}" if ckpt is not None else "from the start of the stage"
        was = f" at '{last}'" if last else ""
        return f"worker lost during {stage} (attempt {rec.attempts}){was}; resuming {resume}"

    # ---- cancel / retry / delete
    def cancel(self, job_id: str, owner: str) -> Manifest:
        with self.coord.manifest_mutex(job_id):
            m = self.get(job_id, owner)
            if m.state == "done":
                raise JobConflict("job_finished", "the job has already finished")
            if m.state in ("failed", "cancelled"):
                return m
            planned = None
            if not self.coord.run_lock_held(job_id):
                # no stage is running (queued, or between two stages): nothing to interrupt. A runner that
                # takes the lock right after this check reads the manifest under the mutex and drops the job.
                self._mark_cancelled(m, "cancelled" if m.state == "running" else "cancelled before it started")
                planned = plan_event(m)
            else:
                m.cancel_requested = True
                self.coord.request_cancel(job_id)
                m.message = "cancel requested"
            self.store.write(m)
        self.store.append_log(job_id, "INFO service: cancel requested")
        self.announce(job_id, planned)
        return m

    @staticmethod
    def _mark_cancelled(m: Manifest, message: str) -> None:
        m.state = "cancelled"
        m.cancel_requested = False
        m.message = message
        run = m.current_run
        if run is not None and run.outcome is None:
            run.outcome, run.finished_at = "cancelled", time.time()

    def retry(self, job_id: str, owner: str) -> Manifest:
        with self.coord.manifest_mutex(job_id):
            m = self.get(job_id, owner)
            if m.state not in ("failed", "cancelled"):
                raise JobConflict("not_retryable", f"only failed or cancelled jobs can be retried (job is {m.state})")
            if self.coord.run_lock_held(job_id):
                raise JobConflict("job_active", "the job's last runner has not stopped yet; retry in a moment")
            opts = JobOptions.from_json(m.options)
            start = first_unfinished(self.job_dir(job_id), opts)
            if start is None:
                raise JobConflict("nothing_to_retry", "every stage of this job is already complete")
            stages = pipeline_stages()
            for s in stages[stages.index(start):]:
                m.stages[s] = StageRecord()
            m.run_id = new_run_id()
            m.state, m.error, m.cancel_requested, m.dispatched = "queued", None, False, []
            m.current_stage, m.message = start, f"retry from {start}"
            m.runs.append(RunRecord(run_id=m.run_id, from_stage=start, queued_at=time.time()))
            self.coord.clear_cancel(job_id)
            self.store.write(m)
            run_id = m.run_id
        self.store.append_log(job_id, f"INFO service: retry from stage {start}")
        return self.dispatch(job_id, run_id, start)

    def delete(self, job_id: str, owner: str) -> None:
        with self.coord.manifest_mutex(job_id):
            m = self.get(job_id, owner)
            if m.state in ("queued", "running") or self.coord.run_lock_held(job_id):
                raise JobConflict("job_active", f"the job is {m.state}; cancel it first")
            self.store.remove(job_id)
        self.coord.forget_job(job_id)

    def list(self, owner: str, state: str | None = None, survey_id: str | None = None) -> list[Manifest]:
        return [m for m in self.store.list()
                if m.owner == owner and (state is None or m.state == state)
                and (survey_id is None or m.survey_id == survey_id)]

    def job_dir(self, job_id: str) -> Path:
        """The job's folder as the API reads it (with an object store: the mirror, brought up to date)."""
        return self.store.mirror(job_id)
