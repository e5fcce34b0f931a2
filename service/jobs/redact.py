"""Server paths never reach clients: messages that a stage, a decoder or the OS wrote with absolute paths in
them are rewritten before they land in a job's status, its log or an error body.

Inside the job folder a path becomes relative to it (``/data/jobs/j1/images/a.jpg`` -> ``images/a.jpg``);
anything else under the data folder becomes ``<data>/...``. Both the spelled and the resolved form are
replaced (the data folder may be reached through a link).
"""

from __future__ import annotations

import os
from pathlib import Path


def _forms(path: Path) -> list[str]:
    spelled = os.path.abspath(path)
    real = os.path.realpath(path)
    return sorted({spelled, real}, key=len, reverse=True)


def redact_paths(text: str, job_dir: Path | None, data_dir: Path | None) -> str:
    """``text`` with the job folder's and the data folder's absolute paths taken out (module docstring)."""
    if job_dir is not None:
        for form in _forms(job_dir):
            text = text.replace(form + "/", "").replace(form, ".")
    if data_dir is not None:
        for form in _forms(data_dir):
            text = text.replace(form, "<data>")
    return text
