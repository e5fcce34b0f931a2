"""The physics per pixel: J = (I − B(r)) / A(r), with a per-channel gain cap and a confidence map.

Rules (docs/DECISIONS.md, "Restoring the originals"):
- With the model's own restored radiance J_m of the pixel (``prior``: the multi-view reconstruction, rendered
  and sampled into the photo; what the restore stage passes): the least-squares J of
  (I − B − A·J)² + λ²·(J − J_m)² per channel:
      J = (A·(I − B) + λ²·J_m) / (A² + λ²),
  λ² = σ_n² / σ_d², the photo's noise against what the model lacks, measured per photo and channel
  (:func:`prior_weights`), never below (1/(2·max_gain))².
  With what the model lacks measured as a covariance across channels, Σ_d (``detail_cov``,
  :func:`detail_covariance`), the three channels are solved together, the posterior mean under that prior:
      J = J_m + G·(I − B − A·J_m),   G = Σ_d·A·(A·Σ_d·A + N)⁻¹,   N = diag(λ²·diag Σ_d),
  which is the per-channel rule above when Σ_d is diagonal; each row of G is scaled to Σ_k |G_ck| ≤ ``max_gain``.
  That joint answer replaces only the model's share m_c = λ_c²/(A_c² + λ_c²) of each channel; the photo's share
  keeps the per-channel gain (:func:`gain_matrix`). Where one channel's photo signal is weak (red in turbid
  water) its missing detail is taken from the channels that see it, as far as they are measured to vary
  together; where a channel's photo is strong it is its own (the joint answer alone cost clear and medium water's
  held-out photos 0.3-0.4 dB: the channels' "detail" includes the water's error, which red carries most).
  Where the water lets light through (A ≫ λ) this is (I − B)/A, the photo's own detail; where it does not (far
  range, red in turbid water) the photo's signal is below its noise and J leans on the model, which saw that
  surface from nearer views. The gain dJ/dI = A / (A² + λ²) is at most 1/(2λ) ≤ ``max_gain``: no channel is
  ever amplified more.
- Without a prior (a bare photo and a medium): the gain cap A_eff = max(A, 1/max_gain) per channel.
- Confidence is the expected error e of the restored pixel turned into [0, 1]: c = τ² / (τ² + mean_c e_c²),
  τ = :data:`CONFIDENCE_ERROR` (c = 1/2 where the expected error is τ, in the output's sRGB units); 0 where
  there is no surface. e_c (:func:`expected_error`) propagates what is known to be uncertain through
  J = (I − B)/A: the water's coefficients (σ of log k_A, log k_B and logit B∞, the fit's posterior from
  ``pipeline.medium.estimate``: an error δ in log k_A scales J by e^(k_A·r·δ), one in B shifts it by δB/A)
  the photo's noise times the gain, what the model lacks through its share of the pixel, and the photo's local
  disagreement with the model beyond its noise over A² (:func:`local_misfit`: where it is large the model's
  depth, water or J is wrong there). It grows with range, with J, where A is small and where the photo and the
  model disagree, which is where the restorations measured wrong (docs/DECISIONS.md, "Confidence as expected
  error").
- No surface (alpha < 0.5, outside the render camera, or z ≤ 0): nothing is invented, J is the photo's pixel
  unchanged.
- J is clipped to [0, 1]; the count of surface pixels with any channel clipped is returned.
- ``space``: "srgb" applies the model to the stored (sRGB-encoded) values, as the model was trained;
  "linear" converts the photo to linear light first and J back to sRGB after (the coefficients must then be
  linear-light ones).
"""

from __future__ import annotations

import numpy as np

from pipeline.restore.guided import _box_mean_reference
from pipeline.restore.records import MediumMaps
from pipeline.scene.colour import linear_to_srgb, srgb_to_linear

