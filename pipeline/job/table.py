"""The stage table: each stage of a job declared once.

Everything that needs to know the stages derives from :data:`STAGE_TABLE`: the runner (order, functions, the
options that key each completion marker), the service's progress (weights), its dispatcher (queues) and its
artifact listing (what each stage makes final). Functions are named as ``module:function`` and imported when
the stage runs, so this module, like all of ``pipeline.job``, imports no torch.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pipeline.job.options import JobOptions, StageContext

StageFunction = Callable[[Path, JobOptions, StageContext], dict]


@dataclass(frozen=True)
class Stage:
    name: str
    function: str  # "module:function" taking (job_dir, options, context) and returning a JSON-able result
    options: tuple[str, ...]  # the job options its completion marker depends on (beyond the stages before it)
    weight: float  # its share of the job's progress bar (relative; the service normalises)
    queue: Literal["cpu", "train"]  # "train": the deployment's training queue (cpu or gpu), else the cpu queue
    publishes: tuple[str, ...] = ()  # JobLayout attributes (files or folders) its marker makes downloadable

    def load(self) -> StageFunction:
        module, name = self.function.split(":")
        return getattr(importlib.import_module(module), name)


STAGE_TABLE: tuple[Stage, ...] = (
    Stage("ingest", "pipeline.ingest.stage:stage_ingest", ("source",), 3, "cpu", ("ingest",)),
    Stage("sfm", "pipeline.sfm.stage:stage_sfm", ("seed",), 12, "cpu"),
    Stage("classify", "pipeline.water.stage:stage_classify", (), 2, "cpu"),
    Stage("train", "pipeline.train.stage:stage_train",
          ("preset", "mode", "max_width", "iterations", "seed", "colour_space"), 70, "train", ("train_result",)),
    Stage("evaluate", "pipeline.evaluate.stage:stage_evaluate", ("ground_truth",), 5, "cpu"),
    Stage("restore", "pipeline.restore.stage:stage_restore", ("restore_format", "max_gain"), 6, "cpu"),
    Stage("survey", "pipeline.survey.stage:stage_survey",
          ("ortho", "ortho_gsd", "telemetry", "scale_bar", "metric_scale"), 6, "cpu", ("survey_result",)),
    Stage("export", "pipeline.export.stage:stage_export", (), 8, "cpu", ("output",)),
)
STAGES: tuple[str, ...] = tuple(s.name for s in STAGE_TABLE)
BY_NAME: dict[str, Stage] = {s.name: s for s in STAGE_TABLE}


def stage(name: str) -> Stage:
    try:
        return BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown stage {name!r}; one of {', '.join(STAGES)}") from None
