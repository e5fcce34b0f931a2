"""Webhooks (service.webhooks): the URL check and the signature, the upload's 422s, one planned event per run end
(API cancel, worker stage end, redelivery), delivery attempts with backoff and give-up against loopback receivers,
and one tiny job through the live stack whose done / failed / cancelled events arrive signed, exactly once each.

Receivers are ``http.server`` threads on 127.0.0.1 inside the test; nothing leaves the machine."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from svc_helpers import (
    HOOK_SECRETS,
    RecordingDispatcher,
    auth,
    job_status,
    make_settings,
    small_jpegs,
    upload,
    wait_for,
    zip_bytes,
)

import pipeline.job.runner
import worker.runner
from service.jobs.store import new_job_id
from service.webhooks.callback import CallbackRefused, check_callback_url, host_allowed
from service.webhooks.deliver import deliver
from service.webhooks.signing import SIGNATURE_HEADER, sign, verify
from worker.runner import execute_stage

ALICE_SECRET = HOOK_SECRETS["alice"]
HOOK_SETTINGS = {"webhook_allowed_hosts": ["127.0.0.1"], "webhook_secrets": HOOK_SECRETS,
                 "webhook_max_attempts": 3, "webhook_backoff_s": 0.3, "webhook_timeout_s": 3}


class Receiver:
    """A loopback HTTP server in a thread that records every POST (headers, raw body) and answers ``status``."""

    def __init__(self, status: int = 204):
        self.status = status
        self.hits: list[tuple[str, dict[str, str], bytes]] = []
        self.lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 (http.server's name)
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                with receiver.lock:
                    receiver.hits.append((self.path, dict(self.headers), body))
                self.send_response(receiver.status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args) -> None:  # quiet
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}"

    def on(self, path: str) -> list[tuple[dict[str, str], bytes]]:
        with self.lock:
            return [(h, b) for p, h, b in self.hits if p == path]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture()
def receivers() -> Iterator[list[Receiver]]:
    made: list[Receiver] = []
    yield made
    for r in made:
        r.close()


def receiver(receivers: list[Receiver], status: int = 204) -> Receiver:
    r = Receiver(status)
    receivers.append(r)
    return r


def hook_headers(headers: dict[str, str]) -> dict[str, str]:
    return {k.lower(): v for k, v in headers.items()}


def check_signed(headers: dict[str, str], body: bytes) -> dict:
    """The event, after checking its signature as a receiver would (docs/SERVICE.md recipe)."""
    h = hook_headers(headers)
    assert verify(ALICE_SECRET, body, h[SIGNATURE_HEADER.lower()]), h
    event = json.loads(body)
    assert h["x-dualphys-delivery"] == event["delivery_id"]
    assert h["x-dualphys-event"] == event["event"] == f"job.{event['state']}"
    assert abs(int(h["x-dualphys-timestamp"]) - time.time()) < 120
    return event


# ---------------------------------------------------------------- signing and the URL check


def test_signature_is_hmac_sha256_of_the_raw_body() -> None:
    body = b'{"event":"job.done","job_id":"j1"}'
    sig = sign("s3cret", body)
    # computed independently: printf '%s' '<body>' | openssl dgst -sha256 -hmac s3cret
    assert sig == "sha256=7201a046f7d4a330f02c30c0c3ddf42de2b70d7fde520f182813db827d5f80f8"
    assert verify("s3cret", body, sig)
    assert not verify("s3cret", body + b" ", sig)  # any byte changed
    assert not verify("other", body, sig)
    assert not verify("s3cret", body, sig.removeprefix("sha256="))  # the prefix is part of the format
    assert not verify("s3cret", body, None)


@pytest.mark.parametrize(("url", "code"), [
    ("http://127.0.0.1:9000/hook", None),
    ("https://hooks.example.org/x?y=1", None),
    ("https://a.b.example.org/x", None),
    ("https://example.org.evil.net/x", "callback_not_allowed"),
    ("https://evil.net/x", "callback_not_allowed"),
    ("http://127.0.0.2/x", "callback_not_allowed"),
    ("http://localhost/x", "callback_not_allowed"),  # names are not resolved: only what the list says
    ("ftp://127.0.0.1/x", "invalid_callback"),
    ("127.0.0.1/x", "invalid_callback"),
    ("http:///x", "invalid_callback"),
    ("http://user:pw@127.0.0.1/x", "invalid_callback"),
    ("http://127.0.0.1:99999/x", "invalid_callback"),
    ("http://127.0.0.1/a b", "invalid_callback"),
    ("http://127.0.0.1/" + "a" * 3000, "invalid_callback"),
])
def test_callback_url_check(url: str, code: str | None) -> None:
    allowed = ["127.0.0.1", ".example.org"]
    if code is None:
        assert check_callback_url(url, allowed, has_secret=True) == url
    else:
        with pytest.raises(CallbackRefused) as e:
            check_callback_url(url, allowed, has_secret=True)
        assert e.value.code == code, str(e.value)


def test_callback_url_check_without_hosts_or_secret() -> None:
    with pytest.raises(CallbackRefused) as e:
        check_callback_url("http://127.0.0.1/x", [], has_secret=True)
    assert e.value.code == "callbacks_disabled"
    with pytest.raises(CallbackRefused) as e:
        check_callback_url("http://127.0.0.1/x", ["127.0.0.1"], has_secret=False)
    assert e.value.code == "callback_no_secret"
    assert host_allowed("EXAMPLE.org", ["example.org."]) and not host_allowed("example.org", [".example.org"])
    assert host_allowed("::1", ["[::1]"])


# ---------------------------------------------------------------- the API (in process, no worker)


@pytest.fixture()
def hook_api(tmp_path, unit_prefix):
    """The API with webhooks on for 127.0.0.1 and a secret for alice; no worker consumes its queues."""
    from fastapi.testclient import TestClient

    from service.app import create_app

    data = tmp_path / "hook"  # beside the plain ``api`` fixture's folder when a test uses both
    (data / "surveys-root").mkdir(parents=True)
    settings = make_settings(data, unit_prefix, survey_settle_s=0, **HOOK_SETTINGS)
    with TestClient(create_app(settings)) as client:
        client.settings = settings
        yield client


def small_zip(seed: int = 0) -> bytes:
    return zip_bytes({f"{i}.jpg": b for i, b in enumerate(small_jpegs(3, seed=seed))})


def test_upload_refuses_callbacks_it_may_not_call(hook_api, api) -> None:
    archive = small_zip()
    cases = [(hook_api, "alice", "http://10.0.0.1/hook", "callback_not_allowed"),
             (hook_api, "alice", "gopher://127.0.0.1/hook", "invalid_callback"),
             (hook_api, "bob", "http://127.0.0.1/hook", "callback_no_secret"),
             (api, "alice", "http://127.0.0.1/hook", "callbacks_disabled")]
    for client, owner, url, code in cases:
        r = upload(client, archive, headers=auth(owner), callback_url=url)
        assert r.status_code == 422, r.text
        assert r.json()["error"]["code"] == code, r.json()
    # also as a query parameter beside a raw body
    r = hook_api.post("/v1/jobs", params={"callback_url": "http://10.0.0.1/"}, content=archive,
                      headers={**auth("alice"), "Content-Type": "application/zip"})
    assert r.status_code == 422 and r.json()["error"]["code"] == "callback_not_allowed"
    assert not list(hook_api.settings.jobs_dir.iterdir())  # refused uploads leave nothing


def test_cancelled_queued_job_announces_once_and_delivers_signed(hook_api, receivers) -> None:
    from service.compose import compose

    rx = receiver(receivers)
    h = auth("alice")
    r = upload(hook_api, small_zip(1), headers=h, callback_url=rx.url + "/c")
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["callback_url"] == rx.url + "/c" and job["webhooks"] == []
    assert hook_api.post(f"/v1/jobs/{job['id']}/cancel", headers=h).json()["state"] == "cancelled"
    hook_api.post(f"/v1/jobs/{job['id']}/cancel", headers=h)  # cancelling a cancelled job plans nothing more
    hooks = hook_api.get(f"/v1/jobs/{job['id']}", headers=h).json()["webhooks"]
    assert [(d["event"], d["status"], d["attempts"]) for d in hooks] == [("job.cancelled", "pending", 0)]
    assert "body" not in hooks[0] and "url" not in hooks[0]

    # the delivery task's body, as the worker runs it (the API queued it; no worker consumes this prefix)
    rt = compose(hook_api.settings, None)
    try:
        out = deliver(rt, job["id"], hooks[0]["id"])
        assert out.status == "delivered", out
        assert deliver(rt, job["id"], hooks[0]["id"]).status == "dropped"  # a redelivered message sends nothing
    finally:
        rt.close()
    [(headers, body)] = rx.on("/c")
    event = check_signed(headers, body)
    assert event["job_id"] == job["id"] and event["state"] == "cancelled" and event["error"] is None
    assert event["run_id"] == job["runs"][0]["run_id"]
    assert event["links"]["bundle"] == f"/v1/jobs/{job['id']}/bundle"
    d = hook_api.get(f"/v1/jobs/{job['id']}", headers=h).json()["webhooks"][0]
    assert (d["status"], d["attempts"], d["last_status_code"], d["last_error"]) == ("delivered", 1, 204, None)
    assert d["finished_at"] >= d["created_at"]


def test_survey_callback_is_checked_and_given_to_its_jobs(hook_api) -> None:
    from service.compose import compose
    from service.surveys.scan import scan

    root = hook_api.settings.survey_roots[0]
    for i, data in enumerate(small_jpegs(6, seed=80)):
        (root / "reef" / "dive-1").mkdir(parents=True, exist_ok=True)
        (root / "reef" / "dive-1" / f"{i}.jpg").write_bytes(data)
    body = {"path": str(root / "reef"), "interval_s": 60}
    for owner, url, code in (("alice", "http://10.0.0.1/x", "callback_not_allowed"),
                             ("bob", "http://127.0.0.1/x", "callback_no_secret")):
        r = hook_api.post("/v1/surveys", json={**body, "callback_url": url}, headers=auth(owner))
        assert r.status_code == 422 and r.json()["error"]["code"] == code, r.text
    r = hook_api.post("/v1/surveys", json={**body, "callback_url": "http://127.0.0.1:9/survey"}, headers=auth("alice"))
    assert r.status_code == 201 and r.json()["callback_url"] == "http://127.0.0.1:9/survey", r.text
    rt = compose(hook_api.settings, None)
    rt.jobs.dispatcher = RecordingDispatcher()
    try:
        [job_id] = scan(rt.surveys, rt.surveys.get(r.json()["id"]), rt.jobs, rt.scan_config)
        assert rt.store.read(job_id).callback_url == "http://127.0.0.1:9/survey"
    finally:
        rt.close()


# ---------------------------------------------------------------- planning in the worker, attempts, give-up


@pytest.fixture()
def hook_rt(tmp_path, unit_prefix, monkeypatch):
    """The worker's components with webhooks on; a dispatcher that records; a fake pipeline stage runner."""
    from service.compose import compose

    settings = make_settings(tmp_path, unit_prefix, **HOOK_SETTINGS)
    runtime = compose(settings, celery_app=None)
    runtime.jobs.dispatcher = RecordingDispatcher()
    runtime.store.ensure()
    failing: set[str] = set()

    def fake_run_stage(job_dir, stage, opts, ctx):
        if stage in failing:
            failing.discard(stage)
            raise RuntimeError(f"{stage} broke")
        return {"stage": stage}, False

    monkeypatch.setattr(worker.runner, "run_stage", fake_run_stage)  # where the runner calls it
    runtime.failing = failing
    yield runtime
    runtime.close()


