"""The job manifest (``JobLayout.manifest`` in the job folder): the truth about a job, written atomically by
whoever changes it (the API on create/cancel/retry, the worker on every stage transition and, throttled, on
progress).

States: ``queued`` -> ``running`` -> ``done`` | ``failed`` | ``cancelled``; ``failed`` and ``cancelled`` go
back to ``queued`` on retry. The stage list comes from ``pipeline.job.runner.STAGES`` when read, so stages added to
the pipeline later appear in old manifests as ``pending``.
"""

from __future__ import annotations

import time
from typing import Literal

from pydantic import BaseModel, Field

from pipeline.job.table import BY_NAME

JobState = Literal["queued", "running", "done", "failed", "cancelled"]
StageStatus = Literal["pending", "running", "done", "failed", "cancelled"]
TERMINAL_STATES: frozenset[str] = frozenset({"done", "failed", "cancelled"})
SCHEMA_VERSION = 1

# A stage an old manifest names that the pipeline no longer has weighs this much of the progress bar.
DEFAULT_STAGE_WEIGHT = 5.0


class AttemptRecord(BaseModel):
    """One runner's go at a stage. ``outcome`` ``worker_lost``: its worker died; ``last`` is the last progress
    message it reported (e.g. "iteration 235/600")."""

    attempt: int
    started_at: float | None
    ended_at: float | None = None
    outcome: str  # done | failed | cancelled | worker_lost
    last: str = ""


class StageRecord(BaseModel):
    status: StageStatus = "pending"
    started_at: float | None = None
    finished_at: float | None = None
    seconds: float | None = None  # wall time of the attempt that finished it
    attempts: int = 0  # how many times a runner started it (a worker crash shows as attempts > 1)
    skipped: bool = False  # its completion marker already matched (redelivery, retry)
    history: list[AttemptRecord] = Field(default_factory=list)  # every finished or lost attempt, in order


class JobError(BaseModel):
    stage: str | None
    code: str
    message: str


class RunRecord(BaseModel):
    run_id: str
    from_stage: str | None
    queued_at: float
    finished_at: float | None = None
    outcome: str | None = None  # done | failed | cancelled


class WebhookDelivery(BaseModel):
    """One event for the job's callback URL (service.webhooks): planned in the write that ends a run, then sent by
    the ``dualphys.deliver_webhook`` task; every attempt updates it. ``body`` is the exact JSON every attempt
    sends (the signature covers it), kept out of the status view."""

    id: str  # the delivery id, also in the body and the X-Dualphys-Delivery header (receivers deduplicate on it)
    event: str  # job.done | job.failed | job.cancelled
    run_id: str
    state: str
    url: str
    created_at: float
    body: str
    status: Literal["pending", "delivered", "given_up"] = "pending"
    attempts: int = 0
    last_status_code: int | None = None  # the receiver's HTTP status at the last attempt (None: no answer)
    last_error: str | None = None  # why the last attempt failed (HTTP status or connection error)
    last_attempt_at: float | None = None
    finished_at: float | None = None  # delivered or given up


class Manifest(BaseModel):
    schema_version: int = SCHEMA_VERSION
    id: str
    owner: str
    created_at: float
    updated_at: float
    state: JobState = "queued"
    cancel_requested: bool = False
    run_id: str
    runs: list[RunRecord] = Field(default_factory=list)
    completed_runs: int = 0  # how many times the last stage finished; exactly 1 for a finished job
    options: dict
    source: dict  # {"kind": "upload", "filename", "bytes", "sha256"} | {"kind": "survey", "survey_id", "set", ...}
    survey_id: str | None = None
    stages: dict[str, StageRecord] = Field(default_factory=dict)
    current_stage: str | None = None
    progress: float = 0.0
    message: str = ""
    error: JobError | None = None
    dispatched: list[str] = Field(default_factory=list)  # stages of the current run whose task was sent
    ingest: dict | None = None  # images, skipped (undecodable, listed), ignored (non-images)
    callback_url: str | None = None  # where each run's end is announced (service.webhooks); None: nowhere
    webhooks: list[WebhookDelivery] = Field(default_factory=list)  # one per run that ended, in order

    def stage(self, name: str) -> StageRecord:
        return self.stages.setdefault(name, StageRecord())

    def next_stage(self, stages: tuple[str, ...]) -> str | None:
        """The first of ``stages`` (the pipeline's, in order) this manifest does not record as done: what the
        job runs next. Normally the one after the stage that just finished; if a new version of the pipeline
        inserted a stage while the job ran, that one runs too instead of leaving a hole in a finished job.
        (What a *retry* starts from is the disk's word instead: ``pipeline.job.runner.first_unfinished``, which
        checks each stage's completion marker against the job's options.)"""
        return next((s for s in stages if self.stage(s).status != "done"), None)

    def touch(self) -> None:
        self.updated_at = time.time()

    @property
    def current_run(self) -> RunRecord | None:
        return next((r for r in reversed(self.runs) if r.run_id == self.run_id), None)


def stage_weights(stages: tuple[str, ...]) -> dict[str, float]:
    """Each stage's share of the 0-100 progress bar: its weight in the stage table (``pipeline.job.table``),
    normalised over ``stages``."""
    w = {s: BY_NAME[s].weight if s in BY_NAME else DEFAULT_STAGE_WEIGHT for s in stages}
    total = sum(w.values()) or 1.0
    return {s: 100.0 * v / total for s, v in w.items()}


def overall_progress(stages: tuple[str, ...], done: set[str], stage: str | None, fraction: float) -> float:
    """0-100: the weights of the finished stages plus the running stage's weight times its fraction."""
    w = stage_weights(stages)
    p = sum(w[s] for s in stages if s in done)
    if stage is not None and stage not in done and stage in w:
        p += w[stage] * min(1.0, max(0.0, fraction))
    return round(min(100.0, p), 3)
