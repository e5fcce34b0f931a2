"""The body of the stage task, kept out of Celery so it can be tested directly.

``execute_stage(rt, job_id, stage, run_id)`` runs one stage of one job run exactly when it should:

- a message for a deleted job, an older run (retried or cancelled since) or a finished job is dropped;
- the per-job run lock (Redis, renewed by a heartbeat) makes sure one runner at a time; a message that finds
  it held comes back later (``Outcome.retry_after``): if the holder dies, its lock expires and the comeback
  (or the broker's redelivery of the holder's own message) takes over;
- a stage already done in this run only makes sure the next one was sent (crash between the two);
- the stage itself is ``pipeline.job.runner.run_stage``: its completion marker makes a redelivered stage a no-op, and
  training resumes from its checkpoint;
- progress goes to the Redis cache (monotonic) and, every few seconds, to the manifest; cancel is a Redis flag
  checked by ``should_cancel``.
"""

from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TypeVar

from redis.exceptions import RedisError

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobCancelled, JobOptions, StageContext
from pipeline.job.runner import run_stage
from service.compose import Components
from service.core.coord import Coordinator, RunLock
from service.core.dispatch import DispatchError
from service.jobs.manifest import TERMINAL_STATES, AttemptRecord, JobError, Manifest, WebhookDelivery, overall_progress
from service.jobs.ops import pipeline_stages
from service.jobs.redact import redact_paths
from service.jobs.store import JobNotFound, JobStore, StoreUnavailable
from service.webhooks.events import plan_event

log = logging.getLogger(__name__)

MANIFEST_PROGRESS_EVERY_S = 2.0
LOG_PROGRESS_EVERY_S = 5.0
CACHE_PROGRESS_EVERY_S = 0.25
CANCEL_CHECK_EVERY_S = 0.5
STORE_RETRY_EVERY_S = 10.0  # a progress write that found the object store away: the next try (each try may block
# for boto's retries, seconds with the training waiting)
OUTAGE_BACKOFF_MAX_S = 5.0
UNREACHABLE_MESSAGE = "the coordinator (Redis) is unreachable"

T = TypeVar("T")


@dataclass
class Outcome:
    status: str  # ran | stale | busy | already_done | cancelled | failed | lost
    retry_after: float | None = None
    detail: str = ""
    next_stage: str | None = None  # the stage to queue after a stage that ran


def error_code(exc: BaseException) -> str:
    """A stable code for a stage failure: the exception's own ``code``, else its class name for the pipeline's
    typed errors (``TooFewRegisteredError`` -> ``too_few_registered``), else ``stage_failed``."""
    code = getattr(exc, "code", None)
    if isinstance(code, str) and code:
        return code
    if type(exc).__module__.startswith("pipeline."):
        name = re.sub(r"Error$", "", type(exc).__name__)
        return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower() or "stage_failed"
    return "stage_failed"


def execute_stage(rt: Components, job_id: str, stage: str, run_id: str, hostname: str = "") -> Outcome:
    """``hostname``: the Celery worker's (the run lock names it, with this pid, as its holder)."""
    try:
        m = rt.store.read(job_id)
    except JobNotFound:
        return Outcome("stale", detail="job deleted")
    if m.run_id != run_id or m.state in TERMINAL_STATES:
        return Outcome("stale", detail=f"run {run_id} is not the job's live run")
    lock = rt.coord.try_run_lock(job_id, rt.settings.lock_ttl_s, hostname)
    if lock is None:
        state, value = rt.coord.holder_state(job_id)
        if state == "dead":  # its worker's heartbeat says the holder is gone: take over now, not at lock expiry
            lock = rt.coord.try_run_lock(job_id, rt.settings.lock_ttl_s, hostname, steal_from=value)
            if lock is not None:
                log.warning("job %s: took the run lock over from dead runner %s", job_id, value)
    if lock is None:
        return Outcome("busy", retry_after=rt.settings.lock_retry_s, detail="another runner holds the job")
    try:
        rt.store.pull(job_id, stage)  # another host may have run the stages before this one (service.storage)
        with job_log(rt.store, job_id, rt.settings.data_dir):
            return _execute_locked(rt, job_id, stage, run_id, lock)
    finally:
        lock.release()