def new_hook_job(rt, url: str) -> str:
    job_id = new_job_id()
    rt.store.job_dir(job_id).mkdir()
    rt.jobs.create(job_id, "alice", {"source": "/nowhere"}, {"kind": "upload"}, callback_url=url)
    return job_id


def run_all(rt, job_id: str) -> None:
    """Run the stages the recording dispatcher was asked to send, until none is left."""
    sent = rt.jobs.dispatcher.sent
    i = next(k for k, s in enumerate(sent) if s[0] == job_id)
    while i < len(sent):
        jid, stage, run_id = sent[i]
        if jid == job_id:
            execute_stage(rt, jid, stage, run_id)
        i += 1


def test_one_event_per_run_end_whatever_is_redelivered(hook_rt) -> None:
    rt = hook_rt
    job_id = new_hook_job(rt, "http://127.0.0.1:9/x")
    rt.failing.add("train")
    run_all(rt, job_id)
    m = rt.store.read(job_id)
    assert m.state == "failed" and [(d.event, d.run_id) for d in m.webhooks] == [("job.failed", m.run_id)]
    first_run = m.run_id
    # every message of that run delivered again: nothing new is planned or sent
    for jid, stage, run_id in list(rt.jobs.dispatcher.sent):
        assert execute_stage(rt, jid, stage, run_id).status == "stale"
    assert len(rt.store.read(job_id).webhooks) == 1
    rt.jobs.retry(job_id, "alice")  # a new run ends again: its own event
    run_all(rt, job_id)
    m = rt.store.read(job_id)
    assert m.state == "done" and m.completed_runs == 1
    assert [(d.event, d.run_id) for d in m.webhooks] == [("job.failed", first_run), ("job.done", m.run_id)]
    assert rt.jobs.dispatcher.webhooks == [(job_id, d.id) for d in m.webhooks]
    body = json.loads(m.webhooks[0].body)
    assert body["error"]["code"] == "stage_failed" and body["error"]["stage"] == "train"


