"""What clients send."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from service.jobs.options import JobOptionsIn
from service.surveys.registry import SurveyOptions


class JobCreateOptions(JobOptionsIn):
    """Options of a new job: multipart form fields beside the archive, or query parameters with a raw body."""

    callback_url: str | None = Field(None, description="http(s) URL on one of the server's allowed webhook hosts: "
                                                       "each run's end (done, failed, cancelled) is POSTed there as "
                                                       "a signed JSON event (docs/SERVICE.md, Webhooks)")


class SurveyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str = Field(..., description="a folder under one of the server's survey roots")
    interval_s: float = Field(..., gt=0, description="seconds between scans")
    name: str | None = Field(None, max_length=200)
    options: SurveyOptions = Field(default_factory=SurveyOptions, description="job options for this survey's sets")
    callback_url: str | None = Field(None, description="every job of this survey POSTs its run ends here, as a "
                                                       "job's callback_url does")
