"""The evaluate stage: held-out scores, restoration against ground truth, timings -> ``JobLayout.evaluate``."""

from __future__ import annotations

from pathlib import Path

from pipeline.evaluate.evaluation import evaluate_job
from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from pipeline.job.options import JobOptions, StageContext
from pipeline.job.table import STAGES
from pipeline.synth.ground_truth import find_ground_truth


def stage_evaluate(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """Held-out scores, restoration against ground truth where it exists, timings, the speed-vs-error curve
    (``pipeline.evaluate.evaluation``) -> ``JobLayout.evaluate``."""
    gt = find_ground_truth(opts.source, opts.ground_truth)
    res = evaluate_job(job, gt, stages=STAGES[:STAGES.index("evaluate")])
    atomic_write_json(JobLayout(job).evaluate, res)
    return res
