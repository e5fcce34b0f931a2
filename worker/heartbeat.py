"""Workers announce themselves in Redis, so ``/ready`` can tell whether anyone consumes the queues.

The worker's main process (not a pool child) starts a daemon thread when Celery reports the worker ready; it
writes ``<prefix>:worker:<hostname>`` = ``{"queues": [...], "pid", "pids", "at"}`` every ``EVERY_S`` seconds with a
TTL of ``3 * EVERY_S`` and deletes it on a clean shutdown. A worker killed with SIGKILL disappears from the list when
its key expires.

``pids`` are the live processes that may run a stage (the main process and its pool children). A job's run lock
names its holder's hostname and pid (``service.core.coord.lock_token``), so a pool child killed mid-stage is known
dead at the next beat (``Coordinator.holder_state``). The main process runs no numba or pycolmap, so its beats
come on time; the pool child's own lock renewals may wait seconds for the GIL, which is why liveness is not
judged from them.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

from service.core.coord import WORKER_BEAT_EVERY_S, WORKER_TTL_S, Coordinator
from service.core.settings import load_settings

log = logging.getLogger(__name__)

EVERY_S = WORKER_BEAT_EVERY_S


def _running(pid: int) -> bool:
    """The process exists and is not a zombie (a killed pool child stays one until billiard reaps it)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    except OSError:  # no /proc: the signal test (a zombie passes it)
        try:
            os.kill(pid, 0)
        except OSError:
            return False
        return True
    return stat[stat.rindex(")") + 2] != "Z"


class Heartbeat:
    def __init__(self, coord, hostname: str, queues: list[str], pool=None):
        self.coord, self.hostname, self.queues, self.pool = coord, hostname, queues, pool
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="worker-heartbeat", daemon=True)

    def start(self) -> None:
        self._beat()
        self._thread.start()

    def _beat(self) -> None:
        try:
            self.coord.announce_worker(self.hostname, self.queues, os.getpid(), ttl_s=WORKER_TTL_S,
                                       pids=self.pids())
        except Exception as e:  # Redis away: /ready says so itself
            log.warning("worker heartbeat failed: %s", e)

    def pids(self) -> list[int]:
        """This process and the pool's live children (prefork: billiard's process list)."""
        try:
            children = [p.pid for p in self.pool._pool._pool]
        except AttributeError:  # solo or threads pool: stages run in this process
            children = []
        return [os.getpid(), *(pid for pid in children if pid and _running(pid))]

    def _run(self) -> None:
        while not self._stop.wait(EVERY_S):
            self._beat()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=EVERY_S)
        try:
            self.coord.forget_worker(self.hostname)
        except Exception as e:
            log.warning("could not remove the worker's heartbeat: %s", e)
        self.coord.close()


_current: Heartbeat | None = None


def on_worker_ready(sender=None, **_) -> None:
    """Celery ``worker_ready`` (sender: the worker's consumer)."""
    global _current
    settings = load_settings()
    try:
        queues = sorted(q.name for q in sender.task_consumer.queues)
    except AttributeError:
        queues = sorted(sender.app.amqp.queues.consume_from)
    _current = Heartbeat(Coordinator.from_url(settings.redis_url, settings.redis_prefix), sender.hostname, queues,
                         getattr(sender, "pool", None))
    _current.start()
    log.info("worker %s consumes %s", sender.hostname, ", ".join(queues))


def on_worker_shutdown(**_) -> None:
    global _current
    if _current is not None:
        _current.stop()
        _current = None
