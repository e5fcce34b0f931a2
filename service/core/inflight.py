"""Which stage tasks the broker holds: the messages waiting in the queue lists and those delivered but not yet
acknowledged (Celery's Redis transport, kombu: ``<prefix>:<queue>`` lists, one per priority step, and the
``<prefix>:unacked`` hash, whose values are ``[message, exchange, routing key]``). The watchdog
(``service.jobs.watchdog``) re-queues a job's stage only when neither holds it.

This reads kombu's storage layout (kombu 5.x); a message it cannot parse is counted as holding every job, so a
layout change makes the watchdog do nothing rather than re-queue work that is still queued.
"""

from __future__ import annotations

import base64
import json
import logging
from dataclasses import dataclass, field

import redis

from .dispatch import CPU_QUEUE, GPU_QUEUE, RUN_STAGE_TASK

log = logging.getLogger(__name__)

PRIORITY_SEP = "\x06\x16"  # kombu.transport.redis.Channel.sep
PRIORITY_STEPS = (0, 3, 6, 9)  # kombu.transport.redis.PRIORITY_STEPS
STAGE_QUEUES = (CPU_QUEUE, GPU_QUEUE)


@dataclass
class Inflight:
    queued: set[tuple[str, str, str]] = field(default_factory=set)  # (job id, stage, run id)
    unacked: set[tuple[str, str, str]] = field(default_factory=set)
    unreadable: int = 0  # messages whose arguments could not be read: treat every job as held

    def holds(self, job_id: str, run_id: str) -> tuple[bool, bool]:
        """(queued, unacked): whether some message for this job's run waits, or is delivered and unacknowledged."""
        if self.unreadable:
            return True, True
        return (any(j == job_id and r == run_id for j, _, r in self.queued),
                any(j == job_id and r == run_id for j, _, r in self.unacked))


def stage_args(raw: dict) -> tuple[str, str, str] | None:
    """(job id, stage, run id) of a ``dualphys.run_stage`` message (kombu's JSON envelope, Celery protocol 2);
    None for another task. Raises ValueError for a message it cannot read."""
    headers = raw.get("headers") or {}
    if headers.get("task") != RUN_STAGE_TASK:
        return None
    body = raw["body"]
    if (raw.get("properties") or {}).get("body_encoding") == "base64":
        body = base64.b64decode(body)
    args = json.loads(body)[0]
    return str(args[0]), str(args[1]), str(args[2])


def scan(client: redis.Redis, prefix: str, queues: tuple[str, ...] = STAGE_QUEUES) -> Inflight:
    """Every stage message in the broker under ``prefix`` (the broker's ``global_keyprefix`` without its colon)."""
    out = Inflight()

    def add(target: set, text) -> None:
        try:
            got = stage_args(json.loads(text))
        except (ValueError, KeyError, IndexError, TypeError) as e:
            log.warning("unreadable broker message (%s): the watchdog stands still", e)
            out.unreadable += 1
            return
        if got is not None:
            target.add(got)

    for q in queues:
        for pri in PRIORITY_STEPS:
            key = f"{prefix}:{q}" + (f"{PRIORITY_SEP}{pri}" if pri else "")
            for text in client.lrange(key, 0, -1):
                add(out.queued, text)
    for text in client.hvals(f"{prefix}:unacked"):
        try:
            message = json.loads(text)[0]
        except (ValueError, IndexError, TypeError):
            out.unreadable += 1
            continue
        add(out.unacked, json.dumps(message))
    return out
