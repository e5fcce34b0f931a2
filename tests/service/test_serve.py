"""``dualphys serve`` (issue 13, items 7 and 11): the environment and the flags compose the documented way, two
owners can be configured without Python, every flag has help, and SIGTERM stops the worker and beat too.

The process under test is the real command (``python -m cli serve``): uvicorn in it, a Celery worker
and beat as its children, the real Redis (DB 15, a key prefix of its own)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import httpx
import pytest
import redis
from svc_helpers import KEYS, METRICS, REDIS_URL, REPO, auth, delete_prefix, free_port, wait_for

from service.embedded import DEFAULT_REDIS_URL, serve_config

pytestmark = pytest.mark.slow

STOP_BOUND_S = 45.0  # STOP_GRACE_S (20) for a warm Celery shutdown, then SIGKILL, with room for a busy machine


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) == pid:
            out.append(int(entry))
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2] != "Z"


def test_every_serve_flag_has_help() -> None:
    from cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    serve = sub.choices["serve"]
    flags = [a for a in serve._actions if a.option_strings and a.dest != "help"]
    assert {a.dest for a in flags} >= {"host", "port", "data_dir", "redis_url", "api_keys_file", "workers",
                                      "no_beat", "log_level"}
    assert all(a.help and len(a.help) > 10 for a in flags), [a.dest for a in flags if not a.help]


def test_serve_config_flags_win_over_the_environment(tmp_path: Path) -> None:
    env = {"DUALPHYS_DATA_DIR": str(tmp_path / "env-data"), "DUALPHYS_REDIS_URL": "redis://10.0.0.1:6379/3",
           "DUALPHYS_API_KEYS": json.dumps({KEYS["alice"]: "alice", KEYS["bob"]: "bob"})}
    from_env = serve_config(environ=env)
    assert from_env.data_dir == tmp_path / "env-data" and from_env.redis_url == "redis://10.0.0.1:6379/3"
    assert from_env.api_keys == {KEYS["alice"]: "alice", KEYS["bob"]: "bob"}
    keys_file = tmp_path / "keys.json"
    keys_file.write_text(json.dumps({KEYS["bob"]: "bob"}))
    flags = serve_config(tmp_path / "flag-data", "redis://127.0.0.1:6379/9", api_keys_file=keys_file, environ=env)
    assert flags.data_dir == tmp_path / "flag-data" and flags.redis_url == "redis://127.0.0.1:6379/9"
    assert flags.api_keys == {KEYS["bob"]: "bob"}
    bare = serve_config(environ={})
    assert bare.redis_url == DEFAULT_REDIS_URL and bare.api_keys is None and bare.data_dir.name == "dualphys-data"
    with pytest.raises(ValueError, match="DUALPHYS_API_KEYS"):
        serve_config(environ={"DUALPHYS_API_KEYS": '["not", "a", "mapping"]'})


@pytest.mark.timeout(240)
def test_serve_reads_the_environment_and_stops_its_children_on_sigterm(tmp_path: Path) -> None:
    prefix = f"dptest-{uuid.uuid4().hex[:8]}-serve"
    port = free_port()
    data = tmp_path / "data-from-env"
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("DUALPHYS_")},
           "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]),
           "OMP_WAIT_POLICY": "PASSIVE", "PYTHONUNBUFFERED": "1",
           "DUALPHYS_REDIS_URL": REDIS_URL, "DUALPHYS_REDIS_PREFIX": prefix, "DUALPHYS_DATA_DIR": str(data),
           "DUALPHYS_API_KEYS": json.dumps({v: k for k, v in KEYS.items()}), "DUALPHYS_MIN_FREE_BYTES": "0"}
    log_path = tmp_path / "serve.log"
    with open(log_path, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "cli", "serve", "--port", str(port), "--log-level",
                                 "warning"], cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    children: list[int] = []
    client = redis.Redis.from_url(REDIS_URL)
    try:
        def up() -> bool:
            assert proc.poll() is None, log_path.read_text(errors="replace")[-3000:]
            try:
                return httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for("dualphys serve to answer", up, timeout=90)
        # both owners of DUALPHYS_API_KEYS work; no local key was made; the data folder is DUALPHYS_DATA_DIR
        for owner in ("alice", "bob"):
            r = httpx.get(f"http://127.0.0.1:{port}/v1/jobs", headers=auth(owner), timeout=10)
            assert r.status_code == 200, (owner, r.text)
        assert (data / "jobs").is_dir() and not (data / "api-key").exists()
        assert not (tmp_path / "dualphys-data").exists()
        # the worker uses DUALPHYS_REDIS_URL (DB 15) with the prefix: its queue bindings are there
        wait_for("the worker's queue bindings in DB 15", lambda: any(client.scan_iter(match=f"{prefix}:*")),
                 timeout=90)
        children = wait_for("the worker and beat", lambda: (c if len(c := _children(proc.pid)) >= 2 else None),
                            timeout=30)
        r = httpx.get(f"http://127.0.0.1:{port}/ready", timeout=10)
        assert r.status_code == 200, r.text
        # SIGTERM (docker stop, systemd): the API exits and so do the worker and beat, within a bounded time
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=STOP_BOUND_S)
        wait_for("the children to exit", lambda: not any(_alive(c) for c in children),
                 timeout=max(1.0, STOP_BOUND_S - (time.monotonic() - t0)))
        took = time.monotonic() - t0
        assert took < STOP_BOUND_S, took
    finally:
        _clean_up(proc, children, client, prefix)


def _clean_up(proc: subprocess.Popen, pids, client, prefix: str) -> None:
    """Kill serve and (only left on a failure) the process groups this test started, by pid; drop its Redis keys."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    for pid in pids:
        if _alive(pid):
            try:
                os.killpg(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    delete_prefix(client, prefix)
    client.close()


def _serve_env(prefix: str, data: Path, **extra: str) -> dict[str, str]:
    return {**{k: v for k, v in os.environ.items() if not k.startswith("DUALPHYS_")},
            "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]),
            "OMP_WAIT_POLICY": "PASSIVE", "PYTHONUNBUFFERED": "1",
            "DUALPHYS_REDIS_URL": REDIS_URL, "DUALPHYS_REDIS_PREFIX": prefix, "DUALPHYS_DATA_DIR": str(data),
            "DUALPHYS_API_KEYS": json.dumps({v: k for k, v in KEYS.items()}), "DUALPHYS_MIN_FREE_BYTES": "0",
            **extra}


@pytest.mark.timeout(300)
def test_serve_restarts_a_killed_worker_and_the_job_resumes(tmp_path: Path, scene_zip: bytes) -> None:
    """kill -9 of the worker's main process under serve (issue 44, item 3): serve reaps it, kills its orphaned
    pool child (no stage goes on unowned) and starts a new worker; the job shows the loss within 10 s and, its
    message left unacknowledged by the dead worker (the visibility timeout is the production 15 minutes here), the
    watchdog re-queues the stage: training resumes from its checkpoint within 30 s and the job finishes."""
    from svc_helpers import job_log, job_status, upload, wait_job

    prefix = f"dptest-{uuid.uuid4().hex[:8]}-serve"
    port = free_port()
    env = _serve_env(prefix, tmp_path / "data", DUALPHYS_WATCHDOG_EVERY_S="1", DUALPHYS_WATCHDOG_GRACE_S="4",
                     DUALPHYS_LOCK_TTL_S="5", DUALPHYS_LOCK_RETRY_S="1")
    log_path = tmp_path / "serve.log"
    with open(log_path, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "cli", "serve", "--port", str(port), "--no-beat"],
                                cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    client = redis.Redis.from_url(REDIS_URL)
    started: list[int] = []
    try:
        base = f"http://127.0.0.1:{port}"

        def ready() -> bool:
            assert proc.poll() is None, log_path.read_text(errors="replace")[-3000:]
            try:
                return httpx.get(f"{base}/ready", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for("serve to be ready (with its worker)", ready, timeout=120)
        c = httpx.Client(base_url=base, headers=auth("alice"), timeout=30)
        r = upload(c, scene_zip, iterations=400, preset="fast")
        assert r.status_code == 201, r.text
        jid = r.json()["id"]
        wait_for("a training checkpoint", lambda: "checkpoint written" in job_log(c, jid), timeout=200)
        [worker] = _children(proc.pid)  # --no-beat: the worker is serve's only child
        pool = _children(worker)
        started += [worker, *pool]
        assert len(pool) == 1, pool
        os.kill(worker, signal.SIGKILL)  # the main process only: its pool child is orphaned, still training
        killed = time.monotonic()
        new = wait_for("serve to start a new worker", lambda: [p for p in _children(proc.pid) if p != worker],
                       timeout=30)
        started += new
        wait_for("the orphaned pool child to be killed", lambda: not _alive(pool[0]), timeout=10)
        lost = wait_for("the loss to show", lambda: s if (s := job_status(c, jid))["worker_lost"] else None,
                        timeout=15, interval=0.2)
        seen = time.monotonic() - killed
        METRICS["serve, worker main killed: loss shown after (s)"] = f"{seen:.1f}"
        assert seen <= 10, seen
        assert lost["state"] == "running" and "worker lost during train" in lost["message"], lost
        wait_for("training to resume", lambda: "resumed from" in job_log(c, jid), timeout=40, interval=0.25)
        resumed = time.monotonic() - killed
        METRICS["serve, worker main killed: training resumed after (s)"] = f"{resumed:.1f}"
        assert resumed <= 30, resumed
        final = wait_job(c, jid, {"done", "failed", "cancelled"}, timeout=200)
        assert final["state"] == "done" and final["completed_runs"] == 1, final
        train = next(s for s in final["stages"] if s["name"] == "train")
        assert [a["outcome"] for a in train["history"]] == ["worker_lost", "done"], train
        assert "the worker exited (code -9); restarting it" in log_path.read_text(errors="replace")
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=STOP_BOUND_S)
    finally:
        _clean_up(proc, started, client, prefix)


def test_a_child_that_keeps_dying_makes_serve_give_up() -> None:
    """The supervisor restarts a dead child after a doubling backoff and gives up after its limit, asking the
    server to stop (serve then raises, and `dualphys serve` exits 1 with the reason)."""
    from service.embedded import Child, Supervisor

    class Server:
        should_exit = False

    server = Server()
    dies = Child("worker", [sys.executable, "-c", "import sys; sys.exit(3)"])
    sup = Supervisor([dies], os.environ, on_give_up=server, max_restarts=2, window_s=600)
    sup.start()
    try:
        wait_for("the supervisor to give up", lambda: sup.gave_up, timeout=30)  # backoff 1 s, 2 s
    finally:
        sup.stop()
    assert sup.gave_up == "the worker exited (code 3) 3 times within 600 s; stopping", sup.gave_up
    assert server.should_exit is True and len(dies.restarts) == 2