def test_runs_ended_before_a_stage_starts_announce_too(hook_rt) -> None:
    rt = hook_rt
    stages = pipeline.job.runner.STAGES
    # the worker died in the first stage as often as allowed: the next delivery fails the job (worker_lost)
    lost = new_hook_job(rt, "http://127.0.0.1:9/lost")
    m = rt.store.read(lost)
    m.stage(stages[0]).status, m.stage(stages[0]).attempts = "running", rt.settings.max_stage_attempts
    rt.store.write(m)
    assert execute_stage(rt, lost, stages[0], m.run_id).status == "failed"
    # a cancel flag set while the stage's message waited in the queue: cancelled before it starts
    flagged = new_hook_job(rt, "http://127.0.0.1:9/flagged")
    rt.coord.request_cancel(flagged)
    assert execute_stage(rt, flagged, stages[0], rt.store.read(flagged).run_id).status == "cancelled"
    events = {j: [(d.event, json.loads(d.body)["error"]) for d in rt.store.read(j).webhooks] for j in (lost, flagged)}
    assert events[lost][0][0] == "job.failed" and events[lost][0][1]["code"] == "worker_lost"
    assert events[flagged] == [("job.cancelled", None)]
    assert [j for j, _ in rt.jobs.dispatcher.webhooks] == [lost, flagged]