def _execute_locked(rt: Components, job_id: str, stage: str, run_id: str, lock: RunLock) -> Outcome:
    stages = pipeline_stages()
    if stage not in stages:
        return Outcome("stale", detail=f"unknown stage {stage!r}")

    ended: Outcome | None = None  # the job ended before the stage started (cancelled, or its worker died too often)
    planned: WebhookDelivery | None = None
    with rt.coord.manifest_mutex(job_id):
        try:
            m = rt.store.read(job_id)
        except JobNotFound:
            return Outcome("stale", detail="job deleted")
        if m.run_id != run_id or m.state in TERMINAL_STATES:
            return Outcome("stale", detail="run superseded or finished")
        rec = m.stage(stage)
        if rec.status == "done":
            nxt = m.next_stage(stages)
            pending_next = nxt is not None and nxt not in m.dispatched
        else:
            if m.cancel_requested or rt.coord.cancel_requested(job_id):
                planned = _finish(m, "cancelled", None, "cancelled before " + stage)
                ended = Outcome("cancelled")
            elif rec.status == "running":  # the previous attempt's worker died: keep that attempt in the record
                last = _last_words(rt, m, stage)
                rec.history.append(AttemptRecord(attempt=rec.attempts, started_at=rec.started_at,
                                                 ended_at=m.updated_at, outcome="worker_lost", last=last))
                log.warning("job %s: the worker running %s died (attempt %d, last: %s)", job_id, stage,
                            rec.attempts, last or "-")
            if ended is None and rec.status == "running" and rec.attempts >= rt.settings.max_stage_attempts:
                msg = f"the worker died {rec.attempts} times while running {stage}"
                planned = _finish(m, "failed", JobError(stage=stage, code="worker_lost", message=msg), msg)
                rec.status, rec.finished_at = "failed", time.time()
                ended = Outcome("failed", detail=msg)
            if ended is None:
                rec.status, rec.started_at, rec.finished_at, rec.seconds = "running", time.time(), None, None
                rec.attempts += 1
                m.state, m.current_stage, m.message = "running", stage, f"{stage} started"
            rt.store.write(m)
            attempt = rec.attempts
    if ended is not None:
        rt.jobs.announce(job_id, planned)  # outside the mutex: announce takes it when the broker refuses
        return ended
    if rec.status == "done":
        if pending_next:
            dispatch_next(rt, job_id, run_id, nxt)
        return Outcome("already_done")

    log.info("job %s: stage %s started (attempt %d, run %s)", job_id, stage, attempt, run_id)
    reporter = ProgressReporter(rt, job_id, run_id, stages, {s for s in stages if m.stage(s).status == "done"},
                                floor=m.progress)
    canceller = CancelCheck(rt.coord, job_id, lock)
    ctx = StageContext(on_progress=reporter, should_cancel=canceller, device=rt.settings.device)
    t0 = time.time()
    try:
        _, skipped = run_stage(rt.store.job_dir(job_id), stage, JobOptions.from_json(m.options), ctx)
    except JobCancelled as e:
        if lock.lost.is_set():
            return Outcome("lost", detail="job lock lost; another runner owns the job")
        log.info("job %s: %s", job_id, e)
        seconds, why = time.time() - t0, str(e)
        return when_redis_answers(rt, f"record the cancel of job {job_id}", lambda: _record_end(
            rt, job_id, run_id, stage, "cancelled", None, why, seconds))
    except Exception as e:  # the stage failed: record why; the task itself succeeds (no broker retry)
        if lock.lost.is_set():
            return Outcome("lost", detail="job lock lost; another runner owns the job")
        log.exception("job %s: stage %s failed", job_id, stage)
        err = JobError(stage=stage, code=error_code(e), message=redact_paths(f"{e}" or type(e).__name__,
                                                                             rt.store.job_dir(job_id),
                                                                             rt.settings.data_dir))
        seconds = time.time() - t0
        return when_redis_answers(rt, f"record the failure of {stage} of job {job_id}", lambda: _record_end(
            rt, job_id, run_id, stage, "failed", err, err.message, seconds))
    log.info("job %s: stage %s %s in %.1f s", job_id, stage, "skipped (marker matches)" if skipped else "done",
             time.time() - t0)
    seconds = time.time() - t0
    out = when_redis_answers(rt, f"record the end of {stage} of job {job_id}", lambda: _record_end(
        rt, job_id, run_id, stage, "done", None, "", seconds, skipped=skipped, progress=reporter.value))
    if out.status == "ran" and out.next_stage is not None:
        dispatch_next(rt, job_id, run_id, out.next_stage)
    return out


