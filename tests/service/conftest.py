"""Fixtures for the service tests.

- ``api``: the FastAPI app in-process (``TestClient``) against the real Redis on 127.0.0.1:6379 (DB 15) under
  its own key prefix, with no worker: fast checks of the HTTP semantics (messages it queues are never run).
- ``live``: the real thing, as subprocesses: uvicorn on a free 127.0.0.1 port, a Celery prefork worker, and
  (on demand) celery beat, all with short timings, their own key prefix and data folder. Every process is
  started in its own session and killed by process group at tear-down; the prefix's Redis keys are deleted.
- ``scene_zip``: a 12-view synthetic underwater scene (cached in pytest's cache folder between runs), zipped.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
import redis
from svc_helpers import (
    HOOK_SECRETS,
    KEYS,
    MAX_ENTRIES,
    MAX_UPLOAD,
    METRICS,
    REDIS_URL,
    REPO,
    SCENE,
    PrivateRedis,
    RecordingDispatcher,
    auth,
    delete_prefix,
    free_port,
    make_settings,
    wait_for,
    zip_bytes,
)

log = logging.getLogger(__name__)


def pytest_terminal_summary(terminalreporter) -> None:
    if METRICS:
        terminalreporter.section("service metrics")
        for k, v in METRICS.items():
            terminalreporter.write_line(f"{k}: {v}")


@pytest.fixture(scope="session")
def redis_client() -> Iterator[redis.Redis]:
    client = redis.Redis.from_url(REDIS_URL, socket_connect_timeout=2)
    try:
        client.ping()
    except redis.RedisError as e:
        pytest.fail(f"the service tests need Redis on 127.0.0.1:6379 ({e}); .ci/run starts one", pytrace=False)
    yield client
    client.close()


# ---------------------------------------------------------------- synthetic data


@pytest.fixture(scope="session")
def scene_images(request) -> list[Path]:
    from pipeline.config import SynthConfig
    from pipeline.synth.procedural import generate_scene

    tag = "-".join(str(v) for v in SCENE.values())
    out = Path(request.config.cache.mkdir(f"dualphys-service-scene-{tag}"))
    images = sorted((out / "images").glob("*.png")) if (out / "images").is_dir() else []
    if len(images) != SCENE["views"]:
        generate_scene(SynthConfig(**SCENE), out)
        images = sorted((out / "images").glob("*.png"))
    return images


@pytest.fixture(scope="session")
def scene_zip(scene_images) -> bytes:
    return zip_bytes({f"dive/{p.name}": p.read_bytes() for p in scene_images})


# ---------------------------------------------------------------- in-process API (no worker)


@pytest.fixture(scope="session")
def unit_prefix(redis_client) -> Iterator[str]:
    prefix = f"dptest-{uuid.uuid4().hex[:8]}-unit"
    yield prefix
    delete_prefix(redis_client, prefix)


@pytest.fixture()
def api(tmp_path, unit_prefix):
    """TestClient over an app with its own data folder (no worker consumes its queues)."""
    from fastapi.testclient import TestClient

    from service.app import create_app

    (tmp_path / "surveys-root").mkdir()
    settings = make_settings(tmp_path, unit_prefix)
    with TestClient(create_app(settings)) as client:
        client.settings = settings
        yield client


@pytest.fixture()
def rt(tmp_path, unit_prefix):
    """The worker's components (real Redis, a job store in tmp_path) whose dispatcher only records."""
    from service.compose import compose

    settings = make_settings(tmp_path, unit_prefix, lock_ttl_s=3, max_stage_attempts=2)
    runtime = compose(settings, celery_app=None)
    runtime.jobs.dispatcher = RecordingDispatcher()
    runtime.store.ensure()
    yield runtime
    runtime.close()


# ---------------------------------------------------------------- live stack (subprocesses)


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen
    log_path: Path

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal_group(self, sig: int) -> None:
        try:
            os.killpg(self.popen.pid, sig)
        except ProcessLookupError:
            pass

    def kill9(self) -> None:
        """SIGKILL the whole process group (the Celery main process and its pool children)."""
        self.signal_group(signal.SIGKILL)
        self.popen.wait(timeout=10)

    def stop(self, grace_s: float = 5.0) -> None:
        if self.alive():
            self.signal_group(signal.SIGTERM)
            try:
                self.popen.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                pass
        self.signal_group(signal.SIGKILL)  # stragglers in the group (pool children) too
        try:
            self.popen.wait(timeout=10)
        except subprocess.TimeoutExpired:
            log.error("%s did not exit", self.name)

    def tail(self, n: int = 40) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except FileNotFoundError:
            return ""


