"""One job = the stages in order, on a job folder. The same functions run from the CLI, a Celery task and tests.

The job folder's paths are in :mod:`pipeline.job.layout`; the stages in :mod:`pipeline.job.table`.

A stage's config hash covers its own options and the hashes of the stages before it, so changing an upstream
option re-runs everything downstream and nothing else. Every stage takes (job_dir, options, context) and
returns a JSON-able result; :func:`run_job` skips stages whose marker matches.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.markers import config_hash, read_marker, run_marked
from pipeline.job.options import JobCancelled, JobOptions, StageContext
from pipeline.job.table import STAGES, stage

log = logging.getLogger(__name__)


def stage_config(opts: JobOptions, name: str) -> dict:
    """What a stage's marker hash covers: its options and the chain of the stages before it."""
    i = STAGES.index(name)
    upstream = config_hash(stage_config(opts, STAGES[i - 1])) if i else None
    return {"stage": name, "upstream": upstream, **{k: getattr(opts, k) for k in stage(name).options}}


def run_stage(job: Path, name: str, opts: JobOptions, ctx: StageContext | None = None) -> tuple[dict, bool]:
    """Run one stage unless its marker matches; returns (result, skipped)."""
    ctx = ctx or StageContext()
    if ctx.should_cancel():
        raise JobCancelled(f"cancelled before {name}")
    ctx.on_progress(name, 0.0, "started")
    result, skipped = run_marked(job, name, stage_config(opts, name), lambda: stage(name).load()(job, opts, ctx))
    ctx.on_progress(name, 1.0, "skipped (already done)" if skipped else "done")
    return result, skipped


def run_job(job: str | Path, opts: JobOptions, ctx: StageContext | None = None,
            stages: tuple[str, ...] = STAGES) -> dict[str, dict]:
    """Run the stages in order in ``job``; finished ones (matching markers) are skipped."""
    job = Path(job)
    job.mkdir(parents=True, exist_ok=True)
    JobLayout(job).options.write_text(json.dumps(opts.to_json(), indent=2))
    results = {}
    for name in stages:
        results[name], skipped = run_stage(job, name, opts, ctx)
        log.info("stage %s %s", name, "skipped (marker matches)" if skipped else "done")
    return results


def first_unfinished(job: str | Path, opts: JobOptions) -> str | None:
    """The stage a retry would start from (None when all are done)."""
    for name in STAGES:
        m = read_marker(job, name)
        if m is None or m.get("config_hash") != config_hash(stage_config(opts, name)):
            return name
    return None