SPACES = ("srgb", "linear")
# λ² never above this: the photo keeps a share A²/(A² + 1) of every pixel (half where the water takes nothing),
# whatever the measurement says. Texture finer than a pixel looks like noise to it (white, no lag-1
# correlation): on bench/restore.py's frame, whose texture has a white component, it measured λ² = 8.5e7.
MAX_PRIOR_WEIGHT = 1.0
CONFIDENCE_ERROR = 0.1  # τ: the expected error (sRGB, [0, 1]) at which the confidence is 1/2
# The water's uncertainty when nothing measured it (rows: log k_A, log k_B, logit B∞): the water type's prior
# (pipeline.medium.estimate.PRIOR_SIGMA_LOG, a factor of 3) on both coefficients, and 1 on the veil's logit.
UNMEASURED_SIGMA = np.array([[np.log(3.0)] * 3, [np.log(3.0)] * 3, [1.0] * 3])


def _check(max_gain: float, space: str) -> None:
    if not max_gain > 1:
        raise ValueError(f"max_gain must be > 1, got {max_gain}")
    if space not in SPACES:
        raise ValueError(f"space must be one of {SPACES}, got {space!r}")


def _k(k: np.ndarray) -> np.ndarray:
    """A coefficient as float32 [n, W, 3] or [1, 1, 3], NaN → 0."""
    k = np.nan_to_num(np.asarray(k, np.float32), nan=0.0)
    return np.ascontiguousarray(k.reshape(1, 1, 3) if k.ndim == 1 else k)


def dewater(img: np.ndarray, r: np.ndarray, surface: np.ndarray, k_A: np.ndarray, k_B: np.ndarray,
            B_inf: np.ndarray, *, max_gain: float = 8.0, space: str = "srgb", out_max: int = 255,
            scale: float | None = None, prior: np.ndarray | None = None, lam2: np.ndarray | None = None,
            sigma: np.ndarray | None = None, noise2: np.ndarray | None = None, detail2: np.ndarray | None = None,
            detail_cov: np.ndarray | None = None, misfit: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray, int]:
    """Restore a block of pixels.

    Args:
        img: [n, W, 3] the photo, uint8/uint16 or float in [0, 1].
        r: [n, W] range along the ray (scene units); surface: [n, W] bool.
        k_A, k_B: [3] or [n, W, 3] effective coefficients; B_inf: [3].
        max_gain: the per-channel gain cap (> 1); space: "srgb" | "linear"; out_max: 255 → uint8 J, 65535 →
        uint16 J.
        scale: multiplies img to [0, 1]; default from its dtype (1/255, 1/65535, 1).
        prior: [n, W, 3] the model's J of each pixel in the physics' space (linear light for "linear"), or None.
        lam2: [3] the prior's weight λ² per channel (:func:`prior_weights`); default and floor (0.5/max_gain)².
        sigma: [3, 3] the water's uncertainty (rows log k_A, log k_B, logit B∞; columns channels); default
        :data:`UNMEASURED_SIGMA`. noise2: [3] the photo's noise variance (physics space); detail2: [3] what the
        model lacks, as a variance of J (:meth:`pipeline.restore.frame.FrameRestorer.calibrate`); defaults 0.
        detail_cov: [3, 3] what the model lacks as a covariance of J across channels (:func:`detail_covariance`;
        it replaces ``detail2``): the channels are solved together. None: each channel alone.
        misfit: [n, W, 3] the mean of the squared residual e = I − B − A·J_m around each pixel
        (:func:`local_misfit`; used with a prior): its excess over ``noise2``, over A_eff², enters the expected
        error. None: 0.
    Returns (J [n, W, 3] uint8 or uint16, confidence [n, W] float32 in [0, 1], clipped pixel count)."""
    # lazy: numba (and torch) load at the first kernel call; the numpy twins and constants here need neither
    from pipeline.restore._kernels import dewater as kernel

    _check(max_gain, space)
    if scale is None:
        scale = 1.0 / np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else 1.0
    J = np.empty(img.shape, np.uint8 if out_max == 255 else np.uint16)
    conf, clipped = kernel(np.ascontiguousarray(img), float(scale), np.ascontiguousarray(r, np.float32),
                           np.ascontiguousarray(surface, np.bool_), _k(k_A), _k(k_B),
                           np.asarray(B_inf, np.float64).reshape(3), float(max_gain), space == "linear", J,
                           int(out_max), np.ascontiguousarray(prior if prior is not None else np.zeros((1, 1, 3)),
                                                              np.float32), prior is not None,
                           _lam2(lam2, max_gain), _sigma(sigma), _variance(noise2), *_covariances(detail2, detail_cov),
                           _misfit(misfit), float(CONFIDENCE_ERROR))
    return J, conf, int(clipped)


