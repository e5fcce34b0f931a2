"""Waiting for a job: poll its status until it is done, failed or cancelled."""

from __future__ import annotations

import time
from collections.abc import Callable

from service.client.http import TERMINAL_STATES, ServiceClient


def wait_job(client: ServiceClient, job_id: str, interval_s: float = 2.0, timeout_s: float | None = None,
             on_update: Callable[[dict], None] | None = None, sleep: Callable[[float], None] = time.sleep) -> dict:
    """The job's status once it reached a terminal state; ``on_update`` sees every status polled. Raises
    TimeoutError after ``timeout_s`` (None: wait as long as it takes)."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while True:
        job = client.job(job_id)
        if on_update:
            on_update(job)
        if job["state"] in TERMINAL_STATES:
            return job
        if deadline is not None and time.monotonic() >= deadline:
            raise TimeoutError(f"job {job_id} is still {job['state']} after {timeout_s:g} s")
        sleep(interval_s)
