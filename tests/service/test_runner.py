"""The stage task's body (``worker.runner.execute_stage``) called directly, with the real Redis, a job folder on
disk, a dispatcher that only records what it would send, and the pipeline's ``run_stage`` replaced by a fake where
the runner calls it (``worker.runner.run_stage``):
redelivery, locking, cancel, failure codes and crash limits, without Celery or torch."""

from __future__ import annotations

import threading
import time

import pytest

import pipeline.job.runner
import service.jobs.ops
import worker.runner
from pipeline.job.options import JobCancelled
from service.compose import Components
from service.jobs.store import new_job_id
from worker.runner import execute_stage

STAGES = pipeline.job.runner.STAGES


class Calls(list):
    """The stages the fake ran, in order; ``behaviour[stage](ctx)`` runs inside the fake stage."""

    def __init__(self) -> None:
        super().__init__()
        self.behaviour: dict = {}


@pytest.fixture()
def calls(monkeypatch):
    """Replace the pipeline's run_stage; ``calls.behaviour[stage]`` may raise or report progress."""
    record = Calls()

    def fake_run_stage(job_dir, stage, opts, ctx):
        record.append(stage)
        ctx.on_progress(stage, 0.0, "started")
        action = record.behaviour.get(stage)
        if action is not None:
            action(ctx)
        ctx.on_progress(stage, 1.0, "done")
        return {"stage": stage}, False

    monkeypatch.setattr(worker.runner, "run_stage", fake_run_stage)
    return record


def new_job(rt: Components) -> tuple[str, str]:
    job_id = new_job_id()
    rt.store.job_dir(job_id).mkdir()
    m = rt.jobs.create(job_id, "alice", {"source": "/nowhere"}, {"kind": "upload"})
    return job_id, m.run_id


def test_runs_every_stage_once_and_hands_over(rt, calls) -> None:
    job_id, run_id = new_job(rt)
    sent = rt.jobs.dispatcher.sent
    assert sent == [(job_id, STAGES[0], run_id)]
    for stage in STAGES:
        assert execute_stage(rt, job_id, stage, run_id).status == "ran"
    assert calls == list(STAGES)
    assert [s for _, s, _ in sent] == list(STAGES)
    m = rt.store.read(job_id)
    assert (m.state, m.progress, m.completed_runs) == ("done", 100.0, 1)
    assert all(m.stage(s).status == "done" and m.stage(s).attempts == 1 for s in STAGES)
    # every stage delivered again (broker redelivery): nothing runs, nothing is sent, still one completed run
    for stage in STAGES:
        assert execute_stage(rt, job_id, stage, run_id).status == "stale"
    assert calls == list(STAGES) and len(sent) == len(STAGES)
    assert rt.store.read(job_id).completed_runs == 1


def test_redelivered_done_stage_only_resends_a_missing_handover(rt, calls) -> None:
    job_id, run_id = new_job(rt)
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "ran"
    m = rt.store.read(job_id)
    m.dispatched.remove(STAGES[1])  # as if the worker died between finishing the stage and sending the next
    rt.store.write(m)
    n = len(rt.jobs.dispatcher.sent)
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "already_done"
    assert rt.jobs.dispatcher.sent[n:] == [(job_id, STAGES[1], run_id)]
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "already_done"
    assert len(rt.jobs.dispatcher.sent) == n + 1 and calls == [STAGES[0]]


def test_a_locked_job_is_not_run_twice(rt, calls) -> None:
    job_id, run_id = new_job(rt)
    lock = rt.coord.try_run_lock(job_id, 3)
    try:
        out = execute_stage(rt, job_id, STAGES[0], run_id)
        assert out.status == "busy" and out.retry_after == rt.settings.lock_retry_s
        assert calls == []
    finally:
        lock.release()
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "ran"


def test_stale_runs_and_deleted_jobs_are_dropped(rt, calls) -> None:
    job_id, run_id = new_job(rt)
    assert execute_stage(rt, job_id, STAGES[0], "not-the-run").status == "stale"
    assert execute_stage(rt, "jdoesnotexist00", STAGES[0], run_id).status == "stale"
    assert calls == []


def test_cancel_flag_stops_the_stage_and_the_chain(rt, calls) -> None:
    job_id, run_id = new_job(rt)

    def wait_for_cancel(ctx):
        rt.jobs.cancel(job_id, "alice")
        for _ in range(100):
            if ctx.should_cancel():
                raise JobCancelled("cancelled in the loop")
            threading.Event().wait(0.05)
        raise AssertionError("should_cancel never turned True")

    calls.behaviour[STAGES[0]] = wait_for_cancel
    # the job is queued and nobody holds its lock yet, so an API cancel now would cancel it outright;
    # run the stage first so the cancel arrives while it runs
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "cancelled"
    m = rt.store.read(job_id)
    assert m.state == "cancelled" and m.stage(STAGES[0]).status == "cancelled"
    assert [s for _, s, _ in rt.jobs.dispatcher.sent] == [STAGES[0]]


