"""Workers announce themselves in Redis, so ``/ready`` can tell whether anyone consumes the queues.

The worker's main process (not a pool child) starts a daemon thread when Celery reports the worker ready; it
writes ``<prefix>:worker:<hostname>`` = ``{"queues": [...], "pid", "at"}`` every ``EVERY_S`` seconds with a TTL of
``3 * EVERY_S`` and deletes it on a clean shutdown. A worker killed with SIGKILL disappears from the list when
its key expires.
"""

from __future__ import annotations

import logging
import os
import threading

from service.core.coord import Coordinator
from service.core.settings import load_settings

log = logging.getLogger(__name__)

EVERY_S = 5.0


class Heartbeat:
    def __init__(self, coord, hostname: str, queues: list[str]):
        self.coord, self.hostname, self.queues = coord, hostname, queues
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="worker-heartbeat", daemon=True)

    def start(self) -> None:
        self._beat()
        self._thread.start()

    def _beat(self) -> None:
        try:
            self.coord.announce_worker(self.hostname, self.queues, os.getpid(), ttl_s=3 * EVERY_S)
        except Exception as e:  # Redis away: /ready says so itself
            log.warning("worker heartbeat failed: %s", e)

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
    _current = Heartbeat(Coordinator.from_url(settings.redis_url, settings.redis_prefix), sender.hostname, queues)
    _current.start()
    log.info("worker %s consumes %s", sender.hostname, ", ".join(queues))


def on_worker_shutdown(**_) -> None:
    global _current
    if _current is not None:
        _current.stop()
        _current = None
