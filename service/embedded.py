"""``dualphys serve``: the API, one Celery worker and beat on this machine, against a Redis on localhost.

The worker and beat run as child processes (Celery's prefork pool needs a process of its own, and the API must
not share a process with torch); the API runs in this process under uvicorn. Ctrl-C or SIGTERM (what
``docker stop``, systemd and process managers send) stops all three: the children get SIGTERM (Celery's warm
shutdown) and, after ``STOP_GRACE_S``, SIGKILL.

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
from collections.abc import Mapping
from dataclasses import dataclass
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
    settings = load_settings(api_keys=api_keys, data_dir=data, redis_url=redis_url)
    celery = [sys.executable, "-m", "celery", "-A", "worker.app"]
    queues = "cpu,surveys" + (",gpu" if settings.train_queue == "gpu" else "")
    commands = [celery + ["worker", "--pool=prefork", f"--concurrency={worker_concurrency}", "-Q", queues,
                          f"--loglevel={log_level.upper()}", "--without-gossip", "--without-mingle"]]
    if beat:
        commands.append(celery + ["beat", "--schedule", str(data / "beat-schedule"), f"--loglevel={log_level.upper()}"])
    children: list[subprocess.Popen] = []
    # uvicorn handles SIGTERM itself, then re-raises it with the handler it found: make that handler unwind
    # this function (as Ctrl-C does), so the worker and beat are stopped instead of orphaned.
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        for cmd in commands:
            children.append(subprocess.Popen(cmd, env=env, start_new_session=True))
        log.info("worker%s started; API on http://%s:%d (docs at /docs)", " and beat" if beat else "", host, port)
        uvicorn.run(create_app(settings), host=host, port=port, log_level=log_level)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the clean-up short
        log.info("stopping the worker%s", " and beat" if beat else "")
        stop_children(children)
        signal.signal(signal.SIGTERM, previous)


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
