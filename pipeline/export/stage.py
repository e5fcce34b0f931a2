"""The export stage: the reconstruction PLY, the per-view images and the report -> ``JobLayout.output``."""

from __future__ import annotations

import json
import time
from pathlib import Path

from pipeline.export.cameras import export_cameras, viewer_display
from pipeline.export.report import write_report
from pipeline.export.views import export_views
from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions, StageContext
from pipeline.splat.ply import export_ply
from pipeline.splat.spz import export_spz
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.model import training_views


def stage_export(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """reconstruction.ply plus the model's renders (``renders/``: restored/, with_water/, attenuation/,
    backscatter/, depth/) of every registered view (training and held-out alike), at the resolution training
    used; then report.json and report.html (``pipeline.export.report``), which read those files and the
    restore stage's."""
    t0 = time.perf_counter()
    layout = JobLayout(job)
    state = load_checkpoint(layout.checkpoint)
    out = layout.output
    out.mkdir(parents=True, exist_ok=True)
    data = export_ply(state["gaussians"], layout.ply)
    spz = export_spz(state["gaussians"], layout.spz)  # the same Gaussians, compressed (docs/SERVICE.md)
    views = training_views(job, state)
    counts = export_views(state, views, layout.renders)
    n_cameras = export_cameras(views, state["gaussians"]["means"].detach().cpu().numpy(), layout.cameras,
                               viewer_display(state, json.loads(layout.train_result.read_text()).get("medium")))
    reports = write_report(job, out, export_s=time.perf_counter() - t0)
    return {layout.ply.name: len(data), layout.spz.name: len(spz), layout.cameras.name: n_cameras, **counts,
            "report": [p.name for p in reports]}
