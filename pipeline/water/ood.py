"""Does the classifier know this water? Out-of-distribution statistics of a scene's images (pure functions).

The classifier (eq. 14) was trained on generated daylight scenes only; it always answers one of its three
classes, with p = 0.998 for dark temperate water lit by a vehicle's lamps (issue 39). Four statistics say when
an image is outside what it learned, each with a threshold calibrated on real photos (``bench/water_ood.py``,
docs/DECISIONS.md "Water type: unknown water"):

- ``distance``: Mahalanobis distance of the image's standardised feature vector from the training features
  (centre and a whitening factor of their shrunk covariance, stored in the weights file). A loose catch-all:
  real daylight photos already lie far outside the generated data by this measure (U45's blue images at a
  median of 11.7), so its threshold sits above every real set and it flags only gross anomalies.
- ``falloff``: how strongly brightness falls off in *every* direction from a hot spot, the weakest downward
  curvature of a quadratic fitted to the low-passed log luma (corner of the frame at radius 1). A lamp on the
  vehicle lights a disc and leaves the rest dark; daylight from above lights the frame evenly.
- ``luma``: mean luma. The training exposures never go below ~0.13; a frame much darker carries little of the
  colour the classifier reads.
- ``clipped``: share of pixels black or saturated (max channel <= 2/255 or >= 254/255); a blank, lens-capped or
  blown-out frame.

Per job, each statistic is the median over the classified images (one odd frame does not make the water
unknown), compared with its threshold. ``trust`` falls linearly from 1 where a statistic is inside what the
training data shows (``typical``) to 0 at the threshold; the decision's confidence is max p × trust.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from pipeline.water.features import luma

CLIP_LOW = 2.0 / 255.0  # a pixel whose brightest channel is at or below this is black
CLIP_HIGH = 254.0 / 255.0  # ... at or above this, saturated
FALLOFF_BLOCKS = 6  # the short side is pooled into this many blocks before the quadratic fit
LOG_FLOOR = 1.0 / 255.0  # luma floor before the log (one 8-bit step)
# λ added to the standardised training features' covariance before inverting: its smallest eigenvalues (~2e-4)
# are exact relations of the generator (e.g. quantiles and means of one channel) that any real photo breaks
# slightly; unshrunk they made every real set look far off (U45 blue at a median of 27 against 13 with λ).
SHRINKAGE = 0.1


@dataclass(frozen=True)
class OodConfig:
    """Thresholds on the job's median statistics (``threshold``: out beyond it) and where trust starts to fall
    (``typical``: the edge of the generated training data). Calibration: docs/DECISIONS.md."""

    distance_typical: float = 6.0  # 99th percentile over generated training-like frames (5.4-6.0)
    distance_max: float = 35.0  # above every real photo we have, one at a time (largest: U45 blue 26.png, 32.7)
    falloff_typical: float = 0.6  # 99th percentile of 8-frame job medians of generated frames (0.58; max 0.68)
    falloff_max: float = 1.0  # lamp-lit jobs: 1.08-2.30; real daylight jobs: at most 0.16
    luma_typical: float = 0.15  # generated frames: 1st percentile 0.17, least 0.13
    luma_min: float = 0.06  # real daylight jobs: at least 0.26
    clipped_typical: float = 0.1  # generated frames: 99th percentile 0.06, most 0.21
    clipped_max: float = 0.5  # real daylight jobs: 0.00

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FeatureDistribution:
    """The training features' distribution in the classifier's standardised space: centre [F] and the whitening
    factor W [F, F] (lower triangular, W Wᵀ = (Σ + λ I)⁻¹), so distance = ‖Wᵀ (z − centre)‖."""

    centre: Tensor  # [F]
    whitening: Tensor  # [F, F]
    shrinkage: float  # λ added to the covariance's diagonal (the standardised features have unit variance)

    def distance(self, z: Tensor) -> Tensor:
        """Mahalanobis distance of standardised features. [N, F] → [N]"""
        return mahalanobis(z, self.centre, self.whitening)


def mahalanobis(z: Tensor, centre: Tensor, whitening: Tensor) -> Tensor:
    """‖Wᵀ (z − c)‖ per row. z [N, F], centre [F], whitening [F, F] → [N]

    >>> round(float(mahalanobis(torch.tensor([[3.0, 4.0]]), torch.zeros(2), torch.eye(2))[0]), 3)
    5.0
    """
    if z.ndim != 2 or z.shape[1] != centre.shape[0]:
        raise ValueError(f"expected z [N, {centre.shape[0]}], got {tuple(z.shape)}")
    return ((z - centre) @ whitening).norm(dim=1)


def fit_distribution(z: Tensor, shrinkage: float) -> FeatureDistribution:
    """Centre and whitening factor of standardised training features z [N, F] (float64 for the inverse)."""
    z64 = z.double()
    centre = z64.mean(dim=0)
    cov = torch.cov(z64.T) + shrinkage * torch.eye(z.shape[1], dtype=torch.float64)
    whitening = torch.linalg.cholesky(torch.linalg.inv(cov))
    return FeatureDistribution(centre.float(), whitening.float(), shrinkage)


def illumination_falloff(images: Tensor) -> Tensor:
    """How strongly brightness falls off in every direction from a hot spot. [N, 3, H, W] → [N]

    The luma is pooled into blocks (``FALLOFF_BLOCKS`` along the short side), log-transformed and fitted with
    a + b·x + c·y + d·x² + e·y² + f·xy, with x, y scaled so the frame's corner lies at radius 1. The value is
    minus the larger eigenvalue of the fit's Hessian: positive when the log brightness curves down along every
    direction (a lit disc), ~0 for even light or a plain gradient, negative for a dark centre. A cos^n lamp
    pattern over a 90° lens gives 2-5; camera vignetting of 1 − 0.3ρ² gives 0.7. Frames smaller than 3×3 blocks
    give 0.

    >>> yy, xx = torch.meshgrid(torch.linspace(-1, 1, 48), torch.linspace(-1, 1, 64), indexing="ij")
    >>> spot = torch.exp(-(xx**2 + yy**2))[None, None].expand(1, 3, 48, 64) * 0.8
    >>> round(float(illumination_falloff(spot)[0]), 1), round(float(illumination_falloff(spot * 0 + 0.5)[0]), 1)
    (3.2, 0.0)
    """
    y = luma(images)  # [N, H, W]
    n, h, w = y.shape
    block = max(1, min(h, w) // FALLOFF_BLOCKS)
    g = F.avg_pool2d(y[:, None], block, stride=block)[:, 0].double()  # [N, gh, gw]
    gh, gw = g.shape[-2:]
    if gh < 3 or gw < 3:
        return torch.zeros(n, dtype=images.dtype, device=images.device)
    diag = (gh * gh + gw * gw) ** 0.5
    ys = (torch.arange(gh, dtype=torch.float64, device=g.device) + 0.5 - gh / 2) / (diag / 2)
    xs = (torch.arange(gw, dtype=torch.float64, device=g.device) + 0.5 - gw / 2) / (diag / 2)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    a = torch.stack([torch.ones_like(xx), xx, yy, xx * xx, yy * yy, xx * yy], dim=-1).reshape(-1, 6)  # [P, 6]
    target = torch.log(g.clamp(min=LOG_FLOOR)).reshape(n, -1, 1)  # [N, P, 1]
    coef = torch.linalg.lstsq(a.expand(n, -1, -1), target).solution[..., 0]  # [N, 6]
    hess = torch.stack([torch.stack([2 * coef[:, 3], coef[:, 5]], -1),
                        torch.stack([coef[:, 5], 2 * coef[:, 4]], -1)], -2)  # [N, 2, 2]
    return (-torch.linalg.eigvalsh(hess)[:, -1]).to(images.dtype)


def clipped_fraction(images: Tensor) -> Tensor:
    """Share of pixels that are black or saturated (brightest channel <= CLIP_LOW or >= CLIP_HIGH). → [N]

    >>> clipped_fraction(torch.zeros(1, 3, 2, 2)).tolist(), clipped_fraction(torch.full((1, 3, 2, 2), 0.5)).tolist()
    ([1.0], [0.0])
    """
    mx = images.amax(dim=1)  # [N, H, W]
    return ((mx <= CLIP_LOW) | (mx >= CLIP_HIGH)).flatten(1).to(images.dtype).mean(dim=1)


def mean_luma(images: Tensor) -> Tensor:
    """[N, 3, H, W] → [N]"""
    return luma(images).flatten(1).mean(dim=1)


@dataclass(frozen=True)
class OodVerdict:
    """The job-level answer: is the water inside what the classifier knows, how much to trust its class, why."""

    known: bool
    trust: float  # in [0, 1]: 1 inside the training data's range, 0 at a threshold
    reason: str | None  # plain words when not known (or when trust is reduced), None otherwise
    statistics: dict[str, float | None]  # the job's medians: distance, falloff, luma, clipped

    def to_dict(self) -> dict:
        """The statistics and trust (known and reason are the decision's own fields)."""
        return {"trust": self.trust, **self.statistics}


def _ramp(value: float, typical: float, limit: float) -> float:
    """1 at or inside ``typical``, 0 at or beyond ``limit``, linear between (either direction)."""
    if (limit - typical) == 0:
        return 1.0 if value == typical else 0.0
    return min(1.0, max(0.0, (limit - value) / (limit - typical)))


def assess(distance: Tensor | None, falloff: Tensor, luma_mean: Tensor, clipped: Tensor,
           cfg: OodConfig | None = None) -> OodVerdict:
    """The job's verdict from per-image statistics ([N] each; ``distance`` None when the weights file carries
    no feature distribution). Each statistic's median over the images is compared with its threshold."""
    cfg = cfg or OodConfig()
    med = {"distance": float(distance.median()) if distance is not None else None,
           "falloff": float(falloff.median()), "luma": float(luma_mean.median()),
           "clipped": float(clipped.median())}
    out = []  # (statistic, plain reason) of every statistic beyond its threshold
    if med["distance"] is not None and med["distance"] > cfg.distance_max:
        out.append(f"the pooled image statistics lie {med['distance']:.1f} standard units from the training "
                   f"images (threshold {cfg.distance_max:g})")
    if med["falloff"] > cfg.falloff_max:
        out.append(f"the light falls off from a bright spot towards every edge (falloff {med['falloff']:.2f} > "
                   f"{cfg.falloff_max:g}): artificial light such as the vehicle's lamps, not daylight")
    if med["luma"] < cfg.luma_min:
        out.append(f"the images are very dark (mean luma {med['luma']:.3f} < {cfg.luma_min:g})")
    if med["clipped"] > cfg.clipped_max:
        out.append(f"{100 * med['clipped']:.0f} % of the pixels are black or saturated")
    trusts = [_ramp(med["falloff"], cfg.falloff_typical, cfg.falloff_max),
              _ramp(-med["luma"], -cfg.luma_typical, -cfg.luma_min),
              _ramp(med["clipped"], cfg.clipped_typical, cfg.clipped_max)]
    if med["distance"] is not None:
        trusts.append(_ramp(med["distance"], cfg.distance_typical, cfg.distance_max))
    trust = min(trusts) if not out else 0.0
    if out:
        reason = "the images' statistics are outside the classifier's training: " + "; ".join(out)
    elif trust < 1.0:
        reason = "the images are near the edge of the classifier's training data (confidence reduced)"
    else:
        reason = None
    return OodVerdict(known=not out, trust=trust, reason=reason, statistics=med)