# what a runner waits out instead of failing: Redis (the mutex, the cache, the broker) or the object store away
OUTAGES = (RedisError, DispatchError, TimeoutError, StoreUnavailable)


def when_redis_answers(rt: Components, what: str, fn: Callable[[], T]) -> T:
    """``fn()``, tried again with backoff while Redis (the mutex, the cache, the broker) or the object store, if
    any, does not answer, up to ``redis_outage_wait_s``; after that the error propagates and the watchdog
    (service.jobs.watchdog) finds the job nobody runs once they are back. ``fn`` must be safe to repeat when it
    failed before writing anything (a manifest write pushes the folder first, and a push repeats cheaply)."""
    deadline = time.monotonic() + rt.settings.redis_outage_wait_s
    delay = 0.5
    while True:
        try:
            return fn()
        except OUTAGES as e:
            if time.monotonic() + delay > deadline:
                log.error("gave up trying to %s: %s", what, e)
                raise
            log.warning("cannot %s yet (%s); trying again in %.1f s", what, e, delay)
            time.sleep(delay)
            delay = min(2 * delay, OUTAGE_BACKOFF_MAX_S)


def dispatch_next(rt: Components, job_id: str, run_id: str, stage: str) -> None:
    """Queue the next stage, waiting out a Redis outage; a broker still away after that leaves the job to the
    watchdog (the manifest says the stage before is done and this one not dispatched), never failing it."""
    try:
        when_redis_answers(rt, f"queue {stage} of job {job_id}",
                           lambda: rt.jobs.dispatch(job_id, run_id, stage, fail_job=False))
    except OUTAGES as e:
        log.error("job %s: %s not queued (%s); the watchdog re-queues it once Redis is back", job_id, stage, e)


def _finish(m: Manifest, state: str, error: JobError | None, message: str) -> WebhookDelivery | None:
    """End the job's run in ``m`` (written by the caller); returns the webhook delivery it planned, which the
    caller queues with ``rt.jobs.announce`` once ``m`` is written."""
    m.state, m.error, m.message, m.cancel_requested = state, error, message, False
    run = m.current_run
    if run is not None and run.outcome is None:
        run.outcome, run.finished_at = state, time.time()
    return plan_event(m)


