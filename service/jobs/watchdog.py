"""The watchdog: finds unfinished jobs nobody runs and re-queues their stage (issue 44).

A job can be left with no runner and no message: Redis restarted without persistence (its queues and
unacknowledged messages gone), a stage's task died on a Redis error before it recorded anything, the worker that
held the message was killed (its unacknowledged message waits for the visibility timeout, 15 minutes). Every
``watchdog_every_s`` the watchdog looks at each ``queued`` or ``running`` job and re-queues the stage the
manifest says comes next (the running one, or the first not done) when, for ``watchdog_grace_s`` in a row:

- no live runner holds the job (``Coordinator.holder_state``: no run lock, or one whose holder's worker heartbeat
  says it is dead), and Redis has been up long enough for a missing lock to mean something;
- no message for the job's run waits in a stage queue; an unacknowledged one counts only until the grace is over
  (a live worker takes a redelivered message over at once; one still unacknowledged after that belongs to a dead
  worker);
- the manifest was not written during the grace (a runner writes it every 2 s while a stage runs).

A duplicate message is harmless (the runner drops a stale, busy or finished one), so the grace only avoids
needless ones. It runs in the API process (a thread, ``start_watchdog``), one pass at a time across API processes
(a Redis lock), not in beat: beat's ticks go through a worker queue and wait behind a running stage, exactly when
workers are in trouble (docs/DECISIONS.md, "Watchdog in the API process").
"""

from __future__ import annotations

import logging
import threading
import time

import redis

from service.core.coord import Coordinator
from service.core.dispatch import DispatchError
from service.core.inflight import scan

from .manifest import TERMINAL_STATES
from .ops import JobOps, pipeline_stages
from .store import StoreUnavailable

log = logging.getLogger(__name__)

PASS_LOCK_TTL_S = 30.0


class Watchdog:
    def __init__(self, jobs: JobOps, coord: Coordinator, grace_s: float):
        self.jobs, self.coord, self.grace_s = jobs, coord, grace_s
        self._since: dict[str, float] = {}  # job id -> when it first looked abandoned (this process's passes)

    def run_pass(self) -> list[tuple[str, str]]:
        """One look at every unfinished job; returns the (job id, stage) pairs it re-queued."""
        with self.coord.watchdog_lock(PASS_LOCK_TTL_S) as got:
            if not got:
                return []
            return self._pass()

    def _pass(self) -> list[tuple[str, str]]:
        now = time.time()
        active = [m for m in self.jobs.store.list() if m.state not in TERMINAL_STATES]
        if not active:
            self._since.clear()
            return []
        inflight = scan(self.coord.redis, self.coord.prefix)
        requeued, seen = [], set()
        for m in active:
            state, _ = self.coord.holder_state(m.id)
            queued, unacked = inflight.holds(m.id, m.run_id)
            if state in ("alive", "unknown") or queued or now - m.updated_at < self.grace_s:
                continue
            seen.add(m.id)
            first = self._since.setdefault(m.id, now)
            if now - first < self.grace_s or (unacked and now - first < 2 * self.grace_s):
                continue
            stage = m.next_stage(pipeline_stages())
            if stage is None:
                continue
            if self._requeue(m.id, m.run_id, stage, state):
                requeued.append((m.id, stage))
                self._since.pop(m.id, None)
        for job_id in set(self._since) - seen:
            self._since.pop(job_id)
        return requeued

    def _requeue(self, job_id: str, run_id: str, stage: str, holder: str) -> bool:
        ckpt = self.jobs.store.last_checkpoint_iteration(job_id) if stage == "train" else None
        where = f"from checkpoint {ckpt}" if ckpt is not None else "from the start of the stage"
        why = "runner lost" if holder == "dead" else "no runner and no queued task"
        with self.coord.manifest_mutex(job_id):
            m = self.jobs.store.read(job_id)
            if m.run_id != run_id or m.state in TERMINAL_STATES:
                return False
            m.message = f"{why}; {stage} re-queued, resuming {where}"
            self.jobs.store.write(m)
        self.jobs.store.append_log(job_id, f"WARNING service: watchdog: {m.message}")
        log.warning("watchdog: job %s: %s", job_id, m.message)
        try:
            self.jobs.dispatch(job_id, run_id, stage, fail_job=False)
        except DispatchError as e:
            log.warning("watchdog: job %s: %s", job_id, e)
            return False
        return True


def start_watchdog(watchdog: Watchdog, every_s: float) -> threading.Event:
    """Run passes every ``every_s`` in a daemon thread until the returned event is set."""
    stop = threading.Event()

    def loop() -> None:
        while not stop.wait(every_s):
            try:
                watchdog.run_pass()
            except (redis.RedisError, TimeoutError, StoreUnavailable) as e:  # Redis or the store away: next pass
                log.debug("watchdog pass skipped: %s", e)
            except Exception:  # a bug here must not stop the watchdog for good
                log.exception("watchdog pass failed")

    threading.Thread(target=loop, name="job-watchdog", daemon=True).start()
    return stop
