"""Container health checks: ``python -m worker.healthcheck`` exits 0 when Redis answers and the data folder
is writable (the beat container's check; the worker's uses ``celery inspect ping``, the API's ``/ready``)."""

from __future__ import annotations

import logging
import sys
import tempfile

import redis

from service.core.settings import load_settings

log = logging.getLogger(__name__)


def healthy() -> bool:
    settings = load_settings()
    try:
        redis.Redis.from_url(settings.redis_url, socket_connect_timeout=3, socket_timeout=3).ping()
        with tempfile.TemporaryFile(dir=settings.data_dir):
            pass
    except (redis.RedisError, OSError) as e:
        log.error("unhealthy: %s", e)
        return False
    return True


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    sys.exit(0 if healthy() else 1)