def _record_end(rt: Components, job_id: str, run_id: str, stage: str, status: str, error: JobError | None,
                message: str, seconds: float, skipped: bool = False, progress: float = 0.0) -> Outcome:
    """Write the stage's end into the manifest; for ``done`` also the job's end or hand-over to the next stage."""
    stages = pipeline_stages()
    next_up: str | None = None
    planned: WebhookDelivery | None = None
    with rt.coord.manifest_mutex(job_id):
        try:
            m = rt.store.read(job_id)
        except JobNotFound:
            return Outcome("stale", detail="job deleted while running")
        if m.run_id != run_id:
            return Outcome("stale", detail="run superseded while running")
        rec = m.stage(stage)
        rec.status, rec.finished_at, rec.seconds, rec.skipped = status, time.time(), round(seconds, 3), skipped
        rec.history.append(AttemptRecord(attempt=rec.attempts, started_at=rec.started_at, ended_at=rec.finished_at,
                                         outcome=status, last=message or m.message))
        if stage == "ingest" and status == "done" and m.ingest is None:
            m.ingest = _read_ingest(rt.store.job_dir(job_id))  # survey jobs: the worker ran ingest, not the API
        done = {s for s in stages if m.stage(s).status == "done"}
        m.progress = max(m.progress, progress, overall_progress(stages, done, None, 0.0))
        if status == "cancelled":
            planned = _finish(m, "cancelled", None, f"cancelled during {stage}")
        elif status == "failed":
            planned = _finish(m, "failed", error, message)
        elif (nxt := m.next_stage(stages)) is None:
            if m.state != "done":
                m.completed_runs += 1
            m.progress, m.current_stage = 100.0, None
            planned = _finish(m, "done", None, "finished")
        elif m.cancel_requested or rt.coord.cancel_requested(job_id):
            planned = _finish(m, "cancelled", None, f"cancelled after {stage}")
            status = "cancelled"
        else:
            m.message = f"{stage} done"
            next_up = nxt
        rt.store.write(m)
        final_progress = m.progress
    rt.jobs.announce(job_id, planned)
    try:
        rt.coord.push_progress(job_id, run_id, stage, final_progress, m.message)
    except Exception as e:  # the cache is only a cache
        log.warning("progress cache unavailable: %s", e)
    return Outcome({"done": "ran"}.get(status, status), detail=message, next_stage=next_up)


def _read_ingest(job_dir) -> dict | None:
    """The ingest stage's result (``ingest.json``) for the job's status: images, skipped, ignored."""
    try:
        data = json.loads(JobLayout(job_dir).ingest.read_text())
    except (OSError, ValueError) as e:
        log.warning("cannot read %s: %s", JobLayout(job_dir).ingest, e)
        return None
    return data if isinstance(data, dict) else None


class ProgressReporter:
    """``StageContext.on_progress``: overall 0-100 from stage weights, never decreasing; cache often, manifest
    and job log now and then."""

    def __init__(self, rt: Components, job_id: str, run_id: str, stages: tuple[str, ...], done: set[str],
                 floor: float):
        self.rt, self.job_id, self.run_id, self.stages, self.done = rt, job_id, run_id, stages, done
        self.value = floor
        self.unreachable = False
        self.store_away = False
        self._cache_at = self._manifest_at = self._log_at = 0.0

    def __call__(self, stage: str, fraction: float, message: str) -> None:
        now = time.time()
        self.value = max(self.value, overall_progress(self.stages, self.done, stage, fraction))
        edge = fraction <= 0.0 or fraction >= 1.0
        if edge or now - self._cache_at >= CACHE_PROGRESS_EVERY_S:
            self._cache_at = now
            try:
                self.value = max(self.value, self.rt.coord.push_progress(self.job_id, self.run_id, stage,
                                                                         self.value, message))
            except Exception as e:
                if not self.unreachable:
                    log.warning("progress cache unavailable: %s", e)
        if now - self._log_at >= LOG_PROGRESS_EVERY_S:
            self._log_at = now
            log.info("job %s: %s %.1f%% %s", self.job_id, stage, self.value, message)
        if now - self._manifest_at >= (STORE_RETRY_EVERY_S if self.store_away else MANIFEST_PROGRESS_EVERY_S):
            self._manifest_at = now
            try:
                with self.rt.coord.manifest_mutex(self.job_id):
                    self._write(stage, message)
            except TimeoutError as e:  # Redis answers but someone holds the mutex: skip this write
                log.warning("job %s: progress not written: %s", self.job_id, e)
                return
            except StoreUnavailable as e:  # the manifest lives in the object store: nothing to write it to; the
                # stage goes on, the next write (and the checkpoints' push) catches up, its end waits for the store
                if not self.store_away:
                    log.warning("job %s: progress not written, %s; %s goes on", self.job_id, e, stage)
                self.store_away = True
                return
            except RedisError as e:
                # Redis away: nobody can take the mutex (the API's writes need it too), so this runner writes its
                # progress without it and says why; the stage goes on and its end waits for Redis
                if not self.unreachable:
                    log.warning("job %s: the coordinator (Redis) is unreachable (%s); %s goes on", self.job_id,
                                e, stage)
                self.unreachable = True
                self._write(stage, f"{UNREACHABLE_MESSAGE}; {stage} goes on ({message})")
                return
            if self.unreachable or self.store_away:
                log.info("job %s: the coordinator and the store answer again", self.job_id)
            self.unreachable = self.store_away = False

    def _write(self, stage: str, message: str) -> None:
        m = self.rt.store.read(self.job_id)
        if m.run_id == self.run_id and m.state == "running":
            m.progress, m.message, m.current_stage = max(m.progress, self.value), message, stage
            self.rt.store.write(m)


