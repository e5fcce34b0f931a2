"""Issue 44, items 1-2: nothing is lost when Redis or a worker dies, and a dead runner shows within seconds.

Live tests run the real processes (uvicorn, a Celery prefork worker) against a redis-server of their own
(``private_live``), which they stop and start again, with append-only persistence and without. The others use the
shared Redis (DB 15, a key prefix of their own) and call the coordinator, the broker scan and the watchdog
directly."""

from __future__ import annotations

import os
import re
import time
import uuid

import pytest
from svc_helpers import REDIS_URL, RecordingDispatcher, job_log, job_status, upload, wait_for, wait_job

from service.core.coord import Coordinator, lock_token, parse_token
from service.core.inflight import scan
from service.jobs.watchdog import Watchdog

ITERATIONS = 400  # checkpoints every 80 (the live tests' scene: 12 views, 160x120, preset fast)
# Longer than every timing of the stack that the outage crosses (conftest.live_env): the run lock's TTL (5 s),
# the visibility timeout (8 s), a worker heartbeat's life (6 s), the watchdog's grace (4 s): so the same paths run
# as with the 60 s outage against the production timings (60 s lock, 15 min visibility), in a fifth of
# the time. (With persistence the lock and heartbeats expire while Redis is down; without, they are gone.)
OUTAGE_S = 12.0
NOTICE_S = 10.0  # the job's state says what is happening within this of each change


def _stage(job: dict, name: str) -> dict:
    return next(s for s in job["stages"] if s["name"] == name)


@pytest.mark.slow
@pytest.mark.timeout(420)
@pytest.mark.parametrize("private_redis", [True, False], ids=["appendonly", "no-persistence"], indirect=True)
def test_redis_outage_mid_training_the_job_finishes_once(private_live, scene_zip) -> None:
    stack = private_live
    c = stack.client("alice", timeout=10)
    r = upload(c, scene_zip, iterations=ITERATIONS, preset="fast")
    assert r.status_code == 201, r.text
    jid = r.json()["id"]

    def training() -> dict | None:
        s = job_status(c, jid)
        assert s["state"] in ("queued", "running"), s
        return s if s["stage"] == "train" and "checkpoint written" in job_log(c, jid) else None

    wait_for("a training checkpoint", training, timeout=240, interval=0.2)
    stack.redis.stop()
    stopped = time.monotonic()
    # while Redis is away the status (from the manifest on disk) says so, and training goes on
    down = wait_for("the status to say the coordinator is unreachable",
                    lambda: (s if "coordinator (Redis) is unreachable" in (s := job_status(c, jid))["message"]
                             else None), timeout=NOTICE_S + 2, interval=0.25)
    noticed = time.monotonic() - stopped
    assert noticed <= NOTICE_S, noticed
    assert down["state"] == "running" and down["worker_lost"] is False, down
    time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - stopped)))
    stack.redis.start()
    back = time.monotonic()
    wait_for("the status to drop the outage message",
             lambda: (s if "unreachable" not in (s := job_status(c, jid))["message"] or s["state"] != "running"
                      else None), timeout=NOTICE_S + 2, interval=0.25)
    assert time.monotonic() - back <= NOTICE_S
    final = wait_job(c, jid, {"done", "failed", "cancelled"}, timeout=240)
    assert final["state"] == "done", final
    # once: one completed run, every stage's record holds exactly one completion
    assert final["completed_runs"] == 1 and [r["outcome"] for r in final["runs"]] == ["done"], final["runs"]
    for s in final["stages"]:  # (ingest ran in the API, which keeps no attempt history)
        assert s["status"] == "done" and [a["outcome"] for a in s["history"]].count("done") == int(
            s["name"] != "ingest"), s
    log = job_log(c, jid)
    # no duplicate next-stage work: every stage after train started once
    for name in ("evaluate", "restore", "export"):
        assert len(re.findall(rf"stage {name} started", log)) == 1, log[-3000:]
    # training either rode the outage out or resumed from its last checkpoint: never from scratch
    resumed = [int(x) for x in re.findall(r"resumed from \S+ at iteration (\d+)", log)]
    assert all(it > 0 for it in resumed), resumed
    assert _stage(final, "train")["attempts"] == 1 + len(resumed)

