"""What clients send."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from service.surveys import SurveyOptions


def _presets() -> list[str]:
    from pipeline.config import TRAIN_PRESETS

    return sorted(TRAIN_PRESETS)


def _modes() -> list[str]:
    from pipeline.job import JOB_MODES

    return list(JOB_MODES)


class JobCreateOptions(BaseModel):
    """Options of a new job: multipart form fields beside the archive, or query parameters with a raw body."""

    model_config = ConfigDict(extra="forbid")

    preset: str = Field("fast", description="training preset: fast | balanced | paper")
    mode: str = Field("auto", description="reconstruction mode: auto (a short probe picks) | 3dgs | homogeneous | "
                                          "dualphys")
    metric_scale: float | None = Field(None, gt=0, description="metres per scene unit, when known")
    max_width: int = Field(400, ge=32, le=16384, description="images wider than this train at a downscale")
    iterations: int | None = Field(None, ge=1, description="override the preset's iteration count")
    seed: int = Field(0, ge=0, le=2**31 - 1)

    @field_validator("preset")
    @classmethod
    def _known_preset(cls, v: str) -> str:
        if v not in _presets():
            raise ValueError(f"unknown preset {v!r}; choose from {_presets()}")
        return v

    @field_validator("mode")
    @classmethod
    def _known_mode(cls, v: str) -> str:
        if v not in _modes():
            raise ValueError(f"unknown mode {v!r}; choose from {_modes()}")
        return v


class SurveyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str = Field(..., description="a folder under one of the server's survey roots")
    interval_s: float = Field(..., gt=0, description="seconds between scans")
    name: str | None = Field(None, max_length=200)
    options: SurveyOptions = Field(default_factory=SurveyOptions, description="job options for this survey's sets")
