"""Redis as the coordinator: per-job run lock (with a heartbeat), manifest mutex, cancel flags, progress cache,
idempotency keys and survey scan locks. Nothing here is the truth about a job (the manifest on disk is);
losing Redis loses queued messages and the cache, never a finished stage.

Keys (all under ``<prefix>:``): ``job:<id>:run`` (runner lock), ``job:<id>:manifest`` (short mutex around a
manifest read-modify-write), ``job:<id>:cancel``, ``job:<id>:progress`` (hash), ``idem:<owner>:<sha256>``,
``survey:<id>:scan``, ``hook:<delivery id>`` (one webhook attempt at a time).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import redis
from redis.exceptions import LockError

log = logging.getLogger(__name__)

PROGRESS_TTL_S = 7 * 24 * 3600
WORKER_BEAT_EVERY_S = 2.0  # worker.heartbeat's period: a dead pool child is known within this
WORKER_TTL_S = 3 * WORKER_BEAT_EVERY_S  # a dead worker's heartbeat is gone within this
IDEMPOTENCY_TTL_S = 24 * 3600

# Progress never goes down: keep the larger of the stored and the new value (a resumed stage restarts its
# fraction from the checkpoint, which may be below what a poller already saw).
_PROGRESS_MAX = """
local old = tonumber(redis.call('HGET', KEYS[1], 'progress') or '-1')
local new = tonumber(ARGV[2])
if old > new then new = old end
redis.call('HSET', KEYS[1], 'run_id', ARGV[1], 'progress', tostring(new), 'stage', ARGV[3],
           'message', ARGV[4], 'updated_at', ARGV[5])
redis.call('EXPIRE', KEYS[1], tonumber(ARGV[6]))
return tostring(new)
"""

_DELETE_IF_EQUAL = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""


_SWAP_IF_EQUAL = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  redis.call('SET', KEYS[1], ARGV[2], 'PX', tonumber(ARGV[3]))
  return 1
end
return 0
"""

UNREACHABLE_RETRY_S = 1.0  # a lock renewal that found Redis away tries again this often (a re-take soon after)
LOCK_SEP = "|"
ANONYMOUS = "?"  # the holder name of a lock taken outside a Celery worker


def lock_token(hostname: str, pid: int) -> str:
    """A run lock's value names its holder: ``<worker hostname>|<pid>|<taken at>|<random>`` (worker.heartbeat
    lists each worker's live pids, so an observer can tell a dead holder from a live one)."""
    return LOCK_SEP.join((hostname.replace(LOCK_SEP, "_"), str(pid), f"{time.time():.3f}", uuid.uuid4().hex[:12]))


def parse_token(token: str) -> tuple[str, int, float] | None:
    """(hostname, pid, taken_at) of a lock value :func:`lock_token` wrote; None for any other value."""
    parts = token.split(LOCK_SEP)
    try:
        return (parts[0], int(parts[1]), float(parts[2])) if len(parts) == 4 else None
    except ValueError:
        return None


