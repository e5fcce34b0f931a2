"""The classify stage: the water type of a few of the job's images -> the job's water decision
(``JobLayout.classify``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TypeVar

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from pipeline.job.options import JobOptions, StageContext
from pipeline.scene.images import read_image
from pipeline.water import classify

T = TypeVar("T")

CLASSIFY_IMAGES = 8  # images (evenly spaced by name) the water classifier averages over


def classify_pick(items: Sequence[T]) -> list[T]:
    """The :data:`CLASSIFY_IMAGES` of ``items`` (in name order) the classifier looks at: evenly spaced."""
    return list(items[:: max(1, len(items) // CLASSIFY_IMAGES)][:CLASSIFY_IMAGES])


def stage_classify(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    layout = JobLayout(job)
    names = sorted(p for p in layout.images.iterdir() if p.is_file())
    decision = classify([read_image(p) for p in classify_pick(names)]).to_dict()
    atomic_write_json(layout.classify, decision)
    return decision
