"""The classify stage: the water type of a few of the job's images -> the job's water decision
(``JobLayout.classify``)."""

from __future__ import annotations

from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions, StageContext

CLASSIFY_IMAGES = 8  # images (evenly spaced by name) the water classifier averages over


def stage_classify(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    from pipeline.job.markers import atomic_write_json
    from pipeline.scene.images import read_image
    from pipeline.water import classify

    layout = JobLayout(job)
    names = sorted(p for p in layout.images.iterdir() if p.is_file())
    pick = names[:: max(1, len(names) // CLASSIFY_IMAGES)][:CLASSIFY_IMAGES]
    decision = classify([read_image(p) for p in pick]).to_dict()
    atomic_write_json(layout.classify, decision)
    return decision
