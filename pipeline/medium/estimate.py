"""The water's global coefficients measured from the sparse model before training.

A surface point seen from several ranges r changes colour only because of the water: its observed colour is
``I_c(r) = J_c·exp(−β_D,c·r) + B∞_c·(1 − exp(−β_B,c·r))`` (eq. 3 with eq. 6) with one unknown J per point and
per channel, while β_D, β_B, B∞ are shared by every point. Fitting all observations of all points jointly by
robust least squares measures the water without assuming anything about the scene's colours (unlike a
grey-world prior, which makes a sandy seabed grey). The same idea underlies Sea-thru's range-dependent
estimates (Akkaynak & Treibitz 2019); here the multi-view tracks of the sparse model replace its depth map.

The medium starts training at these coefficients, and ``L_attenuation`` keeps the effective global β_D near
them (``pipeline.medium.losses.log_anchor``): the medium networks still learn the spatial modulation of
eqs. 5 and 8 around them. Ranges are distances along the ray in scene units, so the coefficients are in
1/scene-unit, like the medium's.

Which views saw a point: the model's tracks (``Scene.sightings``) where it has them (SfM models, and the
generator's true tracks); otherwise a point is taken as seen in a view when it projects inside the image and
is the nearest (within ``depth_tolerance``) of all points falling in its grid cell, a z-buffer of the sparse
points themselves.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from pipeline.scene.records import Sightings, View

log = logging.getLogger(__name__)


@dataclass
class Observations:
    """Every (point, view) sighting: point index, range along the ray (scene units), observed RGB in [0, 1], and
    the index of the view it was seen in."""

    point: np.ndarray  # [M] int
    range: np.ndarray  # [M] float
    colour: np.ndarray  # [M, 3] float
    view: np.ndarray | None = None  # [M] int, index into the views gathered (None: not recorded)
    xy: np.ndarray | None = None  # [M, 2] where in its image: half-widths / half-heights from the centre
    view_mean: np.ndarray | None = None  # [V, 3] each view's mean colour over its whole image (the images' space)


@dataclass
class MediumEstimate:
    beta_D: tuple[float, float, float]  # 1/scene-unit
    beta_B: tuple[float, float, float]  # 1/scene-unit
    B_inf: tuple[float, float, float]
    n_points: int  # points with at least two sightings (the ones that carry range information)
    n_observations: int
    residual: float  # RMS colour residual of the fit
    range_ratio: float  # 90th / 10th percentile of the ranges used: how much range variation there was
    # Per coefficient (beta_D, beta_B, B_inf) and channel: the standard deviation of its log (beta) or logit
    # (B_inf) after the fit (Laplace approximation), what the data alone would give, and which dominated.
    uncertainty: dict | None = None
    median_range: float = 0.0  # median range of the sightings used (scene units)
    # per view gathered: its exposure log gains [3] (linear light, mean-neutral) when the fit measured them
    # (pipeline.medium.exposure_fit), else None
    log_gains: list | None = None
    exposure_evidence: float | None = None  # how far those gains stood out of their noise (exposure_fit)
    # the in-frame fall-off measured beside the gains (pipeline.medium.exposure_gains): its log field's coefficients
    # [5] (the same in every channel), and its brightest over its darkest value over the frame
    exposure_field: list | None = None
    field_span: float | None = None

    def effect(self, r: float | None = None) -> float:
        """How much this water changes a surface seen at range ``r`` (default: the sightings' median range): the
        mean over channels of (1 − e^(−β_D r)) + B∞(1 − e^(−β_B r)), light removed plus light added — the same
        quantity as the mode probe's learned ``effect``."""
        r = self.median_range if r is None else r
        bd, bb, binf = (np.asarray(x, dtype=np.float64) for x in (self.beta_D, self.beta_B, self.B_inf))
        return float(np.mean((1 - np.exp(-bd * r)) + binf * (1 - np.exp(-bb * r))))

    def to_dict(self) -> dict:
        return asdict(self)


def gather_observations(points: np.ndarray, views: Sequence[View], images: Sequence[np.ndarray | torch.Tensor],
                        sightings: dict[str, Sightings] | None = None, cell_px: int = 4,
                        depth_tolerance: float = 0.03) -> Observations:
    """Every sighting of a sparse point in ``views`` with its colour (the image pixel under it) and range.

    ``images[i]`` is [H, W, 3] at the resolution of ``views[i].camera``. Where ``sightings`` has the view (the
    model's tracks: matched features, so visibility is known), those are used; otherwise the points are
    projected and kept where they are the nearest of their grid cell (the module docstring). The colour is the
    single pixel under the point: averaging a patch mixes in a neighbourhood whose size on the surface changes
    with range, and biased β_D on SfM keypoints of a generated scene (docs/DECISIONS.md, "Numbers behind code
    comments").
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    idx_all, rng_all, col_all, view_all, xy_all = [], [], [], [], []
    means = np.zeros((len(views), 3))
    for k, (v, img) in enumerate(zip(views, images, strict=True)):
        im = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
        H, W = im.shape[:2]
        means[k] = im.reshape(-1, im.shape[-1])[:, :3].mean(axis=0)
        if sightings is not None and v.name in sightings:
            s = sightings[v.name]
            ids, uv = s.point, s.xy * (W / s.width)
            u, w = uv[:, 0], uv[:, 1]
            ok = (u >= 0) & (u < W) & (w >= 0) & (w < H)
            vis, u, w = ids[ok], u[ok], w[ok]
        else:
            vis, u, w = _visible_projections(pts, v, W, H, cell_px, depth_tolerance)
        if vis.size == 0:
            continue
        idx_all.append(vis)
        view_all.append(np.full(vis.size, k, np.int64))
        rng_all.append(np.linalg.norm(pts[vis] - v.center, axis=1))
        col_all.append(im[w.astype(np.int64), u.astype(np.int64)].astype(np.float64))
        xy_all.append(np.stack([2 * u / W - 1, 2 * w / H - 1], 1))
    if not idx_all:
        return Observations(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64),
                            np.zeros((0, 2)), means)
    return Observations(np.concatenate(idx_all), np.concatenate(rng_all), np.concatenate(col_all),
                        np.concatenate(view_all), np.concatenate(xy_all), means)


def _visible_projections(pts: np.ndarray, v: View, W: int, H: int, cell_px: int, depth_tolerance: float,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(point indices, u, v) of the points in front of the camera, inside the image and nearest in their cell."""
    u, w, z = v.project(pts)
    ok = (u >= 0) & (u < W) & (w >= 0) & (w < H)  # NaN (behind the camera) fails
    ids = np.nonzero(ok)[0]
    if ids.size == 0:
        return ids, u[ids], w[ids]
    cell = (w[ids] // cell_px).astype(np.int64) * (W // cell_px + 1) + (u[ids] // cell_px).astype(np.int64)
    zmin = np.full(int(cell.max()) + 1, np.inf)
    np.minimum.at(zmin, cell, z[ids])
    vis = ids[z[ids] <= zmin[cell] * (1 + depth_tolerance)]
    return vis, u[vis], w[vis]


PRIOR_SIGMA_LOG = float(np.log(3.0))  # the water-type prior on log β_D and log β_B: a factor of 3 either way
BACKSCATTER_EXCESS_SIGMA = 0.1  # log β_B may exceed log β_D by about this much before it costs (Prior.penalty)
DATA_DOMINATES = 0.5  # data σ below this share of the prior σ: "measured"; above 1/this: "prior"
THETA_LOW = (-12.0, -12.0, -8.0)  # the fit's bounds on (log β_D, log β_B, logit B∞) (_fit_channel clamps there)
THETA_HIGH = (4.0, 4.0, 3.0)  # logit 3: B∞ 0.953
AT_BOUND = 0.05  # a coefficient this close to its bound (in θ) sits on it
FAIL_PRIOR_SIGMAS = 3.0  # a β this many prior σ from the water type's value (a factor 27) ...
FAIL_DATA_SIGMAS = 2.0  # ... while the data alone cannot exclude the prior's value by this many of their σ: failed


@dataclass
class Prior:
    """Independent normal priors on θ = (log β_D, log β_B, logit B∞) of one channel; sigma inf = none."""

    mean: tuple[float, float, float]
    sigma: tuple[float, float, float]

    def penalty(self, theta: torch.Tensor) -> torch.Tensor:
        m = torch.as_tensor(self.mean, dtype=theta.dtype)
        w = 1.0 / torch.as_tensor(self.sigma, dtype=theta.dtype) ** 2  # 0 where sigma is inf
        # Physics: backscatter grows with the scattering coefficient b, the direct signal decays with the beam
        # attenuation c = a + b >= b, so β_B above β_D is unphysical (Akkaynak & Treibitz 2018 relate β_B to b and
        # β_D to c). Without this a narrow range spread explains a colour cast as a veil that saturates with
        # range (β_B large) while nothing is attenuated (β_D -> 0).
        excess = torch.relu(theta[1] - theta[0]) / BACKSCATTER_EXCESS_SIGMA
        return (w * (theta - m) ** 2).sum() + excess**2


def water_type_prior(optical_depth: float, r_med: float) -> Prior:
    """Where the classified water type puts one channel (its optical depth at the sightings' median range):
    β_D and β_B around optical_depth / r_med, a factor of 3 either way; no prior on B∞ (the veil's colour is
    what the photos show best). Scale-free: the optical depth needs no metric scale."""
    mu = float(np.log(max(optical_depth, 1e-3) / r_med))
    return Prior((mu, mu, 0.0), (PRIOR_SIGMA_LOG, PRIOR_SIGMA_LOG, float("inf")))


def _channel_loss(theta: torch.Tensor, inv: torch.Tensor, n_points: int, r: torch.Tensor, I: torch.Tensor,  # noqa: E741
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares misfit of one channel for θ = (log β_D, log β_B, logit B∞), with every point's J
    eliminated in closed form (J_p = Σ a·(I − b) / Σ a², clamped to [0, 1]): variable projection.
    Returns (mean squared residual, J per point)."""
    a = torch.exp(-torch.exp(theta[0]) * r)
    b = torch.sigmoid(theta[2]) * (1 - torch.exp(-torch.exp(theta[1]) * r))
    num = torch.zeros(n_points, dtype=r.dtype).index_add(0, inv, a * (I - b))
    den = torch.zeros(n_points, dtype=r.dtype).index_add(0, inv, a * a)
    J = (num / den.clamp(min=1e-12)).clamp(0, 1)
    return ((J[inv] * a + b - I) ** 2).mean(), J


def _channel_loss_grad(theta: np.ndarray, inv: np.ndarray, n_points: int, r: np.ndarray, I: np.ndarray,  # noqa: E741
                       ) -> tuple[float, np.ndarray]:
    """:func:`_channel_loss`'s misfit and its gradient in θ, in closed form (numpy; :func:`_channel_loss` under
    autograd is the reference twin). Each J_p minimises the misfit for fixed θ (or sits at a clamp, where it does
    not move), so ∂misfit/∂J = 0 or dJ/dθ = 0 and the gradient is the partial in θ at fixed J (variable
    projection's envelope): one pass over the sightings, no autograd graph. The fit calls it thousands of times."""
    bd, bb = np.exp(theta[0]), np.exp(theta[1])
    sig = 1.0 / (1.0 + np.exp(-theta[2]))
    a = np.exp(-bd * r)
    eb = np.exp(-bb * r)
    b = sig * (1.0 - eb)
    num = np.bincount(inv, a * (I - b), minlength=n_points)
    den = np.bincount(inv, a * a, minlength=n_points)
    Ja = np.clip(num / np.maximum(den, 1e-12), 0.0, 1.0)[inv] * a
    e = Ja + b - I
    g = np.array([-bd * (e * Ja) @ r, sig * bb * (e * eb) @ r, sig * (1.0 - sig) * (e @ (1.0 - eb))])
    return float(e @ e) / len(r), g * (2.0 / len(r))


def _fit_channel(inv: torch.Tensor, n_points: int, r: torch.Tensor, I: torch.Tensor,  # noqa: E741
                 starts: Sequence[tuple[float, float, float]], penalty=None) -> tuple[torch.Tensor, float]:
    """Minimise the channel's misfit (+ ``penalty(θ)``) by L-BFGS from each start (β_D, β_B, B∞); the best.

    The misfit and its gradient come from :func:`_channel_loss_grad`, only the 3-parameter penalty goes through
    autograd: the misfit has a long, nearly flat valley where β_B and B∞ trade off (a veil not saturating over
    the ranges seen fixes only about B∞·β_B), and L-BFGS spends most of its 250 evaluations per start along it
    (2,600 in a 24-view job: 4.4 s under autograd, half that in closed form). Gauss-Newton (Levenberg-Marquardt,
    with J's dependence on θ in the Jacobian) was tried and rejected: from some starts it stepped onto the plateau
    of a saturated veil or onto B∞'s bound and stayed, at misfits 30x L-BFGS's."""
    best: tuple[torch.Tensor, float] | None = None
    inv_np, r_np, I_np = inv.numpy(), r.numpy(), I.numpy()

    def objective(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loss, grad = _channel_loss_grad(theta.detach().numpy(), inv_np, n_points, r_np, I_np)
        value, g = torch.tensor(loss, dtype=torch.float64), torch.from_numpy(grad)
        if penalty is not None:
            with torch.enable_grad():
                t = theta.detach().clone().requires_grad_(True)
                p = penalty(t)
                (gp,) = torch.autograd.grad(p, t)
            value, g = value + p.detach(), g + gp
        return value, g

    for s in starts:
        theta = torch.tensor([np.log(s[0]), np.log(s[1]), float(np.log(s[2] / (1 - s[2])))], dtype=torch.float64,
                             requires_grad=True)
        opt = torch.optim.LBFGS([theta], lr=1, max_iter=200, tolerance_grad=1e-12, tolerance_change=1e-15,
                                line_search_fn="strong_wolfe")

        def closure(theta: torch.Tensor = theta) -> torch.Tensor:
            loss, theta.grad = objective(theta)
            return loss

        opt.step(closure)  # type: ignore[arg-type]
        with torch.no_grad():
            theta.clamp_(min=torch.tensor(THETA_LOW, dtype=torch.float64),
                         max=torch.tensor(THETA_HIGH, dtype=torch.float64))
            loss = float(objective(theta)[0])
        if best is None or loss < best[1]:
            best = (theta.detach().clone(), loss)
    assert best is not None
    return best


def _data_precision(theta: torch.Tensor, inv: torch.Tensor, n_points: int, r: torch.Tensor, I: torch.Tensor,  # noqa: E741
                    s2: float, penalty=None) -> np.ndarray:
    """Precision of θ (Laplace approximation): M / (2 s²) · ∇²(mean squared residual [+ ``penalty``]) at θ,
    the data's alone or, with the prior's penalty, the posterior's. [3, 3]"""

    def objective(t: torch.Tensor) -> torch.Tensor:
        loss = _channel_loss(t, inv, n_points, r, I)[0]
        return loss if penalty is None else loss + penalty(t)

    H = torch.autograd.functional.hessian(objective, theta.detach())
    return H.numpy() * len(r) / (2.0 * max(s2, 1e-12))


def _sigmas(precision: np.ndarray, rel_tol: float = 1e-9) -> np.ndarray:
    """Marginal standard deviations from a (symmetric) precision matrix. A parameter with a share in a
    direction the precision does not constrain (eigenvalue ≤ ``rel_tol`` x the largest, or negative: the fit
    sits at a kink or a bound) gets inf; the others come from the pseudo-inverse on the constrained subspace,
    so a well-measured β_D keeps its σ when β_B and B∞ trade off against each other."""
    p = 0.5 * (precision + precision.T)
    if not np.all(np.isfinite(p)):
        return np.full(len(p), np.inf)
    w, v = np.linalg.eigh(p)
    good = w > rel_tol * max(float(np.abs(w).max()), 1e-300)
    cov = (v[:, good] / w[good]) @ v[:, good].T
    free = (np.abs(v[:, ~good]) > 1e-3).any(axis=1)
    return np.where(free, np.inf, np.sqrt(np.clip(np.diag(cov), 0, None)))


def _source(data_sigma: float, prior_sigma: float) -> str:
    """Which determined a coefficient: ``measured`` (the data's σ well below the prior's), ``prior``,
    ``measured+prior``, or ``not determined`` (neither the data nor a prior pin it)."""
    if not np.isfinite(data_sigma):
        return "prior" if np.isfinite(prior_sigma) else "not determined"
    if not np.isfinite(prior_sigma) or data_sigma < DATA_DOMINATES * prior_sigma:
        return "measured"
    return "prior" if data_sigma > prior_sigma / DATA_DOMINATES else "measured+prior"


def fit_failure(theta: torch.Tensor, pr: Prior, data_sigma: np.ndarray) -> str | None:
    """Why one channel's fit is not a measurement, or None when it is one.

    - A coefficient on the fit's bound: the optimum lies outside what the model can express. On real green
      water (RUIE, a video whose exposure changes frame to frame) least squares put B∞ on its upper bound (0.95,
      grey) and β_D at 0.001 of a unit, explaining the frames' colour changes as a veil that never saturates;
      read as water, that was "no water" and the job trained plain splatting on green photos.
    - A β more than ``FAIL_PRIOR_SIGMAS`` prior σ from the water type's value while the data alone do not
      exclude that value (it lies within ``FAIL_DATA_SIGMAS`` of their σ): the departure is the noise's.
    A β measured small with data that do exclude the prior (a scene without water, seen over a wide range of
    distances) is a measurement, and stands."""
    t = theta.detach().numpy()
    names = ("β_D", "β_B", "B∞")
    for k in range(3):
        if t[k] <= THETA_LOW[k] + AT_BOUND or t[k] >= THETA_HIGH[k] - AT_BOUND:
            value = float(np.exp(t[k])) if k < 2 else float(1 / (1 + np.exp(-t[k])))
            side = "lower" if t[k] <= THETA_LOW[k] + AT_BOUND else "upper"
            return f"{names[k]} = {value:.3g} sits on the fit's {side} bound: the colours are not explained by water"
    for k in range(2):
        z_prior = abs(t[k] - pr.mean[k]) / pr.sigma[k]
        z_data = abs(t[k] - pr.mean[k]) / data_sigma[k] if np.isfinite(data_sigma[k]) else 0.0
        if z_prior > FAIL_PRIOR_SIGMAS and z_data < FAIL_DATA_SIGMAS:
            return (f"{names[k]} = {np.exp(t[k]):.3g} is {z_prior:.1f} prior σ from the water type's "
                    f"{np.exp(pr.mean[k]):.3g}, which the data alone cannot exclude ({z_data:.1f} of their σ)")
    return None


def _prior_fallback(inv: torch.Tensor, n_points: int, r: torch.Tensor, I: torch.Tensor, pr: Prior,  # noqa: E741
                    ) -> torch.Tensor:
    """θ of a channel whose fit failed: β_D and β_B at the water type's prior, B∞ refitted alone with them held
    (well posed: J·A and the veil trade off only through β), or, should that land on a bound too, the level that
    puts the veil at the 5th percentile of the sightings' colours at their median range."""
    pin = Prior((pr.mean[0], pr.mean[1], 0.0), (1e-3, 1e-3, float("inf")))
    r_med = float(r.median())
    veil = 1.0 - float(np.exp(-np.exp(pr.mean[1]) * r_med))
    start = float(np.clip(float(I.quantile(0.05)) / max(veil, 1e-3), 0.02, 0.9))
    theta, _ = _fit_channel(inv, n_points, r, I, [(np.exp(pr.mean[0]), np.exp(pr.mean[1]), start)],
                            penalty=lambda t: pin.penalty(t) * float(I.var()) / max(len(r), 1))
    theta = theta.clone()
    theta[0], theta[1] = pr.mean[0], pr.mean[1]
    if theta[2] >= THETA_HIGH[2] - AT_BOUND or theta[2] <= THETA_LOW[2] + AT_BOUND:
        theta[2] = float(np.log(start / (1 - start)))
    return theta


def fit_medium(obs: Observations, init_optical_depth: Sequence[float] = (0.8, 0.3, 0.25),
               min_points: int = 50, prior: bool = True) -> MediumEstimate | None:
    """Fit, per channel, of β_D, β_B, B∞ (shared) and J (per point, eliminated in closed form) to the
    sightings; None when the sightings cannot say anything about range (fewer than ``min_points`` points seen
    twice).

    First the least-squares fit from a few starts, which gives the residual variance s². Then, with ``prior``,
    the maximum a posteriori fit under the water type's prior (``water_type_prior``: ``init_optical_depth`` is
    the classified type's optical depth at the median range): it moves a coefficient only where the data do
    not pin it. A narrow range spread (real footage: the same patch seen from 1.5-3 m) cannot separate
    attenuation from veil, and the least-squares fit then lands on a bound (β_D = 0: "no attenuation"); the
    prior keeps it at the water type's value instead. Each coefficient's uncertainty (σ of its log, Laplace
    approximation) is reported with and without the prior, and which of the two dominated."""
    counts = np.bincount(obs.point) if obs.point.size else np.zeros(0, np.int64)
    if int((counts >= 2).sum()) < min_points:
        log.info("medium estimate: only %d points seen twice; skipped", int((counts >= 2).sum()))
        return None
    keep = counts[obs.point] >= 2
    pid, inv = np.unique(obs.point[keep], return_inverse=True)
    inv_t = torch.as_tensor(inv)
    r = torch.as_tensor(obs.range[keep], dtype=torch.float64)
    colour = torch.as_tensor(obs.colour[keep], dtype=torch.float64)
    r_med = float(r.median())
    coef, sq = [], []
    names = ("beta_D", "beta_B", "B_inf")
    unc: dict[str, dict[str, list]] = {k: {"sigma": [], "data_sigma": [], "source": []} for k in names}
    dof = max(int(keep.sum()) - len(pid) - 3, 1)
    failed: list[str | None] = []  # per channel: why the fit failed (fit_failure), None where it held
    for c in range(3):
        tau = max(float(init_optical_depth[c]), 1e-3)
        binf0 = float(colour[:, c].quantile(0.05).clamp(0.02, 0.9))
        starts = [(k * tau / r_med, k * tau / r_med, binf0) for k in (0.5, 1.0, 2.0)]
        theta, loss = _fit_channel(inv_t, len(pid), r, colour[:, c], starts)
        s2 = loss * int(keep.sum()) / dof
        pr = water_type_prior(tau, r_med)
        # The data's own uncertainty, at the least-squares optimum.
        data = _sigmas(_data_precision(theta, inv_t, len(pid), r, colour[:, c], s2, None))
        post = data
        if prior:
            scale = s2 / int(keep.sum())  # the prior in units of the mean squared residual (module docstring)
            t0 = tuple(float(x) for x in (theta[0].exp(), theta[1].exp(), theta[2].sigmoid()))
            p0 = (tau / r_med, tau / r_med, t0[2])

            def penalty(t: torch.Tensor, pr: Prior = pr, scale: float = scale) -> torch.Tensor:
                return scale * pr.penalty(t)

            theta, _ = _fit_channel(inv_t, len(pid), r, colour[:, c], [t0, p0], penalty=penalty)
            loss = float(_channel_loss(theta, inv_t, len(pid), r, colour[:, c])[0])
            post = _sigmas(_data_precision(theta, inv_t, len(pid), r, colour[:, c], s2, penalty))
        why = fit_failure(theta, pr, data) if prior else None
        if why is not None:  # a failed measurement: the water type's prior, never "no water" (module docstring)
            log.warning("medium estimate, channel %s: %s; the water type's prior is used", "RGB"[c], why)
            theta = _prior_fallback(inv_t, len(pid), r, colour[:, c], pr)
            loss = float(_channel_loss(theta, inv_t, len(pid), r, colour[:, c])[0])
            post = np.array([pr.sigma[0], pr.sigma[1], np.inf])
        failed.append(why)
        for k, name in enumerate(names):
            unc[name]["sigma"].append(float(post[k]) if np.isfinite(post[k]) else None)  # None: not determined
            unc[name]["data_sigma"].append(float(data[k]) if np.isfinite(data[k]) else None)
            unc[name]["source"].append("prior" if why is not None and k < 2 else
                                       "refit (β from the prior)" if why is not None else
                                       _source(float(data[k]), pr.sigma[k] if prior else float("inf")))
        coef.append((float(theta[0].exp()), float(theta[1].exp()), float(theta[2].sigmoid())))
        sq.append(loss)
    unc["scale"] = {"beta_D": "log", "beta_B": "log", "B_inf": "logit"}  # type: ignore[assignment]
    unc["failed"] = failed  # type: ignore[assignment]
    unc["prior"] = {"optical_depth": [float(x) for x in init_optical_depth], "median_range": r_med,  # type: ignore[assignment]
                    "sigma_log": PRIOR_SIGMA_LOG if prior else None}
    q10, q90 = np.percentile(obs.range[keep], [10, 90])
    est = MediumEstimate(
        beta_D=tuple(c[0] for c in coef), beta_B=tuple(c[1] for c in coef),  # type: ignore[arg-type]
        B_inf=tuple(c[2] for c in coef), n_points=len(pid), n_observations=int(keep.sum()),  # type: ignore[arg-type]
        residual=float(np.sqrt(np.mean(sq))), range_ratio=float(q90 / max(q10, 1e-9)), uncertainty=unc,
        median_range=r_med)
    log.info("medium estimate from %d points / %d sightings: beta_D %s beta_B %s B_inf %s (rms %.4f; beta_D %s)",
             est.n_points, est.n_observations, np.round(est.beta_D, 3), np.round(est.beta_B, 3),
             np.round(est.B_inf, 3), est.residual, unc["beta_D"]["source"])
    return est
