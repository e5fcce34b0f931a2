"""``dualphys serve``: the API, one Celery worker and beat on this machine, against a Redis on localhost.

The worker and beat run as child processes (Celery's prefork pool needs a process of its own, and the API must
not share a process with torch); the API runs in this process under uvicorn. Ctrl-C or SIGTERM (what
``docker stop``, systemd and process managers send) stops all three: the children get SIGTERM (Celery's warm
shutdown) and, after ``STOP_GRACE_S``, SIGKILL.

The children are supervised (:class:`Supervisor`): one that exits is reaped, its process group killed (a Celery
worker's pool children would otherwise go on running a stage nobody owns) and started again after a backoff
(1 s, doubling to 30 s); after ``MAX_RESTARTS`` restarts of one child within ``RESTART_WINDOW_S`` serve stops
and exits non-zero saying which child kept dying. ``/ready`` is 503 while a queue has no live worker
(``require_workers``), so a dead worker is never behind a healthy API.

Settings compose as in a deployment: every ``DUALPHYS_*`` variable applies (docs/SERVICE.md), and an argument
given here (a ``dualphys serve`` flag) wins over its variable. Without a data folder, Redis URL or API keys
from either, the defaults are ``./dualphys-data``, ``redis://127.0.0.1:6379/0`` and one key for owner ``local``
written to ``<data_dir>/api-key``.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import redis
import uvicorn

from .app import create_app
from .core.settings import load_settings

log = logging.getLogger(__name__)

KEY_FILE = "api-key"
DEFAULT_DATA_DIR = "dualphys-data"
DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/0"
STOP_GRACE_S = 20.0
MAX_RESTARTS = 5
RESTART_WINDOW_S = 600.0
BACKOFF_S, BACKOFF_MAX_S = 1.0, 30.0
POLL_S = 0.5


@dataclass(frozen=True)
class ServeConfig:
    data_dir: Path
    redis_url: str
    api_keys: dict[str, str] | None  # None: the generated key of owner ``local``


def serve_config(data_dir: str | os.PathLike[str] | None = None, redis_url: str | None = None,
                 api_keys: dict[str, str] | None = None, api_keys_file: str | os.PathLike[str] | None = None,
                 environ: Mapping[str, str] | None = None) -> ServeConfig:
    """Arguments first, then ``DUALPHYS_DATA_DIR`` / ``DUALPHYS_REDIS_URL`` / ``DUALPHYS_API_KEYS``, then the
    defaults. ``api_keys_file`` is a JSON file ``{"<key>": "<owner>"}`` (keys stay out of the process list).
    Raises ValueError for keys that are not such a mapping."""
    env = os.environ if environ is None else environ
    if api_keys is None and api_keys_file is not None:
        api_keys = _keys_from_json(Path(api_keys_file).read_text(), f"--api-keys-file {api_keys_file}")
    if api_keys is None and env.get("DUALPHYS_API_KEYS"):
        api_keys = _keys_from_json(env["DUALPHYS_API_KEYS"], "DUALPHYS_API_KEYS")
    return ServeConfig(data_dir=Path(data_dir or env.get("DUALPHYS_DATA_DIR") or DEFAULT_DATA_DIR).resolve(),
                       redis_url=redis_url or env.get("DUALPHYS_REDIS_URL") or DEFAULT_REDIS_URL,
                       api_keys=api_keys)


def _keys_from_json(text: str, where: str) -> dict[str, str]:
    try:
        keys = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"{where}: not JSON ({e.msg})") from None
    if not isinstance(keys, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in keys.items()):
        raise ValueError(f'{where}: expected a JSON object {{"<key>": "<owner>", ...}}')
    return keys


def local_api_key(data_dir: Path) -> str:
    """The key of the embedded server's single owner ``local``: ``<data_dir>/api-key``, made on first use."""
    path = data_dir / KEY_FILE
    if not path.exists():
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_urlsafe(32) + "\n")
    return path.read_text().strip()


