"""What the restore stage needs of a job, per photo: its lens camera (SfM's model before undistortion) and the
trained model's render in the training camera (depth, alpha and the water as effective coefficients).

The lens camera and the training camera share one pose (COLMAP's undistortion keeps poses), so a photo pixel's
undistorted ray is the same in both: :mod:`pipeline.restore.lens` maps between them.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import torch

from pipeline.job.layout import JobLayout
from pipeline.restore.frame import RestoreOptions, restore_file
from pipeline.restore.lens import exact_rays
from pipeline.restore.medium import coefficients_from_maps, water_sigma
from pipeline.restore.records import MediumMaps, RenderedView
from pipeline.scene.colmap import has_model
from pipeline.scene.colmap import lens_cameras as read_lenses
from pipeline.scene.records import Camera, LensCamera, View, ray_length_factor
from pipeline.train.model import TrainedModel
from pipeline.train.photo_exposure import photo_fall_off, photo_gains, survey_exposure
from pipeline.train.render import ViewOutputs, render_outputs

# What a 3dgs job's report and restore.json say: that mode models no water.
NOTHING_TO_RESTORE = "mode 3dgs models no water: nothing was removed, so there are no restored photos"


class LensModelError(FileNotFoundError):
    """The job has no model of its photos' lens (SfM's model before undistortion)."""


def job_water_sigma(job: Path) -> np.ndarray | None:
    """:func:`pipeline.restore.medium.water_sigma` of the job's train.json (None when it has none)."""
    path = JobLayout(job).train_result
    return water_sigma(json.loads(path.read_text())) if path.is_file() else None


def lens_cameras(scene_dir: Path) -> dict[str, LensCamera]:
    """Image name -> its lens camera, from the SfM output ``scene_dir`` (``distorted/sparse/0``: the camera
    model bundle adjustment refined, at the photos' own resolution)."""
    sparse = scene_dir / "distorted" / "sparse" / "0"
    if not has_model(sparse):
        raise LensModelError(f"{sparse} holds no COLMAP model: the photos' lens is unknown, so they cannot be "
                             f"restored in their own geometry (re-run the sfm stage)")
    return read_lenses(sparse)


def photo_view(view: View, lens: LensCamera) -> tuple[View, int]:
    """``view`` with its render camera padded by ``pad`` pixels on every side (same focal length and centre), just
    enough that every pixel of the photo (``lens``) lands inside it: (the view, pad). The training camera is
    SfM's undistorted crop, and a photo through a barrel lens reaches beyond it along its edges (a 1600x1200
    photo, k1 −0.12: up to 6 render pixels at the corners); the model holds the seabed there (other views saw it),
    so it is rendered, not extrapolated. No pad: the view itself."""
    W, H = lens.width, lens.height
    edges = [exact_rays(lens, 0, 1), exact_rays(lens, H - 1, H), exact_rays(lens, 0, H, 0, 1),
             exact_rays(lens, 0, H, W - 1, W)]
    xn = np.concatenate([e[0].ravel() for e in edges])
    yn = np.concatenate([e[1].ravel() for e in edges])
    c = view.camera
    u, v = c.fx * xn + c.cx, c.fy * yn + c.cy
    over = max(0.0, -float(u.min()), float(u.max()) - c.width, -float(v.min()), float(v.max()) - c.height)
    pad = math.ceil(over) + 1 if over > 0 else 0  # +1: bilinear sampling needs the next pixel centre too
    if pad == 0:
        return view, 0
    cam = Camera(c.width + 2 * pad, c.height + 2 * pad, c.fx, c.fy, c.cx + pad, c.cy + pad)
    return dataclasses.replace(view, camera=cam), pad


def rendered_view(model: TrainedModel, view: View, backend: str = "auto", out: ViewOutputs | None = None,
                  sigma: np.ndarray | None = None, pad: int = 0) -> RenderedView:
    """The model's depth, alpha and water for ``view`` (training camera), from ``out`` when the caller rendered
    it already. The homogeneous medium is three per-channel constants (exact at any resolution); a network
    medium's per-pixel A and B become effective coefficients
    (:func:`pipeline.restore.medium.coefficients_from_maps`). ``sigma``: the water's uncertainty
    (:func:`pipeline.restore.medium.water_sigma`), for the confidence maps. ``pad``: what :func:`photo_view` added
    to ``view``'s camera on each side."""
    medium = model.medium
    if medium is None:
        raise ValueError(NOTHING_TO_RESTORE)
    if out is None:
        out = render_outputs(model.gaussians, view, medium, model.sh_degree, backend, model.background)
    binf = medium.B_inf.detach().double().numpy()
    if medium.mode == "homogeneous":
        with torch.no_grad():
            maps = MediumMaps((medium.w * medium.beta_D).detach().double().numpy(),
                              medium.beta_B.detach().double().numpy(), binf)
    else:
        r = out.depth * ray_length_factor(view.camera)
        assert out.A is not None and out.B is not None
        maps = coefficients_from_maps(out.A, out.B, r, binf, out.alpha)
    maps.sigma = sigma
    # the model's own J where it covers the pixel (premultiplied over black: normalised by alpha), in the space
    # its physics ran in: the restoration's prior where the photo's signal is too weak
    J = np.clip(out.J / np.maximum(out.alpha, 0.5)[..., None], 0.0, 1.0).astype(np.float32)
    return RenderedView(view.camera, out.depth.astype(np.float32), out.alpha.astype(np.float32), maps, J, pad)