def _misfit(misfit: np.ndarray | None) -> np.ndarray:
    """The local misfit as float32 [n, W, 3], or zeros [1, 1, 3] (none). NaN is read as 0 by the kernel (a
    full-frame nan_to_num here cost a pass over 27 M pixels)."""
    if misfit is None:
        return np.zeros((1, 1, 3), np.float32)
    return np.ascontiguousarray(misfit, np.float32)


def local_misfit(img: np.ndarray, r: np.ndarray, surface: np.ndarray, k_A: np.ndarray, k_B: np.ndarray,
                 B_inf: np.ndarray, prior: np.ndarray, radius: int, *, space: str = "srgb",
                 scale: float | None = None, step: int = 1, row0: int = 0,
                 out_rows: tuple[int, int] | None = None) -> np.ndarray:
    """The photo's local disagreement with the model: the mean of e² = (I − B − A·J_m)² per channel over the
    surface pixels around each pixel, weighted by a tent of support ``radius`` (two box means; clipped to the
    rows given), 0 where the window holds no surface. Measured on every ``step``-th pixel (rows at multiples of
    ``step`` counted from the frame's top, ``row0`` being the global row of ``img``'s first row; columns from
    0), the window in those samples, and interpolated bilinearly to ``out_rows`` (local rows [a, b); default all).
    Arguments as :func:`dewater`. Returns [b − a, W, 3] float32 (physics space).

    What it is for (docs/DECISIONS.md, "Confidence as expected error"): the residual is the photo's noise plus
    A·(what the model lacks); where it is large over a neighbourhood, the model's J, depth or water is wrong
    there, and the restored pixel, which takes its depth and water from the model whatever its share, is
    wrong too: on held-out photos that is most of the error the per-photo terms could not place."""
    # lazy: numba (and torch) load at the first kernel call; the numpy twins and constants here need neither
    from pipeline.restore._kernels import box_mean, misfit_terms, misfit_upsample

    if scale is None:
        scale = 1.0 / np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else 1.0
    q = max(1, int(step))
    first = (-int(row0)) % q
    a, b = out_rows if out_rows is not None else (0, img.shape[0])
    terms = misfit_terms(np.ascontiguousarray(img), float(scale), np.ascontiguousarray(r, np.float32),
                         np.ascontiguousarray(surface, np.bool_), _k(k_A), _k(k_B),
                         np.asarray(B_inf, np.float64).reshape(3), space == "linear",
                         np.ascontiguousarray(prior, np.float32), first, q)
    for rad in _tent(max(1, round(radius / q))):
        if rad:
            terms = box_mean(terms, rad)
    return misfit_upsample(terms, first, q, a, b - a, img.shape[1])


def _tent(radius: int) -> tuple[int, int]:
    """The radii of two box means that make a tent of support ``radius`` (a single box left square speckles
    around isolated residuals in the map: a sand grain the model lacks)."""
    r1 = int(radius) // 2
    return r1, int(radius) - r1


def local_misfit_reference(img: np.ndarray, r: np.ndarray, surface: np.ndarray, medium: MediumMaps,
                           prior: np.ndarray, radius: int, *, space: str = "srgb", step: int = 1, row0: int = 0,
                           out_rows: tuple[int, int] | None = None) -> np.ndarray:
    """Slow twin of :func:`local_misfit` (numpy float64, each box mean and the interpolation by explicit
    loops). img float [n, W, 3] in [0, 1]. Returns [b − a, W, 3]."""
    q = max(1, int(step))
    first = (-int(row0)) % q
    kA, kB = (np.asarray(k, np.float64)[first::q, ::q] if np.ndim(k) == 3 else k for k in (medium.k_A, medium.k_B))
    x, _, A, B = _physics_reference(np.asarray(img)[first::q, ::q], np.asarray(r)[first::q, ::q], kA, kB,
                                    medium.B_inf, space)
    s = np.asarray(surface, bool)[first::q, ::q]
    e2 = np.where(s[..., None], (x - B - A * np.asarray(prior, np.float64)[first::q, ::q]) ** 2, 0.0)
    terms = [e2[..., 0], e2[..., 1], e2[..., 2], s.astype(np.float64)]
    for rad in _tent(max(1, round(radius / q))):
        if rad:
            terms = [_box_mean_reference(t, rad) for t in terms]
    m = np.stack(terms)  # [4, nc, wc]
    a, b = out_rows if out_rows is not None else (0, np.shape(img)[0])
    nc, wc = m.shape[1:]
    out = np.zeros((b - a, np.shape(img)[1], 3))
    for ii, i in enumerate(range(a, b)):
        y = min(max((i - first) / q, 0.0), nc - 1.0)
        y0 = min(int(y), max(nc - 2, 0))
        y1, t = min(y0 + 1, nc - 1), y - y0
        for j in range(out.shape[1]):
            xx = min(j / q, wc - 1.0)
            x0 = min(int(xx), max(wc - 2, 0))
            x1, u = min(x0 + 1, wc - 1), xx - x0
            w = np.array([(1 - t) * (1 - u), (1 - t) * u, t * (1 - u), t * u])
            v = w[0] * m[:, y0, x0] + w[1] * m[:, y0, x1] + w[2] * m[:, y1, x0] + w[3] * m[:, y1, x1]
            if v[3] > 1e-12:
                out[ii, j] = v[:3] / v[3]
    return out


