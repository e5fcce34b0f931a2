"""What the API returns."""

from __future__ import annotations

from pydantic import BaseModel, Field

from service.jobs.manifest import Manifest
from service.jobs.ops import StatusView, pipeline_stages


class ErrorDetail(BaseModel):
    code: str = Field(..., description="stable, machine-readable (docs/SERVICE.md lists them)")
    message: str


class ErrorOut(BaseModel):
    error: ErrorDetail


class AttemptOut(BaseModel):
    attempt: int
    started_at: float | None
    ended_at: float | None
    outcome: str = Field(..., description="done | failed | cancelled | worker_lost")
    last: str = Field("", description="the attempt's last progress message")


class StageOut(BaseModel):
    name: str
    status: str
    started_at: float | None
    finished_at: float | None
    seconds: float | None
    attempts: int
    skipped: bool
    history: list[AttemptOut] = Field(default_factory=list, description="every attempt that ended or was lost")


class JobErrorOut(BaseModel):
    stage: str | None
    code: str
    message: str


LIST_CAP = 100  # status stays small however broken an upload was; ingest.json (an artifact) has every entry


class IngestOut(BaseModel):
    images: int
    skipped: list[dict] = Field(default_factory=list, description="files that looked like images but did not "
                                                                  f"decode (first {LIST_CAP})")
    skipped_count: int = 0
    ignored: list[dict] = Field(default_factory=list, description=f"files that are not images (first {LIST_CAP})")
    ignored_count: int = 0
    videos: list[dict] = Field(default_factory=list, description=(
        f"video files (first {LIST_CAP}): file, frames decoded, keyframes kept, error; every keyframe with its "
        "reasons is in the ingest stage's JSON artifact"))


def video_summaries(videos: list[dict]) -> list[dict]:
    return [{"file": v.get("file"), "frames_decoded": v.get("frames_decoded", 0), "kept": len(v.get("kept", [])),
             "error": v.get("error")} for v in videos[:LIST_CAP]]


class RunOut(BaseModel):
    run_id: str
    from_stage: str | None
    queued_at: float
    finished_at: float | None
    outcome: str | None


class WebhookOut(BaseModel):
    id: str = Field(..., description="delivery id, also the body's delivery_id and the X-Dualphys-Delivery header")
    event: str = Field(..., description="job.done | job.failed | job.cancelled")
    run_id: str
    state: str
    status: str = Field(..., description="pending | delivered | given_up")
    attempts: int
    last_status_code: int | None = Field(None, description="the receiver's HTTP status at the last attempt")
    last_error: str | None = None
    created_at: float
    last_attempt_at: float | None = None
    finished_at: float | None = Field(None, description="when it was delivered or given up")


class JobOut(BaseModel):
    id: str
    state: str = Field(..., description="queued | running | cancelling | done | failed | cancelled")
    worker_lost: bool = Field(False, description="the running stage's runner is gone (its worker's heartbeat "
                                                 "says so); the stage is taken over or re-queued (the message "
                                                 "says from where it resumes)")
    stage: str | None = Field(None, description="the stage running now (or last run)")
    progress: float = Field(..., ge=0, le=100, description="0-100, never decreases")
    message: str
    created_at: float
    updated_at: float
    options: dict
    source: dict
    survey_id: str | None
    stages: list[StageOut]
    error: JobErrorOut | None
    ingest: IngestOut | None
    runs: list[RunOut]
    completed_runs: int
    callback_url: str | None = None
    webhooks: list[WebhookOut] = Field(default_factory=list, description="one event per run that ended")

    @classmethod
    def from_view(cls, v: StatusView) -> JobOut:
        m: Manifest = v.manifest
        names = list(pipeline_stages()) + [s for s in m.stages if s not in pipeline_stages()]
        stages = [StageOut(name=s, **m.stage(s).model_dump()) for s in names]
        source = {k: val for k, val in m.source.items() if k != "path"}
        ingest = None
        if m.ingest is not None:
            skipped, ignored = m.ingest.get("skipped", []), m.ingest.get("ignored", [])
            ingest = IngestOut(images=len(m.ingest.get("images", [])), skipped=skipped[:LIST_CAP],
                               skipped_count=len(skipped), ignored=ignored[:LIST_CAP], ignored_count=len(ignored),
                               videos=video_summaries(m.ingest.get("videos", [])))
        return cls(id=m.id, state=v.state, worker_lost=v.worker_lost, stage=v.stage, progress=v.progress,
                   message=v.message,
                   created_at=m.created_at, updated_at=m.updated_at,
                   options={k: val for k, val in m.options.items() if k != "source"}, source=source,
                   survey_id=m.survey_id, stages=stages, error=JobErrorOut(**m.error.model_dump()) if m.error else None,
                   ingest=ingest, runs=[RunOut(**r.model_dump()) for r in m.runs], completed_runs=m.completed_runs,
                   callback_url=m.callback_url,
                   webhooks=[WebhookOut(**d.model_dump(exclude={"body", "url"})) for d in m.webhooks])


class JobList(BaseModel):
    jobs: list[JobOut]
    total: int
    offset: int
    limit: int
    next_offset: int | None


class LogOut(BaseModel):
    offset: int
    next_offset: int = Field(..., description="pass as ?offset= to get what was written since")
    size: int
    text: str


class ArtifactOut(BaseModel):
    path: str
    size: int
    sha256: str
    media_type: str
    url: str


class ArtifactList(BaseModel):
    job_id: str
    artifacts: list[ArtifactOut]


class SubmittedSetOut(BaseModel):
    set_hash: str
    name: str
    images: int
    job_id: str
    submitted_at: float


class SurveyOut(BaseModel):
    id: str
    name: str
    path: str
    interval_s: float
    options: dict
    callback_url: str | None = None
    origin: str = Field(..., description="api | config")
    created_at: float
    last_scan_at: float | None
    scans: int
    last_error: str | None = Field(..., description="why the last scan submitted nothing (folder replaced by a "
                                                    "link, outside the roots, claimed by another owner ...)")
    last_error_code: str | None = None
    waiting: list[dict] = Field(default_factory=list, description="sets the last scan found but did not submit, "
                                                                  "with the reason (too few images, settling)")
    sets: list[SubmittedSetOut]


class SurveyList(BaseModel):
    surveys: list[SurveyOut]


class ScanQueued(BaseModel):
    survey_id: str
    task_id: str


class HealthOut(BaseModel):
    status: str


class ReadyOut(BaseModel):
    status: str = Field(..., description="ready | not_ready")
    redis: bool
    data_dir_writable: bool
    disk_free_bytes: int
    min_free_bytes: int
    workers: dict[str, int] = Field(default_factory=dict, description="live workers per queue (cpu, gpu, surveys), "
                                                                      "from their Redis heartbeats")
    workers_ok: bool = Field(False, description="some worker consumes the cpu queue (stages) and the surveys queue "
                                                "(scans), and the gpu queue when training is routed there")
    object_store: bool | None = Field(None, description="the object store answers (null: none configured, the "
                                                        "data folder is the store)")
    warnings: list[str] = Field(default_factory=list)