def test_failure_is_recorded_with_stage_and_code(rt, calls) -> None:
    from pipeline.sfm.recipe import NoModelError

    job_id, run_id = new_job(rt)

    def boom(ctx):
        raise NoModelError("no initial image pair")

    calls.behaviour[STAGES[0]] = boom
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "failed"
    m = rt.store.read(job_id)
    assert m.state == "failed"
    assert m.error.model_dump() == {"stage": STAGES[0], "code": "no_model", "message": "no initial image pair"}
    assert "no initial image pair" in rt.store.read_log(job_id, 0, 1 << 20)[0]


def test_a_stage_whose_worker_keeps_dying_fails_the_job(rt, calls) -> None:
    job_id, run_id = new_job(rt)
    m = rt.store.read(job_id)
    rec = m.stage(STAGES[0])
    rec.status, rec.attempts = "running", rt.settings.max_stage_attempts  # two earlier runners died mid-stage
    rt.store.write(m)
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "failed"
    m = rt.store.read(job_id)
    assert m.state == "failed" and m.error.code == "worker_lost" and calls == []
    assert m.stage(STAGES[0]).status == "failed"
    assert [a.outcome for a in m.stage(STAGES[0]).history] == ["worker_lost"]  # the last lost attempt is kept


def test_every_attempt_stays_in_the_stage_record(rt, calls) -> None:
    """Issue 13, item 6: a stage whose first worker died shows both attempts, the lost one with its last
    progress message, and the status says the worker is lost while nobody holds the job."""
    job_id, run_id = new_job(rt)
    m = rt.store.read(job_id)
    rec = m.stage(STAGES[0])
    rec.status, rec.attempts, rec.started_at = "running", 1, time.time() - 5
    m.state, m.current_stage, m.message = "running", STAGES[0], "iteration 235/600"
    rt.store.write(m)
    rt.store.append_log(job_id, "INFO pipeline.train.checkpoint: checkpoint written: train/latest.pt (iteration 120)")
    view = rt.jobs.view(rt.store.read(job_id))  # nobody holds the run lock: the worker is gone
    assert view.worker_lost and view.state == "running"
    assert view.message.startswith(f"worker lost during {STAGES[0]} (attempt 1) at 'iteration 235/600'")
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "ran"
    m = rt.store.read(job_id)
    hist = m.stage(STAGES[0]).history
    assert [(a.attempt, a.outcome) for a in hist] == [(1, "worker_lost"), (2, "done")]
    assert hist[0].last == "iteration 235/600" and m.stage(STAGES[0]).attempts == 2
    assert not rt.jobs.view(m).worker_lost


def test_retry_resumes_from_the_failed_stage(rt, calls, monkeypatch) -> None:
    job_id, run_id = new_job(rt)
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "ran"
    calls.behaviour[STAGES[1]] = lambda ctx: (_ for _ in ()).throw(RuntimeError("disk full"))
    assert execute_stage(rt, job_id, STAGES[1], run_id).status == "failed"
    # the real first_unfinished reads markers; the fake run_stage wrote none, so point it at the failed stage
    with monkeypatch.context() as patched:
        patched.setattr(service.jobs.ops, "first_unfinished", lambda job, opts: STAGES[1])
        m = rt.jobs.retry(job_id, "alice")
    assert m.state == "queued" and m.run_id != run_id and len(m.runs) == 2
    assert rt.jobs.dispatcher.sent[-1] == (job_id, STAGES[1], m.run_id)
    assert execute_stage(rt, job_id, STAGES[1], run_id).status == "stale"  # the old run's message
    calls.behaviour.clear()
    for stage in STAGES[1:]:
        assert execute_stage(rt, job_id, stage, m.run_id).status == "ran"
    m = rt.store.read(job_id)
    assert m.state == "done" and m.completed_runs == 1 and [r.outcome for r in m.runs] == ["failed", "done"]


def test_progress_cache_never_decreases(rt, calls) -> None:
    job_id, run_id = new_job(rt)
    rt.coord.push_progress(job_id, run_id, "train", 50.0, "before a crash")
    assert rt.coord.push_progress(job_id, run_id, "train", 20.0, "resumed") == 50.0
    m = rt.store.read(job_id)
    view = rt.jobs.view(m)
    assert view.progress == 50.0


def test_cancel_between_stages_is_immediate(rt, calls) -> None:
    job_id, run_id = new_job(rt)
    assert execute_stage(rt, job_id, STAGES[0], run_id).status == "ran"  # next stage queued, nobody runs it
    m = rt.jobs.cancel(job_id, "alice")
    assert m.state == "cancelled" and [r.outcome for r in m.runs] == ["cancelled"]
    assert execute_stage(rt, job_id, STAGES[1], run_id).status == "stale"
    assert calls == [STAGES[0]]
