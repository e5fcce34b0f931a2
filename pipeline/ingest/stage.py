"""The ingest stage: the job's source (archive or folder) -> the job's images (``JobLayout.images``)."""

from __future__ import annotations

from pathlib import Path

from pipeline.job.options import JobOptions, StageContext


def stage_ingest(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    from pipeline.ingest.intake import ingest

    return ingest(opts.source, job, ctx.ingest).to_json()
