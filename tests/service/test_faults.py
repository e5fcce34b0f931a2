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
import redis
from svc_helpers import METRICS, REDIS_URL, job_log, job_status, upload, wait_for, wait_job

from service.core.coord import Coordinator, lock_token, parse_token
from service.core.inflight import scan
from service.jobs.store import new_job_id
from service.jobs.watchdog import Watchdog
from worker.runner import execute_stage

# checkpoints every 140 (the live tests' scene: 12 views, 160x120, preset fast): training (~45 s here) outlasts the
# outage, which starts at the first checkpoint, so the runner rides it out and goes on after it
ITERATIONS = 700
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
    kind = "appendonly" if stack.redis.appendonly else "no persistence"
    METRICS[f"Redis outage ({kind}): unreachable shown after (s)"] = f"{noticed:.1f}"
    assert noticed <= NOTICE_S, noticed
    assert down["state"] == "running" and down["worker_lost"] is False, down
    time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - stopped)))
    stack.redis.start()
    back = time.monotonic()
    during = int(re.search(r"iteration (\d+)/", down["message"])[1])  # "…; train goes on (iteration 123/700)"

    def no_false_loss(s: dict) -> dict:
        # the runner lives on through the outage: never declared lost (a false loss = two runners)
        assert not s["worker_lost"], s
        return s

    # back: the status shows training's own progress again (the runner kept its lock, re-taking it if it vanished)
    def progressing() -> dict | None:
        s = no_false_loss(job_status(c, jid))
        m = re.match(r"iteration (\d+)/", s["message"])
        return s if m and int(m[1]) > during else None

    again = wait_for("the status to show training's progress again", progressing, timeout=NOTICE_S + 2,
                     interval=0.25)
    assert again["state"] == "running" and again["stage"] == "train", again
    METRICS[f"Redis outage ({kind}): back to progress after (s)"] = f"{time.monotonic() - back:.1f}"
    assert time.monotonic() - back <= NOTICE_S
    final = wait_job(c, jid, {"done", "failed", "cancelled"}, timeout=240, on_poll=no_false_loss)
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
    # training rode the outage out: one attempt, never resumed (nor restarted)
    assert "resumed from" not in log and _stage(final, "train")["attempts"] == 1, log[-3000:]
    METRICS[f"Redis outage ({kind}): train iterations during the outage"] = f"{again['message']} (at the stop: "\
        f"{during})"



# ---------------------------------------------------------------- runner liveness (shared Redis, DB 15)


@pytest.fixture()
def coord(unit_prefix):
    c = Coordinator.from_url(REDIS_URL, f"{unit_prefix}-{uuid.uuid4().hex[:6]}")
    yield c
    c.delete_all_keys()
    c.close()


def test_a_lock_names_its_holder_and_a_dead_one_is_taken_over(coord) -> None:
    job = "j" + uuid.uuid4().hex[:12]
    lock = coord.try_run_lock(job, ttl_s=30, holder="w1@host")
    try:
        host, pid, taken = parse_token(lock.token)
        assert (host, pid) == ("w1@host", os.getpid()) and abs(taken - time.time()) < 5
        # no heartbeat of w1@host at all (and Redis up for longer than a heartbeat's life): dead
        assert coord.uptime_s() > 7
        assert coord.holder_state(job) == ("dead", lock.token)
        # a heartbeat older than the lock proves nothing (a pool child that just started): alive
        coord.redis.set(coord.key("worker", "w1@host"), '{"queues": ["cpu"], "pid": 1, "pids": [1], "at": 0}')
        assert coord.holder_state(job)[0] == "alive"
        coord.announce_worker("w1@host", ["cpu"], 1, ttl_s=6, pids=[1, os.getpid()])
        assert coord.holder_state(job)[0] == "alive"
        # the next beat no longer lists the holder's pid: dead; a busy task takes the lock over, once
        coord.announce_worker("w1@host", ["cpu"], 1, ttl_s=6, pids=[1, 99999999])
        state, value = coord.holder_state(job)
        assert state == "dead" and value == lock.token
        assert coord.try_run_lock(job, 30, "w2@host") is None  # a plain try still finds it held
        second = coord.try_run_lock(job, 30, "w2@host", steal_from=value)
        assert second is not None and coord.run_lock_value(job) == second.token
        assert coord.try_run_lock(job, 30, "w3@host", steal_from=value) is None  # the value moved on
        # the old holder's next renewal finds another runner's lock: it stops (lost), it does not re-take it
        with pytest.raises(redis.exceptions.LockNotOwnedError):
            lock._renew()
        second.release()
    finally:
        lock._stop.set()
    # an anonymous holder (taken outside a worker) is judged by its TTL only
    anon = coord.try_run_lock(job, 30)
    assert coord.holder_state(job)[0] == "unknown"
    anon.release()
    assert coord.holder_state(job) == ("none", None)


def test_a_lock_that_vanished_with_redis_is_re_taken_only_if_free(coord) -> None:
    job = "j" + uuid.uuid4().hex[:12]
    lock = coord.try_run_lock(job, ttl_s=30, holder="w1@host")
    lock._stop.set()  # renew by hand
    coord.redis.delete(coord.key("job", job, "run"))  # what a restart without persistence does
    lock._renew()
    assert lock.retaken == 1 and coord.run_lock_value(job) == lock.token
    coord.redis.set(coord.key("job", job, "run"), lock_token("w9@host", 1))  # someone else took it meanwhile
    with pytest.raises(redis.exceptions.LockNotOwnedError):
        lock._renew()
    assert lock.retaken == 1