def test_failing_receiver_is_retried_with_backoff_then_given_up(hook_rt, receivers) -> None:
    rt = hook_rt
    rx = receiver(receivers, status=500)
    job_id = new_hook_job(rt, rx.url + "/bad")
    rt.jobs.cancel(job_id, "alice")
    [(_, delivery_id)] = rt.jobs.dispatcher.webhooks
    outcomes = [deliver(rt, job_id, delivery_id) for _ in range(4)]
    assert [(o.status, o.retry_after) for o in outcomes] == [("retry", 0.3), ("retry", 0.6), ("given_up", None),
                                                             ("dropped", None)]
    hits = rx.on("/bad")
    assert len(hits) == 3  # = webhook_max_attempts
    assert [hook_headers(h)["x-dualphys-attempt"] for h, _ in hits] == ["1", "2", "3"]
    assert len({b for _, b in hits}) == 1  # every attempt sends the same signed body
    check_signed(*hits[0])
    m = rt.store.read(job_id)
    assert m.state == "cancelled"  # the job is untouched by its webhook
    d = m.webhooks[0]
    assert (d.status, d.attempts, d.last_status_code, d.last_error) == ("given_up", 3, 500, "HTTP 500")


def test_unreachable_receiver_and_a_host_no_longer_allowed(hook_rt) -> None:
    rt = hook_rt
    job_id = new_hook_job(rt, "http://127.0.0.1:9/closed")  # port 9 (discard): nothing listens
    rt.jobs.cancel(job_id, "alice")
    [(_, delivery_id)] = rt.jobs.dispatcher.webhooks
    out = deliver(rt, job_id, delivery_id)
    assert out.status == "retry" and "ConnectError" in out.detail
    assert rt.store.read(job_id).webhooks[0].last_status_code is None
    # the operator took 127.0.0.1 off the list since: the next attempt gives up without connecting
    rt.settings = make_settings(rt.settings.data_dir, rt.settings.redis_prefix,
                                **{**HOOK_SETTINGS, "webhook_allowed_hosts": ["hooks.example.org"]})
    out = deliver(rt, job_id, delivery_id)
    assert out.status == "given_up" and out.detail.startswith("callback_not_allowed"), out
    assert rt.store.read(job_id).webhooks[0].attempts == 2


