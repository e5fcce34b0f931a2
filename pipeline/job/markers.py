"""The stage contract: a stage writes its outputs, then a completion marker holding its config hash; a
stage whose marker matches is skipped, so a crashed, redelivered or retried job resumes where it stopped.

Markers live in the job folder at :meth:`pipeline.job.layout.JobLayout.marker`. Writes are atomic (temp file +
rename), so a reader never sees half a marker and a killed process leaves either the old state or the new one.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.job.layout import JobLayout


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` via a temp file in the same folder and an atomic rename (fsynced)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str))


def config_hash(obj: Any) -> str:
    """A stable short hash of a JSON-able config (key order does not matter)."""
    blob = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def marker_path(job_dir: str | Path, stage: str) -> Path:
    return JobLayout(job_dir).marker(stage)


def read_marker(job_dir: str | Path, stage: str) -> dict | None:
    p = marker_path(job_dir, stage)
    try:
        return json.loads(p.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def clear_marker(job_dir: str | Path, stage: str) -> None:
    marker_path(job_dir, stage).unlink(missing_ok=True)


def run_marked(job_dir: str | Path, stage: str, cfg: Any, fn: Callable[[], dict]) -> tuple[dict, bool]:
    """Run ``fn`` unless the stage's marker matches ``cfg``; returns (result, skipped).

    ``fn`` returns a JSON-able result that is stored in the marker and handed back on later skips.
    """
    chash = config_hash(cfg)
    m = read_marker(job_dir, stage)
    if m is not None and m.get("config_hash") == chash:
        return m.get("result", {}), True
    clear_marker(job_dir, stage)
    t0 = time.time()
    result = fn()
    atomic_write_json(marker_path(job_dir, stage), {
        "stage": stage, "config_hash": chash, "config": cfg, "result": result,
        "started_at": t0, "finished_at": time.time(), "seconds": round(time.time() - t0, 3),
    })
    return result, False
