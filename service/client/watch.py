"""Waiting for a job: poll its status until it is done, failed or cancelled."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from service.client.errors import ClientError

if TYPE_CHECKING:  # annotations only: this module itself needs no httpx
    from service.client.remote import ServiceClient

log = logging.getLogger(__name__)

TERMINAL_STATES = frozenset({"done", "failed", "cancelled"})
TRANSIENT = frozenset({"connection_failed", "timeout", "transport_error"})
TRANSIENT_STATUS = frozenset({502, 503, 504})


def wait_job(client: ServiceClient, job_id: str, interval_s: float = 2.0, timeout_s: float | None = None,
             on_update: Callable[[dict], None] | None = None, sleep: Callable[[float], None] = time.sleep,
             max_misses: int = 5) -> dict:
    """The job's status once it reached a terminal state; ``on_update`` sees every status polled. A server that
    does not answer (restarting, a flaky link from a vessel) is asked again, up to ``max_misses`` polls in a row,
    waiting twice as long each time; any other error is raised at once. Raises TimeoutError after ``timeout_s``
    (None: wait as long as it takes)."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    misses = 0
    while True:
        try:
            job = client.job(job_id)
        except ClientError as e:
            misses += 1
            if misses > max_misses or not (e.code in TRANSIENT or e.status in TRANSIENT_STATUS):
                raise
            log.warning("polling job %s: %s; asking again (%d/%d)", job_id, e.message, misses, max_misses)
            sleep(interval_s * 2 ** misses)
            continue
        misses = 0
        if on_update:
            on_update(job)
        if job["state"] in TERMINAL_STATES:
            return job
        if deadline is not None and time.monotonic() >= deadline:
            raise TimeoutError(f"job {job_id} is still {job['state']} after {timeout_s:g} s")
        sleep(interval_s)
