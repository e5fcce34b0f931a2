"""`dualphys run`'s job flags, built from :class:`pipeline.job.options.JobOptions` as the API's form fields are
(service/jobs/options.py): each flag's default and type come from its field, and the parsed flags go back into a
``JobOptions`` by field name. Torch-free (the client install builds this parser too).

What the command line adds: which fields are flags and their spelling (``restore_format`` is ``--format``), the
choices of the text fields, the integer fields that must be positive, and its own help wording where that is
shorter than the field's ``help`` (the API's description); a field not in ``RUN_HELP`` shows its ``help``.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pipeline.cli_args import positive
from pipeline.config import TRAIN_PRESETS
from pipeline.job.options import COLOUR_SPACES, JOB_MODES, RESTORE_FORMATS, JobOptions

# JobOptions field -> flag, in --help order. Not flags: source (the positional input), ground_truth (found next
# to a generated scene's images). A bool field is a --flag / --no-flag pair.
RUN_FLAGS: dict[str, str] = {
    "preset": "--preset", "mode": "--mode", "iterations": "--iterations", "max_width": "--max-width",
    "seed": "--seed", "colour_space": "--colour-space", "restore_format": "--format", "max_gain": "--max-gain",
    "ortho": "--ortho", "ortho_gsd": "--ortho-gsd", "telemetry": "--telemetry", "scale_bar": "--scale-bar",
    "metric_scale": "--metric-scale",
}
CHOICES: dict[str, Sequence[str]] = {
    "preset": tuple(TRAIN_PRESETS), "mode": JOB_MODES, "colour_space": COLOUR_SPACES,
    "restore_format": RESTORE_FORMATS,
}
POSITIVE: frozenset[str] = frozenset({"iterations", "max_width"})  # the rest: their field's type
# The command line's wording where it differs from the field's help; None: no help line.
RUN_HELP: dict[str, str | None] = {
    "preset": None,
    "mode": "auto (default): a short probe picks the simplest mode the scene needs",
    "max_width": "train wider images at an integer downscale",
    "seed": None,
    "colour_space": "where the water physics runs: on the photos' sRGB values or on linear light",
    "restore_format": "the restored photos: auto (each as its input: 8-bit JPEG or PNG) | tiff16",
    "max_gain": "cap on the restoration's per-channel gain 1/A",
    "ortho": "make the orthomosaics and elevation model (--no-ortho: skip them)",
    "telemetry": "a per-frame CSV (file, camera_to_bottom_m, lat, lon): a path, or a file name in the input folder",
    "scale_bar": "known lengths in the photos: 'PHOTO:X1,Y1:X2,Y2:METRES', several joined by ';'",
}


def _value_type(hint: Any) -> Callable[[str], Any]:
    """``int | None`` -> int: what a given flag's text converts to."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        (hint,) = (a for a in typing.get_args(hint) if a is not type(None))
    return hint


def add_job_flags(parser: argparse.ArgumentParser) -> None:
    """The ``RUN_FLAGS`` on ``parser``; each parses into the attribute named as its field."""
    fields = {f.name: f for f in dataclasses.fields(JobOptions)}
    hints = typing.get_type_hints(JobOptions)
    for name, flag in RUN_FLAGS.items():
        field = fields[name]
        extra = {"choices": list(CHOICES[name])} if name in CHOICES else {}
        kind = _value_type(hints[name])
        if kind is bool:
            extra["action"] = argparse.BooleanOptionalAction
        else:
            extra["type"] = positive if name in POSITIVE else kind
        parser.add_argument(flag, dest=name, default=field.default,
                            help=RUN_HELP.get(name, field.metadata.get("help")), **extra)


def job_options(args: argparse.Namespace, source: Path) -> JobOptions:
    """The job the parsed ``RUN_FLAGS`` ask for, on ``source``. A telemetry file given by a path that exists is
    made absolute (the job may run from another folder); a bare name is looked up among the input's CSV files."""
    values = {name: getattr(args, name) for name in RUN_FLAGS}
    if values.get("telemetry") and Path(values["telemetry"]).is_file():
        values["telemetry"] = str(Path(values["telemetry"]).resolve())
    return JobOptions(source=str(source), **values)
