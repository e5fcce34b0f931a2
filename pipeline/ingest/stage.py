"""The ingest stage: the job's source (archive or folder) -> the job's images (``JobLayout.images``)."""

from __future__ import annotations

from pathlib import Path

from pipeline.ingest.intake import ingest
from pipeline.job.options import JobCancelled, JobOptions, StageContext


def stage_ingest(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """Videos can take minutes to decode: their progress is reported, and a cancel stops them."""
    def tick(fraction: float, message: str) -> None:
        if ctx.should_cancel():
            raise JobCancelled(f"cancelled during ingest ({message})")
        ctx.on_progress("ingest", fraction, message)

    return ingest(opts.source, job, ctx.ingest, tick).to_json()
