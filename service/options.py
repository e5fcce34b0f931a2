"""The job options a client may set, checked once for uploads and survey folders alike.

An unknown preset or mode is refused when the job or survey is created (a 422 with the reason), not later when
a worker would fail on it; a survey registered with a bad option would otherwise fail every set it finds.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator


def known_presets() -> list[str]:
    from pipeline.config import TRAIN_PRESETS

    return sorted(TRAIN_PRESETS)


def known_modes() -> list[str]:
    from pipeline.job.options import JOB_MODES

    return list(JOB_MODES)


class JobOptionsIn(BaseModel):
    """Options of a job (the pipeline's JobOptions minus the source)."""

    model_config = ConfigDict(extra="forbid")

    preset: str = Field("fast", description="training preset: fast | balanced | paper")
    mode: str = Field("auto", description="reconstruction mode: auto (a short probe picks) | 3dgs | homogeneous | "
                                          "dualphys")
    metric_scale: float | None = Field(None, gt=0, description="metres per scene unit, when known")
    max_width: int = Field(400, ge=32, le=16384, description="images wider than this train at a downscale")
    iterations: int | None = Field(None, ge=1, description="override the preset's iteration count")
    seed: int = Field(0, ge=0, le=2**31 - 1)

    @field_validator("preset", "mode")
    @classmethod
    def _known(cls, v: str, info: ValidationInfo) -> str:
        choices = known_presets() if info.field_name == "preset" else known_modes()
        if v not in choices:
            raise ValueError(f"unknown {info.field_name} {v!r}; choose from {choices}")
        return v

    def over_limit(self, max_iterations: int) -> str | None:
        """Why these options exceed the server's iteration limit, or None."""
        if self.iterations is not None and self.iterations > max_iterations:
            return f"iterations: at most {max_iterations}"
        return None