def render_for_photo(model: TrainedModel, view: View, lens: LensCamera, sigma: np.ndarray | None = None,
                     backend: str = "auto", log_gain: np.ndarray | None = None,
                     survey_log_gain: np.ndarray | None = None, fall_off: np.ndarray | None = None
                     ) -> tuple[RenderedView, ViewOutputs, int]:
    """The model rendered for restoring ``view``'s photo (``lens``), in :func:`photo_view`'s padded camera: (what
    the restorer reads, the render's outputs, the pad in render pixels on each side). ``log_gain``: the photo's
    exposure (:func:`pipeline.train.photo_exposure.photo_gains`), removed before it is de-watered;
    ``survey_log_gain``: the survey's mean exposure on the model's (:func:`~pipeline.train.photo_exposure
    .survey_exposure`), given to the restored photo; ``fall_off``: the survey's in-frame fall-off
    (:func:`pipeline.train.photo_exposure.photo_fall_off`), divided out with the exposure."""
    padded, pad = photo_view(view, lens)
    out = render_outputs(model.gaussians, padded, model.medium, model.sh_degree, backend, model.background)
    rendered = rendered_view(model, padded, backend, out=out, sigma=sigma, pad=pad)
    return (dataclasses.replace(rendered, log_gain=log_gain, output_log_gain=survey_log_gain, fall_off=fall_off),
            out, pad)


@dataclasses.dataclass(frozen=True)
class JobPhotos:
    """What de-watering a trained job's photos reads of the job, read once: the lens cameras, the water's spread,
    each photo's exposure and the survey's mean, the in-frame fall-off (``fall_record``: whether it was divided
    out and why). The restore stage and ``dualphys render --what photos`` both restore through it."""

    model: TrainedModel
    lenses: dict[str, LensCamera]
    sigma: np.ndarray | None
    gains: dict[str, np.ndarray]
    survey: np.ndarray | None
    fall_off: np.ndarray | None
    fall_record: dict

    @classmethod
    def of(cls, job: Path, model: TrainedModel) -> JobPhotos:
        gains = photo_gains(job)  # each photo's exposure, removed before it is de-watered
        fall_off, fall_record = photo_fall_off(job)  # divided out as training divided it out
        return cls(model, lens_cameras(JobLayout(job).scene), job_water_sigma(job), gains,
                   survey_exposure(gains), fall_off, fall_record)  # the restored photos get the survey's exposure

    def render(self, view: View) -> tuple[RenderedView, ViewOutputs, int]:
        """:func:`render_for_photo` of ``view`` with this job's lens, water, exposure and fall-off."""
        return render_for_photo(self.model, view, self.lenses[view.name], self.sigma,
                                log_gain=self.gains.get(view.name), survey_log_gain=self.survey,
                                fall_off=self.fall_off)


def restore_photo(src: Path, restored_dir: Path, confidence_dir: Path, lens: LensCamera, view: RenderedView, *,
                  max_gain: float, fmt: str, space: str) -> dict:
    """One photo de-watered (:func:`pipeline.restore.frame.restore_file`): the restored image into
    ``restored_dir`` (the photo's name and format, or 16-bit TIFF for ``fmt`` "tiff16"), its confidence map
    ``<stem>.png`` and surface mask ``<stem>_surface.png`` into ``confidence_dir``. Returns what restore.json
    records of it."""
    res = restore_file(src, lens, view, restored_dir, RestoreOptions(max_gain=max_gain, space=space),
                       tiff16=fmt == "tiff16", confidence_dir=confidence_dir)
    n = lens.width * lens.height
    return {"file": res.paths["J"].name, "width": lens.width, "height": lens.height,
            "surface": round(res.surface_pixels / n, 5), "extended": round(res.extended_pixels / n, 5),
            "clipped": round(res.clipped / n, 5),
            "camera": lens.model, "prior_weight": res.lam2}