def _last_words(rt, m, stage: str) -> str:
    """What a dead worker last said about ``stage``: the progress cache's message (pushed every
    CACHE_PROGRESS_EVERY_S) when it is this run's and this stage's, else the manifest's (written every
    MANIFEST_PROGRESS_EVERY_S, so it can be a step behind: a worker killed 1 s after the probe ended left 'probe:
    chose dualphys' there while it was already training)."""
    try:
        live = rt.coord.read_progress(m.id)
    except Exception as e:  # the cache is a nicety here; the manifest's message will do
        log.warning("progress cache unavailable: %s", e)
        live = None
    if live and live["run_id"] == m.run_id and live["stage"] == stage and live["message"]:
        return live["message"]
    return m.message


class CancelCheck:
    """``StageContext.should_cancel``: the job's Redis cancel flag (polled at most every 0.5 s) or a lost lock."""

    def __init__(self, coord: Coordinator, job_id: str, lock: RunLock):
        self.coord, self.job_id, self.lock = coord, job_id, lock
        self._checked_at = 0.0
        self._cancelled = False

    def __call__(self) -> bool:
        if self.lock.lost.is_set():
            return True
        now = time.monotonic()
        if not self._cancelled and now - self._checked_at >= CANCEL_CHECK_EVERY_S:
            self._checked_at = now
            try:
                self._cancelled = self.coord.cancel_requested(self.job_id)
            except Exception as e:
                if not self.lock.unreachable.is_set():
                    log.warning("cannot read the cancel flag: %s", e)
        return self._cancelled


class JobLogFormatter(logging.Formatter):
    """The job log is the client's: server paths are taken out of every line, and a traceback (file names of
    the installed code) is cut to its last line; the worker's own log keeps the whole record."""

    def __init__(self, job_dir, data_dir):
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s", "%Y-%m-%dT%H:%M:%SZ")
        self.converter = time.gmtime
        self.job_dir, self.data_dir = job_dir, data_dir

    def formatException(self, ei) -> str:
        exc = ei[1]
        return f"{type(exc).__name__}: {exc}" if exc is not None else ""

    def formatStack(self, stack_info: str) -> str:
        return ""

    def format(self, record: logging.LogRecord) -> str:
        cached, record.exc_text = record.exc_text, None  # other handlers may have cached the full traceback
        try:
            return redact_paths(super().format(record), self.job_dir, self.data_dir)
        finally:
            record.exc_text = cached


@contextmanager
def job_log(store: JobStore, job_id: str, data_dir=None) -> Iterator[None]:
    """Copy log records (ours and the pipeline's, INFO and up) into the job's log.txt while a stage runs."""
    handler = logging.FileHandler(store.layout(job_id).log, encoding="utf-8", delay=True)
    handler.setLevel(logging.INFO)
    handler.setFormatter(JobLogFormatter(store.job_dir(job_id), data_dir))
    root = logging.getLogger()
    loggers = [logging.getLogger(n) for n in ("pipeline", "worker", "service")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        if lg.getEffectiveLevel() > logging.INFO:
            lg.setLevel(logging.INFO)
    root.addHandler(handler)
    try:
        yield
    finally:
        root.removeHandler(handler)
        handler.close()
        for lg, lvl in zip(loggers, levels):
            lg.setLevel(lvl)