@dataclass
class LiveStack:
    root: Path
    prefix: str
    env: dict[str, str]
    port: int
    procs: dict[str, Proc] = field(default_factory=dict)
    counter: int = 0
    redis: PrivateRedis | None = None  # the stack's own Redis server (private_live), else the shared one

    @property
    def data_dir(self) -> Path:
        return self.root / "data"

    @property
    def survey_root(self) -> Path:
        return self.root / "surveys-root"

    @property
    def api_tmp(self) -> Path:
        return self.root / "api-tmp"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _spawn(self, name: str, args: list[str], env: dict[str, str] | None = None) -> Proc:
        self.counter += 1
        log_path = self.root / "logs" / f"{name}-{self.counter}.log"
        log_path.parent.mkdir(exist_ok=True)
        out = open(log_path, "wb")
        p = subprocess.Popen(args, cwd=REPO, env=env or self.env, stdout=out, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL, start_new_session=True)
        out.close()
        proc = Proc(name, p, log_path)
        self.procs[name] = proc
        return proc

    def start_api(self) -> Proc:
        env = {**self.env, "TMPDIR": str(self.api_tmp)}
        proc = self._spawn("api", [sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app",
                                   "--host", "127.0.0.1", "--port", str(self.port), "--log-level", "warning"], env)

        def up() -> bool:
            assert proc.alive(), f"api exited:\n{proc.tail()}"
            try:
                return httpx.get(f"{self.url}/health", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for("the API to answer /health", up, timeout=60)
        return proc

    def start_worker(self) -> Proc:
        proc = self._spawn("worker", [sys.executable, "-m", "celery", "-A", "worker.app", "worker", "--pool=prefork",
                                      "--concurrency=1", "-Q", "cpu,surveys", "--loglevel=INFO", "--without-gossip",
                                      "--without-mingle", "--without-heartbeat", "-n", f"w{self.counter + 1}@%h"])
        wait_for("the worker to be ready", lambda: self._ready(proc), timeout=60)
        return proc

    def _ready(self, proc: Proc) -> bool:
        assert proc.alive(), f"{proc.name} exited:\n{proc.tail()}"
        return "ready." in proc.log_path.read_text(errors="replace")

    def ensure_worker(self) -> Proc:
        w = self.procs.get("worker")
        return w if w is not None and w.alive() else self.start_worker()

    def start_beat(self) -> Proc:
        proc = self._spawn("beat", [sys.executable, "-m", "celery", "-A", "worker.app", "beat", "--loglevel=INFO",
                                    "--schedule", str(self.data_dir / "beat-schedule")])
        wait_for("beat to start", lambda: proc.alive() and "beat: Starting" in
                 proc.log_path.read_text(errors="replace"), timeout=60)
        return proc

    def client(self, owner: str | None = "alice", timeout: float = 30.0) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=auth(owner) if owner else {}, timeout=timeout)

    def teardown(self) -> None:
        for p in self.procs.values():
            p.stop()


def live_env(stack: LiveStack, redis_url: str) -> dict[str, str]:
    """The environment of a live stack's processes: its own prefix and data folder, short timings, ``redis_url``."""
    return {
        **{k: v for k, v in os.environ.items() if not k.startswith("DUALPHYS_")},
        "OMP_WAIT_POLICY": "PASSIVE",
        "PYTHONUNBUFFERED": "1",
        # the processes import this checkout, whatever copy of the project the interpreter has installed
        "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]),
        "DUALPHYS_API_KEYS": json.dumps({v: k for k, v in KEYS.items()}),
        "DUALPHYS_DATA_DIR": str(stack.data_dir),
        "DUALPHYS_REDIS_URL": redis_url,
        "DUALPHYS_REDIS_PREFIX": stack.prefix,
        "DUALPHYS_MAX_UPLOAD_BYTES": str(MAX_UPLOAD),
        "DUALPHYS_ARCHIVE_MAX_ENTRIES": str(MAX_ENTRIES),
        "DUALPHYS_MIN_FREE_BYTES": "0",
        "DUALPHYS_VISIBILITY_TIMEOUT_S": "8",
        "DUALPHYS_RESTORE_INTERVAL_S": "1",
        "DUALPHYS_LOCK_TTL_S": "5",
        "DUALPHYS_LOCK_RETRY_S": "1",
        "DUALPHYS_WATCHDOG_EVERY_S": "1",
        "DUALPHYS_WATCHDOG_GRACE_S": "4",
        "DUALPHYS_SURVEY_ROOTS": json.dumps([str(stack.survey_root)]),
        "DUALPHYS_SURVEYS_FILE": str(stack.root / "surveys.toml"),
        "DUALPHYS_SURVEY_TICK_S": "1",
        "DUALPHYS_SURVEY_MIN_INTERVAL_S": "1",
        "DUALPHYS_SURVEY_SETTLE_S": "0",
        "DUALPHYS_SURVEY_MIN_IMAGES": "4",
        # webhooks to loopback receivers in the tests (tests/service/test_webhooks.py), quick retries
        "DUALPHYS_WEBHOOK_ALLOWED_HOSTS": json.dumps(["127.0.0.1"]),
        "DUALPHYS_WEBHOOK_SECRETS": json.dumps(HOOK_SECRETS),
        "DUALPHYS_WEBHOOK_MAX_ATTEMPTS": "3",
        "DUALPHYS_WEBHOOK_BACKOFF_S": "0.3",
        "DUALPHYS_WEBHOOK_TIMEOUT_S": "3",
    }