# ---------------------------------------------------------------- the live stack: one tiny job


@pytest.mark.slow
@pytest.mark.timeout(480)
def test_live_events_for_done_failed_and_cancelled(live, scene_zip, receivers) -> None:
    live.ensure_worker()
    ok, bad = receiver(receivers), receiver(receivers, status=500)
    c = live.client("alice")
    t0 = time.monotonic()
    # mode 3dgs: no water probe, no medium; the webhook does not care what the job computed
    r = upload(c, scene_zip, iterations=60, preset="fast", mode="3dgs", callback_url=ok.url + "/done")
    assert r.status_code == 201, r.text
    done_id = r.json()["id"]
    failed_id = upload(c, small_zip(70), callback_url=ok.url + "/failed").json()["id"]  # SfM cannot register
    cancel_id = upload(c, small_zip(71), callback_url=bad.url + "/cancelled").json()["id"]
    assert c.post(f"/v1/jobs/{cancel_id}/cancel").status_code == 202

    ids = (done_id, failed_id, cancel_id)
    seen: dict[str, dict] = {}

    def all_ended() -> bool:
        seen.update({j: job_status(c, j) for j in ids})
        return all(seen[j]["state"] in ("done", "failed", "cancelled") for j in ids)

    try:
        wait_for("the three jobs to end", all_ended, timeout=360, interval=0.5)
    except AssertionError:
        raise AssertionError({j: (v["state"], v["stage"], v["message"]) for j, v in seen.items()}) from None
    final = seen
    assert [final[j]["state"] for j in (done_id, failed_id, cancel_id)] == ["done", "failed", "cancelled"]
    wait_for("the done and failed events", lambda: len(ok.on("/done")) >= 1 and len(ok.on("/failed")) >= 1, 60)
    wait_for("3 attempts at the failing receiver", lambda: len(bad.on("/cancelled")) >= 3, 60)
    given_up = wait_for("the delivery to be given up", lambda: [
        d for d in job_status(c, cancel_id)["webhooks"] if d["status"] == "given_up"], 30)
    elapsed = time.monotonic() - t0
    time.sleep(2.0)  # time for any duplicate or extra retry to arrive

    [(h_done, b_done)] = ok.on("/done")  # exactly one each
    [(h_failed, b_failed)] = ok.on("/failed")
    assert len(bad.on("/cancelled")) == 3
    done_event, failed_event = check_signed(h_done, b_done), check_signed(h_failed, b_failed)
    assert (done_event["job_id"], done_event["state"], done_event["error"]) == (done_id, "done", None)
    assert done_event["run_id"] == final[done_id]["runs"][-1]["run_id"]
    assert (failed_event["job_id"], failed_event["state"]) == (failed_id, "failed")
    assert failed_event["error"]["stage"] == "sfm" and failed_event["error"]["code"]
    assert failed_event["error"] == final[failed_id]["error"]
    cancelled_event = check_signed(*bad.on("/cancelled")[0])
    assert (cancelled_event["job_id"], cancelled_event["state"]) == (cancel_id, "cancelled")

    for j in (done_id, failed_id):
        [d] = job_status(c, j)["webhooks"]
        assert (d["status"], d["attempts"], d["last_status_code"]) == ("delivered", 1, 204), d
    [d] = given_up
    assert (d["attempts"], d["last_status_code"], d["last_error"]) == (3, 500, "HTTP 500")
    s = job_status(c, cancel_id)
    assert s["state"] == "cancelled" and s["error"] is None  # the job is untouched by its failing webhook
    assert job_status(c, done_id)["state"] == "done"
    from svc_helpers import METRICS

    METRICS["webhooks: done + failed + cancelled (3 attempts, given up)"] = f"{elapsed:.1f} s"