# ---------------------------------------------------------------- broker scan and watchdog


def _new_job(rt) -> tuple[str, str]:
    job_id = new_job_id()
    rt.store.job_dir(job_id).mkdir()
    m = rt.jobs.create(job_id, "alice", {"source": "/nowhere"}, {"kind": "upload"})
    return job_id, m.run_id


def test_the_broker_scan_sees_queued_and_unacknowledged_stage_messages(tmp_path, unit_prefix) -> None:
    from svc_helpers import make_settings

    from service.core.broker import producer
    from service.core.dispatch import Dispatcher

    prefix = f"{unit_prefix}-{uuid.uuid4().hex[:6]}"
    settings = make_settings(tmp_path, prefix)
    coord = Coordinator.from_url(REDIS_URL, prefix)
    app = producer(settings)
    try:
        d = Dispatcher(app)
        d.send_stage("jaaaaaaaa1", "train", "run1")
        d.send_stage("jaaaaaaaa2", "sfm", "run2")
        d.send_webhook("jaaaaaaaa3", "hook1")  # another task: not a stage
        found = scan(coord.redis, prefix)
        assert found.queued == {("jaaaaaaaa1", "train", "run1"), ("jaaaaaaaa2", "sfm", "run2")}, found
        assert found.unacked == set() and found.unreadable == 0
        # a delivered, unacknowledged message moves from the queue list to the unacked hash (as kombu does)
        raw = coord.redis.rpop(f"{prefix}:cpu")
        coord.redis.hset(f"{prefix}:unacked", "tag-1", f'[{raw}, "dualphys", "cpu"]')
        found = scan(coord.redis, prefix)
        assert found.holds("jaaaaaaaa1", "run1") != found.holds("jaaaaaaaa2", "run2")
        assert len(found.queued) == 1 and len(found.unacked) == 1
        assert found.holds("jaaaaaaaa1", "other-run") == (False, False)
        coord.redis.hset(f"{prefix}:unacked", "tag-2", "not json")
        assert scan(coord.redis, prefix).holds("jzzzzzzzz", "x") == (True, True)  # unreadable: hands off
    finally:
        app.close()
        coord.delete_all_keys()
        coord.close()


def test_the_watchdog_re_queues_a_job_nobody_holds_after_its_grace_only(rt) -> None:
    job_id, run_id = _new_job(rt)  # queued, its message "sent" to a dispatcher that only records
    sent = rt.jobs.dispatcher.sent
    assert sent == [(job_id, "ingest", run_id)]
    dog = Watchdog(rt.jobs, rt.coord, grace_s=0.6)
    assert dog.run_pass() == []  # the manifest was written just now
    time.sleep(0.7)
    assert dog.run_pass() == []  # abandoned from now on: the grace starts
    # a live runner holds it: never re-queued
    lock = rt.coord.try_run_lock(job_id, 30)  # anonymous: "unknown", the TTL decides
    time.sleep(0.7)
    assert dog.run_pass() == []
    lock.release()
    assert dog.run_pass() == []  # the grace starts again
    time.sleep(0.7)
    assert dog.run_pass() == [(job_id, "ingest")]
    assert sent[-1] == (job_id, "ingest", run_id) and len(sent) == 2
    m = rt.store.read(job_id)
    assert m.message == "no runner and no queued task; ingest re-queued, resuming from the start of the stage"
    assert "watchdog: no runner and no queued task" in rt.store.layout(job_id).log.read_text()
    # a finished job is left alone
    m.state = "done"
    rt.store.write(m)
    time.sleep(0.7)
    assert dog.run_pass() == [] and dog.run_pass() == [] and len(sent) == 2


@pytest.fixture()
def calls(monkeypatch) -> list[str]:
    """The pipeline's run_stage replaced where the runner calls it: records the stage, reports progress."""
    import worker.runner

    ran: list[str] = []

    def fake_run_stage(job_dir, stage, opts, ctx):
        ran.append(stage)
        ctx.on_progress(stage, 1.0, "done")
        return {"stage": stage}, False

    monkeypatch.setattr(worker.runner, "run_stage", fake_run_stage)
    return ran


def test_a_stage_whose_end_meets_a_redis_outage_waits_for_it(rt, calls, monkeypatch) -> None:
    """The end of a stage is recorded once Redis answers again (here: the first two mutex attempts fail)."""
    job_id, run_id = _new_job(rt)
    real = rt.coord.manifest_mutex
    failures = [0]

    def flaky(job, timeout_s=30.0):
        if calls and failures[0] < 2:  # once the stage ran: its progress write (goes on) and its end (waits)
            failures[0] += 1
            raise redis.ConnectionError("Redis is away")
        return real(job, timeout_s)

    monkeypatch.setattr(rt.coord, "manifest_mutex", flaky)
    out = execute_stage(rt, job_id, "ingest", run_id)
    assert out.status == "ran" and failures[0] == 2
    m = rt.store.read(job_id)
    assert m.stage("ingest").status == "done" and [a.outcome for a in m.stage("ingest").history] == ["done"]
    assert rt.jobs.dispatcher.sent == [(job_id, "ingest", run_id), (job_id, "sfm", run_id)]