def start_stack(stack: LiveStack, redis_url: str) -> LiveStack:
    """Start ``stack`` (its folders, the API and a worker) against the Redis at ``redis_url``."""
    for d in (stack.data_dir, stack.survey_root, stack.api_tmp):
        d.mkdir()
    stack.env = live_env(stack, redis_url)
    stack.start_api()
    stack.start_worker()
    return stack


@pytest.fixture(scope="session")
def live(tmp_path_factory, redis_client) -> Iterator[LiveStack]:
    root = tmp_path_factory.mktemp("live")
    prefix = f"dptest-{uuid.uuid4().hex[:8]}-live"
    stack = LiveStack(root=root, prefix=prefix, env={}, port=free_port())
    try:
        yield start_stack(stack, REDIS_URL)
    finally:
        stack.teardown()
        delete_prefix(redis_client, prefix)


@pytest.fixture()
def private_redis(tmp_path, request) -> Iterator[PrivateRedis]:
    """A redis-server of this test's own on a free port (it may be stopped and restarted); ``request.param``:
    True for append-only persistence, False for none."""
    server = PrivateRedis(tmp_path / "redis", appendonly=bool(getattr(request, "param", False)))
    server.start()
    try:
        yield server
    finally:
        server.kill()


@pytest.fixture()
def private_live(tmp_path, private_redis) -> Iterator[LiveStack]:
    """A live stack of this test's own against ``private_redis``."""
    root = tmp_path / "live"
    root.mkdir()
    stack = LiveStack(root=root, prefix="dptest-private", env={}, port=free_port(), redis=private_redis)
    try:
        yield start_stack(stack, private_redis.url)
    finally:
        stack.teardown()


# ---------------------------------------------------------------- object store (workers on many hosts)


@pytest.fixture(scope="session")
def object_server(tmp_path_factory):
    """A real S3 server (SeaweedFS ``weed server -s3``, tests/service/object_server.py) on free local ports."""
    from object_server import start_object_server

    server = start_object_server(tmp_path_factory.mktemp("object-store"))
    yield server
    server.stop()


HOSTS = {"cpu-box": "cpu,surveys", "train-a": "gpu", "train-b": "gpu"}  # worker name -> the queues it consumes
HOSTS_BUCKET = "dualphys-test"


@pytest.fixture()
def hosts(tmp_path, redis_client, object_server) -> Iterator[LiveStack]:
    """The API and one Celery worker per ``HOSTS`` entry, each with its own data folder (nothing shared but Redis
    and the object store), ``train_queue=gpu``, with the live stacks' short timings (``live_env``). The numba
    kernels are compiled into their cache once first, so the three workers do not each compile them (raster_bwd,
    never cached, compiles in every process: docs/DECISIONS.md, "Rendering engine")."""
    subprocess.run([sys.executable, "-m", "cli.main", "warmup"], cwd=REPO, check=True, capture_output=True,
                   timeout=300)
    prefix = f"dptest-{uuid.uuid4().hex[:8]}-hosts"
    stack = LiveStack(root=tmp_path, prefix=prefix, env={}, port=free_port())
    for d in (stack.data_dir, stack.survey_root, stack.api_tmp):
        d.mkdir()
    # the API's own folder is live_env's data_dir; each worker gets another below
    stack.env = {**live_env(stack, REDIS_URL), "DUALPHYS_TRAIN_QUEUE": "gpu", **object_server.env(HOSTS_BUCKET, prefix)}
    try:
        stack.start_api()
        for name, queues in HOSTS.items():
            start_host(stack, name, queues)
        yield stack
    finally:
        stack.teardown()
        delete_prefix(redis_client, prefix)


def start_host(stack: LiveStack, name: str, queues: str) -> Proc:
    folder = stack.root / f"{name}-data"
    folder.mkdir(exist_ok=True)
    env = {**stack.env, "DUALPHYS_DATA_DIR": str(folder)}
    proc = stack._spawn(name, [sys.executable, "-m", "celery", "-A", "worker.app", "worker", "--pool=prefork",
                               "--concurrency=1", "-Q", queues, "--loglevel=INFO", "--without-gossip",
                               "--without-mingle", "--without-heartbeat", "-n", f"{name}@%h"], env)
    wait_for(f"{name} to be ready", lambda: stack._ready(proc), timeout=60)
    return proc
