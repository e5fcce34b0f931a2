"""Idempotency keys on disk: ``<data>/idempotency/<owner>/<sha256 of the key>.json`` = ``{"job_id", "sha256",
"created_at"}``, written atomically when the job is created.

Redis holds the same mapping for the in-flight part (``pending:<job>`` while the first request uploads) and as a
cache; the file makes the key outlive a Redis that lost its data, so a repeat after such a loss still returns
the first job instead of creating a second one. Records older than ``IDEMPOTENCY_TTL_S`` are ignored (and
removed), as Redis expires its keys.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.job.markers import atomic_write_text
from service.core.coord import IDEMPOTENCY_TTL_S

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IdempotencyRecord:
    job_id: str
    created_at: float


class IdempotencyIndex:
    def __init__(self, root: Path, ttl_s: float = IDEMPOTENCY_TTL_S):
        self.root = Path(root)
        self.ttl_s = ttl_s

    def _path(self, owner: str, key: str) -> Path:
        # owner names are letters, digits, '-', '_' and '.' (service.core.settings); never '..' alone
        if not owner or owner in (".", "..") or "/" in owner:
            raise ValueError(f"unusable owner name {owner!r}")
        return self.root / owner / f"{hashlib.sha256(key.encode()).hexdigest()}.json"

    def lookup(self, owner: str, key: str) -> IdempotencyRecord | None:
        path = self._path(owner, key)
        try:
            data = json.loads(path.read_text())
            rec = IdempotencyRecord(str(data["job_id"]), float(data["created_at"]))
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.error("unreadable idempotency record %s: %s", path, e)
            return None
        if time.time() - rec.created_at > self.ttl_s:
            path.unlink(missing_ok=True)
            return None
        return rec

    def record(self, owner: str, key: str, job_id: str) -> None:
        path = self._path(owner, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps({"job_id": job_id, "created_at": time.time()}))
