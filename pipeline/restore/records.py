"""Records of the restorer: the photo's lens camera, the medium as per-pixel coefficients, one rendered view.

Conventions (those of ``pipeline/scene/records.py``): pixel-centre convention for every camera (the centre of
the top-left pixel is at (0.5, 0.5), COLMAP's and pycolmap's), poses ``cam_from_world``. The lens camera and the
render camera share one pose, so a pixel's undistorted normalised ray (xn, yn) = (x/z, y/z) is the same in
both; the render camera is the undistorted PINHOLE camera at the training resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.scene.records import Camera


@dataclass
class MediumMaps:
    """The water of one view as effective coefficients, one path for both medium modes:

        A = exp(−k_A·r),   B = B∞·(1 − exp(−k_B·r)),   r = distance along the ray (scene units).

    ``k_A`` / ``k_B`` are either [3] (homogeneous medium: β_D, β_B everywhere, exact closed form) or
    [h, w, 3] maps in the render camera (network medium; :func:`pipeline.restore.medium.coefficients_from_maps`),
    sampled bilinearly at full resolution and re-evaluated with the full-resolution range. ``B_inf`` [3]."""

    k_A: np.ndarray
    k_B: np.ndarray
    B_inf: np.ndarray
    # [3, 3] the water's uncertainty: σ of log k_A, log k_B, logit B∞ (rows) per channel (columns), for the
    # confidence map (pipeline.restore.dewater.expected_error); None: not measured (the water type's prior).
    sigma: np.ndarray | None = None

    @property
    def constant(self) -> bool:
        """True when both coefficients are per-channel constants [3]."""
        return np.ndim(self.k_A) == 1 and np.ndim(self.k_B) == 1


@dataclass
class RenderedView:
    """What the trained model rendered for one view in its render camera (PINHOLE, training resolution).

    depth [h, w]: camera z in scene units, 0 where nothing was rendered; alpha [h, w] in [0, 1] (a pixel is
    surface where alpha ≥ 0.5); medium: the view's water; J [h, w, 3] (optional): the model's restored radiance
    (alpha-normalised, in the space the physics runs in), the prior where the photo's signal is too weak
    (:mod:`pipeline.restore.dewater`)."""

    camera: Camera
    depth: np.ndarray
    alpha: np.ndarray
    medium: MediumMaps
    J: np.ndarray | None = None
    # render pixels added on each side of the training camera so the whole photo lands inside
    # (pipeline.restore.views.photo_view); the upsampling factor is the photo's width over the unpadded width
    pad: int = 0
    # the photo's exposure and white balance, log gains [3] on linear light (pipeline.scene.exposure), removed
    # before it is de-watered; None: taken at neutral exposure
    log_gain: np.ndarray | None = None
    # log gains [3] on linear light that take the de-watered photo from the model's exposure to the survey's mean
    # (pipeline.train.photo_exposure.survey_exposure); None: left at the model's
    output_log_gain: np.ndarray | None = None
    # the survey's in-frame fall-off (vignetting, a lamp's cone) as the coefficients [5] of its grey log field over
    # the training image's coordinates (pipeline.medium.exposure_gains), divided out of the photo with its
    # exposure; None: left in
    fall_off: np.ndarray | None = None

    def __post_init__(self) -> None:
        shape = (self.camera.height, self.camera.width)
        if np.shape(self.depth) != shape or np.shape(self.alpha) != shape:
            raise ValueError(f"depth {np.shape(self.depth)} and alpha {np.shape(self.alpha)} must be {shape}")
        for k in (self.medium.k_A, self.medium.k_B):
            if np.ndim(k) != 1 and np.shape(k) != (*shape, 3):
                raise ValueError(f"medium coefficients must be [3] or {(*shape, 3)}, got {np.shape(k)}")