def serve(host: str = "127.0.0.1", port: int = 8000, data_dir: str | os.PathLike[str] | None = None, *,
          redis_url: str | None = None, api_keys: dict[str, str] | None = None,
          api_keys_file: str | os.PathLike[str] | None = None, worker_concurrency: int = 1, beat: bool = True,
          log_level: str = "info") -> None:
    """Run the service locally until interrupted (Ctrl-C or SIGTERM).

    ``api_keys`` maps key -> owner (or ``api_keys_file``, the same as JSON); arguments left None come from the
    environment, then the defaults (module docstring, :func:`serve_config`). Raises RuntimeError when Redis
    does not answer at the Redis URL.
    """
    cfg = serve_config(data_dir, redis_url, api_keys, api_keys_file)
    data, redis_url, api_keys = cfg.data_dir, cfg.redis_url, cfg.api_keys
    data.mkdir(parents=True, exist_ok=True)
    if api_keys is None:
        api_keys = {local_api_key(data): "local"}
        log.warning("API key for owner 'local' is in %s", data / KEY_FILE)
    try:
        redis.Redis.from_url(redis_url, socket_connect_timeout=3).ping()
    except redis.RedisError as e:
        raise RuntimeError(f"no Redis answers at {redis_url} ({e}); start one, e.g. "
                           "`redis-server --bind 127.0.0.1 --port 6379 --daemonize yes`") from e

    env = {**os.environ, "DUALPHYS_API_KEYS": json.dumps(api_keys), "DUALPHYS_DATA_DIR": str(data),
           "DUALPHYS_REDIS_URL": redis_url, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    env["DUALPHYS_REQUIRE_WORKERS"] = "true"  # /ready is 503 while a queue has no live worker
    settings = load_settings(api_keys=api_keys, data_dir=data, redis_url=redis_url, require_workers=True)
    celery = [sys.executable, "-m", "celery", "-A", "worker.app"]
    queues = "cpu,surveys" + (",gpu" if settings.train_queue == "gpu" else "")
    commands = [("worker", celery + ["worker", "--pool=prefork", f"--concurrency={worker_concurrency}", "-Q", queues,
                          f"--loglevel={log_level.upper()}", "--without-gossip", "--without-mingle"])]
    if beat:
        commands.append(("beat", celery + ["beat", "--schedule", str(data / "beat-schedule"),
                                           f"--loglevel={log_level.upper()}"]))
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host=host, port=port, log_level=log_level))
    supervisor = Supervisor([Child(name, cmd) for name, cmd in commands], env, on_give_up=server)
    # uvicorn handles SIGTERM itself, then re-raises it with the handler it found: make that handler unwind
    # this function (as Ctrl-C does), so the worker and beat are stopped instead of orphaned.
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        supervisor.start()
        log.info("worker%s started; API on http://%s:%d (docs at /docs)", " and beat" if beat else "", host, port)
        try:
            server.run()
        except KeyboardInterrupt:  # Ctrl-C: stop the children below, as SIGTERM does
            pass
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the clean-up short
        supervisor.stop()
        log.info("stopping the worker%s", " and beat" if beat else "")
        stop_children([c.popen for c in supervisor.children if c.popen is not None])
        signal.signal(signal.SIGTERM, previous)
    if supervisor.gave_up:
        raise RuntimeError(supervisor.gave_up)
    if not server.started:
        raise RuntimeError(f"the API did not start on {host}:{port} (see the log above)")


@dataclass
class Child:
    name: str
    cmd: list[str]
    popen: subprocess.Popen | None = None
    restarts: list[float] = field(default_factory=list)  # monotonic times of the restarts


class Supervisor:
    """Starts the children, and restarts one that exits (its process group killed first) after a doubling
    backoff; gives up after ``max_restarts`` restarts of one child within ``window_s``: ``gave_up`` says why and
    ``on_give_up.should_exit`` (the uvicorn server) is set, so serve stops and exits non-zero."""

    def __init__(self, children: list[Child], env: Mapping[str, str], on_give_up=None,
                 max_restarts: int = MAX_RESTARTS, window_s: float = RESTART_WINDOW_S):
        self.children, self.env, self.on_give_up = children, dict(env), on_give_up
        self.max_restarts, self.window_s = max_restarts, window_s
        self.gave_up: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="serve-supervisor", daemon=True)

    def start(self) -> None:
        for c in self.children:
            self._spawn(c)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10)

    def _spawn(self, c: Child) -> None:
        c.popen = subprocess.Popen(c.cmd, env=self.env, start_new_session=True)
        log.info("started %s (pid %d)", c.name, c.popen.pid)

    def _watch(self) -> None:
        while not self._stop.wait(POLL_S):
            for c in self.children:
                if c.popen is None or c.popen.poll() is None:
                    continue
                if not self._restart(c):
                    return

    def _restart(self, c: Child) -> bool:
        code = c.popen.returncode
        _kill_group(c.popen.pid)  # the dead worker's pool children must not go on running its stage
        now = time.monotonic()
        c.restarts = [t for t in c.restarts if now - t < self.window_s]
        if len(c.restarts) >= self.max_restarts:
            self.gave_up = (f"the {c.name} exited (code {code}) {len(c.restarts) + 1} times within "
                            f"{self.window_s:.0f} s; stopping")
            log.error("%s", self.gave_up)
            if self.on_give_up is not None:
                self.on_give_up.should_exit = True
            return False
        delay = min(BACKOFF_MAX_S, BACKOFF_S * 2 ** len(c.restarts))
        log.error("the %s exited (code %s); restarting it in %.0f s (restart %d of at most %d within %.0f s)",
                  c.name, code, delay, len(c.restarts) + 1, self.max_restarts, self.window_s)
        if self._stop.wait(delay):
            return False
        c.restarts.append(time.monotonic())
        self._spawn(c)
        return True


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def _exit_on_sigterm(signum: int, frame) -> None:
    raise SystemExit(128 + signum)


def stop_children(children: list[subprocess.Popen], grace_s: float = STOP_GRACE_S) -> None:
    """SIGTERM each child's process group (a warm Celery shutdown), SIGKILL what is left after ``grace_s``."""
    for p in children:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    for p in children:
        try:
            p.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(timeout=10)