def _covariances(detail2: np.ndarray | None, detail_cov: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(the prior's covariance shape the estimate uses, what the model lacks for the expected error), [3, 3]
    float64 each: (Σ_d, Σ_d) with ``detail_cov``; else (identity, diag(detail2)), the channels apart."""
    if detail_cov is None:
        return np.eye(3), np.diag(_variance(detail2))
    c = _psd(detail_cov)
    return c, c


def _psd(c: np.ndarray, floor: float = 1e-12) -> np.ndarray:
    """The symmetric part of ``c`` [3, 3] with its eigenvalues floored at ``floor``: a valid covariance."""
    c = np.nan_to_num(np.asarray(c, np.float64).reshape(3, 3))
    w, U = np.linalg.eigh(0.5 * (c + c.T))
    return np.ascontiguousarray((U * np.maximum(w, floor)) @ U.T)


def detail_covariance(residual_lag: np.ndarray, a_cross: np.ndarray) -> np.ndarray:
    """What the model lacks as a covariance of J across channels, Σ_d [3, 3], from a photo's residual
    e = A·d + n (:func:`prior_weights`): the lag-1 cross products E[e_c,x · e_k,x+1] (``residual_lag`` [3, 3])
    keep A_c·A_k·cov(d_c, d_k) and lose the white noise; over E[A_c·A_k] (``a_cross`` [3, 3]). Symmetrised and
    made positive definite; its diagonal is :func:`noise_and_detail`'s σ_d²."""
    lag = np.asarray(residual_lag, np.float64).reshape(3, 3)
    return _psd(0.5 * (lag + lag.T) / np.maximum(np.asarray(a_cross, np.float64).reshape(3, 3), 1e-12))


def _sigma(sigma: np.ndarray | None) -> np.ndarray:
    """[3, 3] float64, finite and ≥ 0; None or a non-finite entry → :data:`UNMEASURED_SIGMA`'s."""
    if sigma is None:
        return UNMEASURED_SIGMA.copy()
    s = np.asarray(sigma, np.float64).reshape(3, 3)
    return np.ascontiguousarray(np.where(np.isfinite(s), np.maximum(s, 0.0), UNMEASURED_SIGMA))


def _variance(v: np.ndarray | None) -> np.ndarray:
    """A per-channel variance [3] float64, finite and ≥ 0; None → 0."""
    return np.zeros(3) if v is None else np.maximum(np.nan_to_num(np.asarray(v, np.float64).reshape(3)), 0)


def expected_error(J: np.ndarray, r: np.ndarray, k_A: np.ndarray, k_B: np.ndarray, B_inf: np.ndarray,
                   A_eff: np.ndarray, noise_var: np.ndarray | float = 0.0, model_var: np.ndarray | float = 0.0,
                   sigma: np.ndarray | None = None) -> np.ndarray:
    """The expected error of a restored value J (physics space, [0, 1]) per channel, first order:
    e² = (J·k_A·r·σ_A)² + ((B∞·k_B·r·e^(−k_B r)·σ_B)² + (B∞(1 − B∞)(1 − e^(−k_B r))·σ_∞)²) / A_eff²
         + noise_var + model_var:
    an error δ in log k_A scales J by e^(k_A·r·δ); one in log k_B or logit B∞ moves B, and J by δB/A_eff;
    ``noise_var`` is the photo's noise through the gains (σ_n²/A_eff² without a prior; Σ_k G_ck²·σ_n,k² with
    one), ``model_var`` what the model lacks through I − G·A (:func:`dewater_reference`). J, r[..., None], k_A,
    k_B, A_eff and the variances broadcast to [..., 3]. Float64 numpy; the reference for the kernel's loop."""
    s = _sigma(sigma)
    oA = np.minimum(np.asarray(k_A, np.float64) * r, 80.0)
    oB = np.minimum(np.asarray(k_B, np.float64) * r, 80.0)
    dA = J * oA * s[0]
    dB = (B_inf * oB * np.exp(-oB) * s[1]) ** 2 + (B_inf * (1 - B_inf) * -np.expm1(-oB) * s[2]) ** 2
    return np.sqrt(dA**2 + dB / A_eff**2 + noise_var + model_var)


def confidence_from_error(J: np.ndarray, e: np.ndarray, linear: bool) -> np.ndarray:
    """τ² / (τ² + mean_c e_c²) with e in the output's units: for ``linear`` physics, the sRGB values J ± e span
    (the larger side), else e (capped at 1). J, e [..., 3] → [...]."""
    if linear:
        s0 = linear_to_srgb(J)
        e = np.maximum(linear_to_srgb(np.minimum(J + e, 1.0)) - s0, s0 - linear_to_srgb(np.maximum(J - e, 0.0)))
    else:
        e = np.minimum(e, 1.0)
    return CONFIDENCE_ERROR**2 / (CONFIDENCE_ERROR**2 + (e**2).mean(-1))


def _lam2(lam2: np.ndarray | None, max_gain: float) -> np.ndarray:
    """λ² per channel [3] float64, never below (0.5 / max_gain)² (so the gain stays ≤ max_gain)."""
    floor = (0.5 / max_gain) ** 2
    if lam2 is None:
        return np.full(3, floor)
    return np.maximum(np.nan_to_num(np.asarray(lam2, np.float64).reshape(3), nan=floor), floor)


def prior_weights(residual_sq: np.ndarray, residual_lag: np.ndarray, a_sq: np.ndarray, max_gain: float
                  ) -> np.ndarray:
    """λ² per channel from a photo's residual against the model, e = I − (A·J_m + B) = A·d + n: d what the
    model lacks (spatially correlated: detail, colour error), n the photo's noise (white). The lag-1 products
    of e (horizontal neighbours) keep A²σ_d² and lose the noise, so σ_n² = E[e²] − E[e_x e_x+1] and
    σ_d² = E[e_x e_x+1] / E[A²]; the least-squares weight is λ² = σ_n² / σ_d² (floored at (0.5/max_gain)²).

    Args (each [3], means over the surface pixels of the sampled rows): residual_sq E[e²], residual_lag
    E[e_x·e_x+1], a_sq E[A²]. Returns lam2 [3], at most :data:`MAX_PRIOR_WEIGHT`."""
    noise, detail = noise_and_detail(residual_sq, residual_lag, a_sq)
    return _lam2(np.minimum(noise / detail, MAX_PRIOR_WEIGHT), max_gain)


def noise_and_detail(residual_sq: np.ndarray, residual_lag: np.ndarray, a_sq: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(σ_n², σ_d²) per channel from a photo's residual against the model (:func:`prior_weights`): the white
    part E[e²] − E[e_x e_x+1] is the photo's noise, the correlated part over E[A²] what the model lacks (as a
    variance of J). Each floored at 1e-12."""
    noise = np.maximum(residual_sq - residual_lag, 1e-12)
    detail = np.maximum(residual_lag, 1e-12) / np.maximum(a_sq, 1e-12)
    return noise, detail


def gain_matrix(A: np.ndarray, cov: np.ndarray, lam2: np.ndarray, max_gain: float) -> np.ndarray:
    """The gains G [..., 3, 3] of J = J_m + G·(I − B − A·J_m) per pixel (A [..., 3]; cov [3, 3] the prior's
    covariance across channels; lam2 [3]): the joint posterior's cov·A·(A·cov·A + N)⁻¹, N = diag(λ²·diag cov),
    each row scaled to Σ_k |G_ck| ≤ max_gain, taken for the model's share m_c = λ_c²/(A_c² + λ_c²) of channel c
    only; the photo's share keeps the per-channel gain A_c/(A_c² + λ_c²). A diagonal cov gives the per-channel
    rule. Numpy float64: the reference for the kernel's ``_gain_matrix``."""
    A = np.asarray(A, np.float64)
    DA = A[..., :, None] * np.eye(3)
    G = cov @ DA @ np.linalg.inv(DA @ cov @ DA + np.diag(lam2 * np.diag(cov)))
    G = G * np.minimum(1.0, max_gain / np.abs(G).sum(-1))[..., None]
    m = lam2 / (A * A + lam2)
    return m[..., :, None] * G + ((1 - m) * A / (A * A + lam2))[..., :, None] * np.eye(3)


def _physics_reference(img: np.ndarray, r: np.ndarray, k_A: np.ndarray, k_B: np.ndarray, B_inf: np.ndarray,
                       space: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The twins' shared start, float64: (the photo in the physics' space [n, W, 3], the range r [n, W, 1] with
    NaN and negatives at 0, A and B [n, W, 3])."""
    x = np.asarray(img, np.float64)
    x = srgb_to_linear(x) if space == "linear" else x
    rr = np.nan_to_num(np.maximum(np.asarray(r, np.float64), 0.0), nan=0.0)[..., None]
    A = np.exp(-np.clip(np.nan_to_num(k_A) * rr, 0, 80))
    B = B_inf * -np.expm1(-np.clip(np.nan_to_num(k_B) * rr, 0, 80))
    return x, rr, A, B


def dewater_reference(img: np.ndarray, r: np.ndarray, surface: np.ndarray, medium: MediumMaps, *,
                      max_gain: float = 8.0, space: str = "srgb", prior: np.ndarray | None = None,
                      lam2: np.ndarray | None = None, noise2: np.ndarray | None = None,
                      detail2: np.ndarray | None = None, detail_cov: np.ndarray | None = None,
                      misfit: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Slow twin of :func:`dewater` (numpy, float64, unquantised; per-pixel matrices by ``np.linalg``). img
    float [n, W, 3] in [0, 1]. Returns (J float64 [n, W, 3] in [0, 1], confidence [n, W], clipped count)."""
    _check(max_gain, space)
    x, rr, A, B = _physics_reference(img, r, medium.k_A, medium.k_B, medium.B_inf, space)
    Ae = np.maximum(A, 1.0 / max_gain)
    n2 = _variance(noise2)
    if prior is None:
        raw = (x - B) / Ae
        noise_var, model_var = n2 / Ae**2, 0.0
    else:
        P = np.asarray(prior, np.float64)
        cov, dcov = _covariances(detail2, detail_cov)
        G = gain_matrix(A, cov, _lam2(lam2, max_gain), max_gain)
        raw = P + (G @ (x - B - A * P)[..., None])[..., 0]
        K = np.eye(3) - G @ (A[..., :, None] * np.eye(3))
        noise_var = (G**2) @ n2
        model_var = np.maximum(np.einsum("...ca,ab,...cb->...c", K, dcov, K), 0.0)
        if misfit is not None:
            model_var = model_var + np.maximum(np.asarray(misfit, np.float64) - n2, 0.0) / Ae**2
    J = np.clip(raw, 0, 1)
    kA, kB = (np.clip(np.nan_to_num(k, nan=0.0), 0, 1e30) for k in (medium.k_A, medium.k_B))
    e = expected_error(J, rr, kA, kB, medium.B_inf, Ae, noise_var, model_var, medium.sigma)
    conf = confidence_from_error(J, e, space == "linear")
    J = linear_to_srgb(J) if space == "linear" else J
    surface = np.asarray(surface, bool)
    J = np.where(surface[..., None], J, np.clip(img, 0, 1))
    conf = np.where(surface, conf, 0.0)
    clipped = int((surface & ((raw < 0) | (raw > 1)).any(-1)).sum())
    return J, conf, clipped
