"""Versioned training checkpoints on disk: a named dict of tensors and plain values, written atomically."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import torch

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1
CHECKPOINT_KIND = "dualphys.trainer"


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> Path:
    """Write ``state`` (plus version and kind keys) to ``path`` via a temp file and rename, so a crash
    mid-write leaves the previous checkpoint intact."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"version": CHECKPOINT_VERSION, "kind": CHECKPOINT_KIND, **state}, tmp)
    os.replace(tmp, path)
    log.info("checkpoint written: %s (iteration %s)", path, state.get("iteration"))
    return path


def load_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by ``save_checkpoint`` (tensors only, no pickled code: ``weights_only``)."""
    state = torch.load(Path(path), map_location=map_location, weights_only=True)
    if not isinstance(state, dict) or state.get("kind") != CHECKPOINT_KIND:
        raise ValueError(f"{path} is not a dualphys training checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {state.get('version')!r}, this code reads {CHECKPOINT_VERSION}")
    return state
