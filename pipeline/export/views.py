"""The per-view images of a trained model, written as files named after the view's image stem.

Folders (under ``out``, a job's ``output/renders/``; names in :data:`pipeline.job.layout.RENDER_FOLDERS`):
``restored/`` (the model's J), ``with_water/`` (I), ``attenuation/`` (A), ``backscatter/`` (B), ``depth/`` (16-bit PNG
normalised to the scene's depth range for viewing, plus float32 ``.npy`` of the camera-space z in scene units). In
mode ``3dgs`` there is no medium: nothing is restored, so only ``with_water/`` and ``depth/`` are written (a J
equal to I titled "restored" would claim a restoration that did not happen). The user's photos de-watered are
the restore stage's (``pipeline.restore``), not these renders.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.scene.images import write_image
from pipeline.scene.records import View
from pipeline.train.model import model_from_state
from pipeline.train.render import displayed, render_outputs

log = logging.getLogger(__name__)


def export_views(state: dict[str, Any], views: Sequence[View], out: str | Path, backend: str = "auto",
                 what: Sequence[str] | None = None) -> dict:
    """Write the restored outputs of every view from a training checkpoint ``state``; returns counts.
    ``what`` limits the folders written (default: all that the model has; see
    :data:`~pipeline.job.layout.RENDER_FOLDERS`)."""
    out = Path(out)
    model = model_from_state(state)
    medium = model.medium
    results = [(v, displayed(render_outputs(model.gaussians, v, medium, model.sh_degree, backend, model.background),
                             model.colour_space)) for v in views]
    zmax = max(float(r.depth.max()) for _, r in results) or 1.0
    folders = ["with_water", "depth"] + (["restored", "attenuation", "backscatter"] if medium is not None else [])
    if what is not None:
        folders = [f for f in folders if f in what]
    for f in folders:
        (out / f).mkdir(parents=True, exist_ok=True)
    for v, r in results:
        stem = Path(v.name).stem
        images = {"restored": r.J, "with_water": r.I, "attenuation": r.A, "backscatter": r.B}
        for f in folders:
            if f == "depth":
                write_image(out / "depth" / f"{stem}.png", np.clip(r.depth / zmax, 0, 1), bits=16)
                np.save(out / "depth" / f"{stem}.npy", r.depth.astype(np.float32))
            else:
                write_image(out / f / f"{stem}.png", images[f])
    log.info("exported %d views (%s) to %s", len(results), ", ".join(folders), out)
    return {"views": len(results), "folders": folders, "depth_max": zmax}
