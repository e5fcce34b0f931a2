"""Render a trained job again (``dualphys render``): its own cameras, a chosen few, or novel cameras on a smooth
path through them. The rendering itself is :func:`pipeline.export.views.export_views` (the export stage's)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.export.views import export_views
from pipeline.job.layout import RENDER_FOLDERS, JobLayout
from pipeline.restore.views import NOTHING_TO_RESTORE, JobPhotos, restore_photo
from pipeline.scene.colmap import qvec_to_rotmat, rotmat_to_qvec
from pipeline.scene.records import View
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.model import model_from_state, training_views

log = logging.getLogger(__name__)


class RenderError(ValueError):
    """The job cannot be rendered as asked (not trained yet, unknown view name, bad folder name)."""


def _slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (w first), along the shorter arc."""
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:  # nearly equal: linear is exact enough and avoids dividing by sin(0)
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(d)
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


def path_views(views: Sequence[View], n: int) -> list[View]:
    """``n`` novel cameras evenly spaced (by distance travelled) along the path through ``views`` in name order:
    centres interpolated linearly, orientations by slerp, the intrinsics of the first view. Named
    ``novel_0000.png`` ..."""
    if n < 1:
        raise RenderError(f"the number of novel views must be at least 1, got {n}")
    ordered = sorted(views, key=lambda v: v.name)
    if len(ordered) < 2:
        raise RenderError("novel views need at least two cameras to interpolate between")
    centres = np.stack([v.center for v in ordered])  # [V, 3]
    quats = [rotmat_to_qvec(v.R.T) for v in ordered]  # world_from_cam orientations
    seg = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(seg)])  # [V]
    if along[-1] <= 0:
        along = np.arange(len(ordered), dtype=np.float64)  # all cameras in one place: step by index
    out = []
    for k, a in enumerate(np.linspace(0.0, along[-1], n)):
        i = int(np.clip(np.searchsorted(along, a, side="right") - 1, 0, len(ordered) - 2))
        s = float((a - along[i]) / max(along[i + 1] - along[i], 1e-12))
        c = (1 - s) * centres[i] + s * centres[i + 1]
        R = qvec_to_rotmat(_slerp(quats[i], quats[i + 1], s)).T  # back to cam_from_world
        out.append(View(f"novel_{k:04d}.png", ordered[0].camera, R, -R @ c))
    return out


def render_job(job: str | Path, out: str | Path, views: str | Sequence[str] = "all",
               what: Sequence[str] = ("restored", "with_water"), novel: int = 0, backend: str = "auto",
               max_gain: float = 8.0, fmt: str = "auto") -> dict:
    """Render the trained model of ``job`` into ``out`` laid out as a job's output folder: the model's renders in
    ``out/renders/<what>/`` for the job's views (``"all"`` or names, with or without the extension) and ``novel``
    cameras on a path through them; with ``"photos"`` in ``what``, the chosen views' input photos de-watered at
    full resolution into ``out/restored/`` and ``out/confidence/`` (as the restore stage does, with this gain cap
    and format; novel cameras have no photo). Returns counts."""
    job, out = Path(job), Path(out)
    photos = "photos" in what
    what = [w for w in what if w != "photos"]
    bad = [w for w in what if w not in RENDER_FOLDERS]
    if bad:
        raise RenderError(f"unknown output {', '.join(bad)}; choose from photos, {', '.join(RENDER_FOLDERS)}")
    ckpt = JobLayout(job).checkpoint
    if not ckpt.is_file():
        raise RenderError(f"{job} has no trained model ({ckpt} is missing): run `dualphys run` on it first")
    state = load_checkpoint(ckpt)
    cams = training_views(job, state)
    if views == "all":
        chosen = cams
    else:
        by_name = {v.name: v for v in cams} | {Path(v.name).stem: v for v in cams}
        missing = [n for n in views if n not in by_name]
        if missing:
            names = ", ".join(sorted(v.name for v in cams))
            raise RenderError(f"no view named {', '.join(missing)} in {job}; it has {names}")
        chosen = [by_name[n] for n in views]
    restored = _restore_photos(job, state, chosen, out, max_gain, fmt) if photos else None
    chosen = chosen + (path_views(cams, novel) if novel else [])
    if not chosen:
        raise RenderError("nothing to render: no views chosen and no novel views asked for")
    renders = out / JobLayout(job).renders.relative_to(JobLayout(job).output)
    counts = export_views(state, chosen, renders, backend=backend, what=what) if what else {"views": len(chosen)}
    if restored is not None:
        counts["photos"] = restored
    if state.get("medium") is None and set(what) & {"attenuation", "backscatter"}:
        log.warning("the job was trained in mode 3dgs: there is no water, so no attenuation/backscatter maps")
    log.info("rendered %d views (%d novel) of %s into %s", len(chosen), novel, job, out)
    return {**counts, "novel": novel, "mode": state["mode"]}


def _restore_photos(job: Path, state: dict, views: Sequence[View], out: Path, max_gain: float, fmt: str) -> int:
    """The input photos of ``views`` de-watered into ``out/restored`` and ``out/confidence``; their count."""
    model = model_from_state(state)
    if model.medium is None:
        raise RenderError(NOTHING_TO_RESTORE)
    layout = JobLayout(job)
    job_photos = JobPhotos.of(job, model)  # exposure and fall-off as the restore stage removed them
    for v in views:  # out/ gets the job's own folder names for them
        restore_photo(layout.images / v.name, out / layout.restored.name, out / layout.confidence.name,
                      job_photos.lenses[v.name], job_photos.render(v)[0], max_gain=max_gain, fmt=fmt,
                      space=model.colour_space)
    return len(views)


__all__ = ["RenderError", "path_views", "render_job"]
