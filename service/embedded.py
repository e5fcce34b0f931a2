"""``dualphys serve``: the API, one Celery worker and beat on this machine, against a Redis on localhost.

The worker and beat run as child processes (Celery's prefork pool needs a process of its own, and the API must
not share a process with torch); the API runs in this process under uvicorn. Ctrl-C stops all three.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import signal
import subprocess
import sys
from pathlib import Path

log = logging.getLogger(__name__)

KEY_FILE = "api-key"


def local_api_key(data_dir: Path) -> str:
    """The key of the embedded server's single owner ``local``: ``<data_dir>/api-key``, made on first use."""
    path = data_dir / KEY_FILE
    if not path.exists():
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_urlsafe(32) + "\n")
    return path.read_text().strip()


def serve(host: str = "127.0.0.1", port: int = 8000, data_dir: str | os.PathLike[str] = "dualphys-data", *,
          redis_url: str = "redis://127.0.0.1:6379/0", api_keys: dict[str, str] | None = None,
          worker_concurrency: int = 1, beat: bool = True, log_level: str = "info") -> None:
    """Run the service locally until interrupted.

    ``api_keys`` maps key -> owner; without it a key for owner ``local`` is created in ``<data_dir>/api-key``.
    Other settings come from ``DUALPHYS_*`` variables as in a deployment (docs/SERVICE.md). Raises
    RuntimeError when Redis does not answer at ``redis_url``.
    """
    import redis
    import uvicorn

    from .app import create_app
    from .settings import load_settings

    data = Path(data_dir).resolve()
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
    try:
        for cmd in commands:
            children.append(subprocess.Popen(cmd, env=env, start_new_session=True))
        log.info("worker%s started; API on http://%s:%d (docs at /docs)", " and beat" if beat else "", host, port)
        uvicorn.run(create_app(settings), host=host, port=port, log_level=log_level)
    finally:
        stop_children(children)


def stop_children(children: list[subprocess.Popen], grace_s: float = 20.0) -> None:
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
