"""The job options a client may set, checked once for uploads and survey folders alike.

An unknown preset or mode is refused when the job or survey is created (a 422 with the reason), not later when
a worker would fail on it; a survey registered with a bad option would otherwise fail every set it finds.

The fields, their types, defaults and descriptions are the pipeline's :class:`pipeline.job.options.JobOptions`
(declared once, there); this module adds only what the API checks on top: which of them a client may set and
their bounds.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, create_model, field_validator

from pipeline.config import TRAIN_PRESETS
from pipeline.job.options import COLOUR_SPACES, JOB_MODES, RESTORE_FORMATS, JobOptions, parse_scale_bars

# What a client may set (``source`` is the upload or the survey's set; ``ground_truth`` is for local runs only),
# in the order the API documents them, with the API's bounds.
CLIENT_OPTIONS: dict[str, dict[str, Any]] = {
    "preset": {}, "mode": {}, "metric_scale": {"gt": 0}, "max_width": {"ge": 32, "le": 16384},
    "iterations": {"ge": 1}, "seed": {"ge": 0, "le": 2**31 - 1}, "colour_space": {}, "restore_format": {},
    "max_gain": {"ge": 1, "le": 1000},
    # the survey products; telemetry names a CSV inside the upload (a bare name: no server path is ever read)
    "ortho": {}, "ortho_gsd": {"gt": 0}, "telemetry": {"pattern": r"^[^/\\]{1,200}\.csv$"},
    "scale_bar": {"max_length": 4000},
}


def known_presets() -> list[str]:
    return sorted(TRAIN_PRESETS)


def known_modes() -> list[str]:
    return list(JOB_MODES)


def known_colour_spaces() -> list[str]:
    return list(COLOUR_SPACES)


def known_restore_formats() -> list[str]:
    return list(RESTORE_FORMATS)


class _ClientOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    @field_validator("preset", "mode", "colour_space", "restore_format", check_fields=False)
    @classmethod
    def _known(cls, v: str, info: ValidationInfo) -> str:
        choices = {"preset": known_presets, "mode": known_modes, "restore_format": known_restore_formats,
                   "colour_space": known_colour_spaces}[
            info.field_name]()
        if v not in choices:
            raise ValueError(f"unknown {info.field_name} {v!r}; choose from {choices}")
        return v

    @field_validator("scale_bar", check_fields=False)
    @classmethod
    def _bars(cls, v: str | None) -> str | None:
        parse_scale_bars(v)  # ValueError with the reason: a 422 at submission, not a failed stage later
        return v

    def over_limit(self, max_iterations: int) -> str | None:
        """Why these options exceed the server's iteration limit, or None."""
        iterations = getattr(self, "iterations", None)
        if iterations is not None and iterations > max_iterations:
            return f"iterations: at most {max_iterations}"
        return None


def _client_fields() -> dict[str, Any]:
    hints = typing.get_type_hints(JobOptions)
    spec = {f.name: f for f in dataclasses.fields(JobOptions)}
    return {name: (hints[name], Field(spec[name].default, description=spec[name].metadata.get("help"), **bounds))
            for name, bounds in CLIENT_OPTIONS.items()}


JobOptionsIn = create_model("JobOptionsIn", __base__=_ClientOptions, __module__=__name__, **_client_fields())
JobOptionsIn.__doc__ = "Options of a job (the pipeline's JobOptions minus the source)."