class RunLock:
    """The one-runner-per-job lock, renewed by a daemon thread every ttl/3 while held.

    ``lost`` is set when a renewal finds the lock taken by someone else (it expired and another runner owns the
    job): the stage must then stop without recording anything. A lock that vanished with the Redis that held it
    (a restart without persistence, or expired during an outage longer than the TTL) is re-taken when nobody
    else holds it. ``unreachable`` is set while renewals cannot reach Redis. ``worst_gap_s`` is the longest a
    renewal came late (the thread waited for the GIL; numba kernels and pycolmap hold it), logged at release.
    """

    def __init__(self, lock: redis.lock.Lock, ttl_s: float, token: str):
        self._lock = lock
        self._ttl_s = ttl_s
        self.token = token
        self.lost = threading.Event()
        self.unreachable = threading.Event()
        self.retaken = 0
        self.renewals = 0
        self.worst_gap_s = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start_heartbeat(self) -> None:
        self._thread = threading.Thread(target=self._beat, name="job-lock-heartbeat", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        every = self._ttl_s / 3
        wait = every
        while True:
            t0 = time.monotonic()
            if self._stop.wait(wait):
                return
            self.worst_gap_s = max(self.worst_gap_s, time.monotonic() - t0 - wait)
            try:
                self._renew()
            except LockError:
                log.error("job lock %s is held by another runner; stopping this one", self._lock.name)
                self.lost.set()
                return
            except redis.RedisError as e:  # Redis away: keep trying; the stage goes on (its end waits for Redis)
                if not self.unreachable.is_set():
                    log.warning("could not renew job lock %s: %s", self._lock.name, e)
                self.unreachable.set()
                wait = min(every, UNREACHABLE_RETRY_S)
                continue
            self.unreachable.clear()
            self.renewals += 1
            wait = every

    def _renew(self) -> None:
        try:
            self._lock.reacquire()
        except LockError:
            if not self._lock.do_acquire(self.token):  # SET NX: only if nobody holds it
                raise
            self.retaken += 1
            log.warning("job lock %s had vanished (Redis lost it); re-taken", self._lock.name)

    def release(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        log.log(logging.INFO if self.renewals or self.retaken else logging.DEBUG,
                "job lock %s: %d renewals every %.1f s, worst delay %.2f s, re-taken %d times",
                self._lock.name, self.renewals, self._ttl_s / 3, self.worst_gap_s, self.retaken)
        try:
            self._lock.release()
        except LockError:
            pass
        except redis.RedisError as e:
            log.warning("could not release job lock %s (it expires by itself): %s", self._lock.name, e)


class Coordinator:
    def __init__(self, client: redis.Redis, prefix: str):
        self.redis = client
        self.prefix = prefix
        self._progress = client.register_script(_PROGRESS_MAX)
        self._delete_if_equal = client.register_script(_DELETE_IF_EQUAL)
        self._swap_if_equal = client.register_script(_SWAP_IF_EQUAL)

    @classmethod
    def from_url(cls, url: str, prefix: str) -> Coordinator:
        client = redis.Redis.from_url(url, decode_responses=True, socket_timeout=10, socket_connect_timeout=5,
                                      health_check_interval=30)
        return cls(client, prefix)

    def key(self, *parts: str) -> str:
        return ":".join((self.prefix, *parts))

    def ping(self) -> bool:
        try:
            return bool(self.redis.ping())
        except redis.RedisError:
            return False

    def close(self) -> None:
        self.redis.close()

    # ---- locks
    @contextmanager
    def manifest_mutex(self, job_id: str, timeout_s: float = 30.0) -> Iterator[None]:
        """Serialise read-modify-write of one manifest between the API and the workers."""
        lock = self.redis.lock(self.key("job", job_id, "manifest"), timeout=timeout_s, blocking_timeout=timeout_s)
        if not lock.acquire():
            raise TimeoutError(f"manifest of job {job_id} stayed locked for {timeout_s} s")
        try:
            yield
        finally:
            try:
                lock.release()
            except LockError:
                log.warning("manifest mutex of %s expired while held", job_id)
            except redis.RedisError as e:  # the write is done; the mutex expires by itself
                log.warning("could not release the manifest mutex of %s: %s", job_id, e)

    def try_run_lock(self, job_id: str, ttl_s: float, holder: str = "", steal_from: str | None = None
                     ) -> RunLock | None:
        """The job's run lock for ``holder`` (a worker hostname), or None when someone holds it. ``steal_from``:
        take it over from that value (a holder :meth:`holder_state` found dead) if it still holds it."""
        token = lock_token(holder or ANONYMOUS, os.getpid())
        lock = self.redis.lock(self.key("job", job_id, "run"), timeout=ttl_s, blocking=False, thread_local=False)
        if steal_from is not None:
            if not self._swap_if_equal(keys=[lock.name], args=[steal_from, token, int(ttl_s * 1000)]):
                return None
            lock.local.token = self.redis.get_encoder().encode(token)
        elif not lock.acquire(blocking=False, token=token):
            return None
        held = RunLock(lock, ttl_s, token)
        held.start_heartbeat()
        return held

    def run_lock_held(self, job_id: str) -> bool:
        return bool(self.redis.exists(self.key("job", job_id, "run")))

    def run_lock_value(self, job_id: str) -> str | None:
        return self.redis.get(self.key("job", job_id, "run"))

    def holder_state(self, job_id: str) -> tuple[str, str | None]:
        """(state, lock value): ``none`` (no lock), ``alive``, ``dead`` (its worker's heartbeat, written after the
        lock was taken, no longer lists the holder's pid, or the worker's heartbeat expired), ``unknown`` (a
        value without a holder, or Redis restarted too recently for a missing heartbeat to mean anything)."""
        value = self.run_lock_value(job_id)
        if value is None:  # right after a Redis restart the runner may not have re-taken its lock yet
            return ("unknown" if self.uptime_s() < WORKER_TTL_S + 1 else "none"), None
        holder = parse_token(value)
        if holder is None or holder[0] == ANONYMOUS:
            return "unknown", value  # a holder that names no worker (not a Celery task): only its TTL tells
        hostname, pid, taken_at = holder
        beat = self.worker_beat(hostname)
        if beat is None:
            fresh = self.uptime_s() < WORKER_TTL_S + 1
            return ("unknown" if fresh else "dead"), value
        if pid in beat.get("pids", [pid]) or float(beat.get("at", 0)) <= taken_at:
            return "alive", value  # listed, or the beat predates the lock (a child that just started)
        return "dead", value

    def uptime_s(self) -> float:
        return float(self.redis.info("server").get("uptime_in_seconds", 0))

    @contextmanager
    def _try_lock(self, name: str, ttl_s: float) -> Iterator[bool]:
        """Yields whether this caller got the Redis lock ``name`` (never waits); releases it after, if held."""
        lock = self.redis.lock(name, timeout=ttl_s, blocking=False)
        got = lock.acquire(blocking=False)
        try:
            yield got
        finally:
            if got:
                try:
                    lock.release()
                except LockError:
                    pass

    def watchdog_lock(self, ttl_s: float):
        """Yields False while another API process runs a watchdog pass (service.jobs.watchdog)."""
        return self._try_lock(self.key("watchdog"), ttl_s)

    def scan_lock(self, survey_id: str, ttl_s: float = 600.0):
        """Yields False when another scanner holds this survey's lock (the caller skips the scan)."""
        return self._try_lock(self.key("survey", survey_id, "scan"), ttl_s)

    def webhook_claim(self, delivery_id: str, ttl_s: float):
        """Yields False when another task is sending this webhook delivery right now (a duplicated message):
        one attempt at a time per delivery. The TTL outlives the HTTP timeout, so a crashed sender frees it."""
        return self._try_lock(self.key("hook", delivery_id), ttl_s)

    # ---- cancel
    def request_cancel(self, job_id: str) -> None:
        self.redis.set(self.key("job", job_id, "cancel"), "1", ex=PROGRESS_TTL_S)

    def clear_cancel(self, job_id: str) -> None:
        self.redis.delete(self.key("job", job_id, "cancel"))

    def cancel_requested(self, job_id: str) -> bool:
        return bool(self.redis.exists(self.key("job", job_id, "cancel")))

    # ---- progress cache
    def push_progress(self, job_id: str, run_id: str, stage: str, progress: float, message: str) -> float:
        """Store progress (kept monotonic in Redis); returns the stored value."""
        out = self._progress(keys=[self.key("job", job_id, "progress")],
                             args=[run_id, f"{progress:.3f}", stage, message[:500], f"{time.time():.3f}",
                                   PROGRESS_TTL_S])
        return float(out)

    def read_progress(self, job_id: str) -> dict | None:
        d = self.redis.hgetall(self.key("job", job_id, "progress"))
        if not d:
            return None
        return {"run_id": d.get("run_id", ""), "progress": float(d.get("progress", 0)), "stage": d.get("stage", ""),
                "message": d.get("message", ""), "updated_at": float(d.get("updated_at", 0))}

    def forget_job(self, job_id: str) -> None:
        self.redis.delete(self.key("job", job_id, "progress"), self.key("job", job_id, "cancel"))

    # ---- idempotency keys
    def _idem_key(self, owner: str, key: str) -> str:
        return self.key("idem", owner, hashlib.sha256(key.encode()).hexdigest())

    def claim_idempotency(self, owner: str, key: str, job_id: str) -> str | None:
        """Claim ``key`` for a new job. Returns None when claimed, else what it holds: a job id, or
        ``pending:<job id>`` while another request with the same key is still uploading."""
        k = self._idem_key(owner, key)
        if self.redis.set(k, f"pending:{job_id}", nx=True, ex=IDEMPOTENCY_TTL_S):
            return None
        return self.redis.get(k) or f"pending:{job_id}"

    def confirm_idempotency(self, owner: str, key: str, job_id: str) -> None:
        self.redis.set(self._idem_key(owner, key), job_id, ex=IDEMPOTENCY_TTL_S)

    def release_idempotency(self, owner: str, key: str, job_id: str) -> None:
        self._delete_if_equal(keys=[self._idem_key(owner, key)], args=[f"pending:{job_id}"])

    # ---- workers (worker.heartbeat)
    def announce_worker(self, hostname: str, queues: list[str], pid: int, ttl_s: float,
                        pids: list[int] | None = None) -> None:
        """``pids``: the processes that may run stages (the main process and its pool children)."""
        self.redis.set(self.key("worker", hostname),
                       json.dumps({"queues": queues, "pid": pid, "pids": pids or [pid], "at": time.time()}),
                       ex=max(1, int(ttl_s)))

    def worker_beat(self, hostname: str) -> dict | None:
        raw = self.redis.get(self.key("worker", hostname))
        try:
            return json.loads(raw) if raw else None
        except ValueError:
            return None

    def forget_worker(self, hostname: str) -> None:
        self.redis.delete(self.key("worker", hostname))

    def workers(self) -> dict[str, list[str]]:
        """Live workers (hostname -> queues they consume), from their heartbeats."""
        out: dict[str, list[str]] = {}
        for k in self.redis.scan_iter(match=self.key("worker", "*"), count=100):
            raw = self.redis.get(k)
            if raw:
                try:
                    out[k[len(self.key("worker", "")):]] = list(json.loads(raw)["queues"])
                except (ValueError, KeyError, TypeError):
                    continue
        return out

    # ---- housekeeping (tests)
    def delete_all_keys(self) -> int:
        """Delete every key under this prefix (the broker's too). Only tests and tear-downs call this."""
        n = 0
        for k in self.redis.scan_iter(match=f"{self.prefix}:*", count=500):
            n += self.redis.delete(k)
        return n
