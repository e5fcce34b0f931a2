"""Restore one whole frame in row bands: bounded memory whatever the photo's size.

Per band of ``band_rows`` photo rows (plus a halo of :func:`~pipeline.restore.guided.halo_rows` for the filter):
lens map → sample the render's filled depth and alpha → guided filter on the photo's luminance → surface mask
(sampled alpha ≥ 0.5, inside the render camera, z > 0) → range r = z·√(1 + xn² + yn²) → dewater. Bands start at
multiples of the filter's block size, so the result equals a whole-frame run up to float rounding.

Seabed next to the reconstruction that no training view covered (``unseen="extend"``, the default): the render's
depth, filled outwards from the surface, is carried on, and the photo alone is de-watered there (no model prior:
the model holds nothing of it) with the gain cap, confidence 0, blended into the photo as taken with the weight
:func:`extension_weight` (by distance from the reconstructed surface and by how much light the water lets through
at that range). Beyond that reach, and where the water hides the bottom (open water), the pixel is left as taken.
docs/DECISIONS.md, "Seabed the model does not hold".
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from pipeline.medium.fall_off import log_fall_off_at
from pipeline.restore._kernels import calibration_sums, luminance, surface_range
from pipeline.restore.dewater import (
    _k,
    detail_covariance,
    dewater,
    local_misfit,
    noise_and_detail,
    prior_weights,
)
from pipeline.restore.files import BandReader, BandWriter, output_spec, restored_path
from pipeline.restore.guided import (
    DEFAULT_EPS,
    default_radius,
    default_subsample,
    fast_guided_filter,
    fill_invalid,
    halo_rows,
    upsampling_factor,
)
from pipeline.restore.lens import DEFAULT_TOL, LensGrid
from pipeline.restore.records import RenderedView
from pipeline.restore.sample import sample_maps
from pipeline.scene.colour import srgb_to_linear
from pipeline.scene.exposure import exposed, neutral
from pipeline.scene.records import Camera, LensCamera

logger = logging.getLogger(__name__)

CALIBRATION_BANDS = 6  # row bands of a photo that FrameRestorer.calibrate measures the prior's weight on
# pixels of a band it measures at most (every k-th row beyond): all of a 1600-wide photo's 256-row band, a quarter of
# a 27 MP frame's (the statistics are means over 10^5-10^6 pixels either way; 1.4 → 0.4 s on bench/restore.py)
CALIBRATION_PIXELS = 500_000
UNSEEN = ("extend", "keep")
# The window of the photo's local disagreement with the model (the confidence's misfit term,
# pipeline.restore.dewater.local_misfit): its radius in render pixels. Probed on the held-out photos of the
# 1600x1200 turbid scene (1.75 and 5 render pixels) and of 320x240 photo-family jobs (2 and 5): the correlation of
# the confidence with the error moved by at most 0.06 per frame (docs/DECISIONS.md, "Confidence as expected error").
MISFIT_RADIUS = 1.5
# samples of the misfit per window radius at most: a 27 MP photo's window (22 photo pixels) is measured on every
# 5th pixel (at every pixel the residual cost bench/restore.py's frame +4.5 s, sampled +1.5 s, two jobs beside it)
MISFIT_SAMPLES = 4


@dataclass(frozen=True)
class RestoreOptions:
    """How to restore. radius: guided-filter radius in photo pixels (None: half the upsampling factor; 0: plain
    bilinear depth); eps: its regulariser (luminance² units); band_rows: photo rows per band (rounded up to the
    filter's block size)."""

    max_gain: float = 8.0
    space: str = "srgb"
    radius: int | None = None
    eps: float = DEFAULT_EPS
    band_rows: int = 256
    lens_tol: float = DEFAULT_TOL
    # Pixels with no reconstructed surface: "extend" de-waters the photo alone at the depth carried on from the
    # nearby surface (within ``reach`` x the render's long side, fading over its second half, and fading out
    # where the mean transmission at that range falls from 2 x ``min_transmission`` to ``min_transmission``);
    # "keep" leaves them as taken.
    # A pixel whose photo lies within ``water_margin`` (every channel, physics space) of the water's own colour
    # B∞ is open water as far as the photo can tell, and is left as taken (fading in up to 2 x the margin).
    unseen: str = "extend"
    reach: float = 0.25
    min_transmission: float = 0.15
    water_margin: float = 0.03

    def __post_init__(self) -> None:
        if self.unseen not in UNSEEN:
            raise ValueError(f"unseen must be one of {UNSEEN}, got {self.unseen!r}")
        if not (self.reach >= 0 and 0 < self.min_transmission < 0.5 and self.water_margin > 0):
            raise ValueError(f"reach must be >= 0, min_transmission in (0, 0.5) and water_margin > 0, got "
                             f"{self.reach}, {self.min_transmission}, {self.water_margin}")


@dataclass
class FrameResult:
    """One restored frame. Arrays only from :func:`restore_array`; paths only from :func:`restore_file`."""

    J: np.ndarray | None = None  # [H, W, 3] uint8 / uint16
    confidence: np.ndarray | None = None  # [H, W] float32 in [0, 1]
    surface: np.ndarray | None = None  # [H, W] bool
    extended: np.ndarray | None = None  # [H, W] float32 in [0, 1]: weight of the photo-only restoration off the surface
    clipped: int = 0  # surface pixels with a channel clipped to [0, 1]
    surface_pixels: int = 0
    extended_pixels: float = 0.0  # sum of the extension's weights (pixel equivalents)
    lam2: list[float] | None = None  # the prior's weight per channel (FrameRestorer.calibrate), None: none
    seconds: float = 0.0
    paths: dict[str, Path] = field(default_factory=dict)


class FrameRestorer:
    """Everything of one view that does not depend on the photo's rows: the lens grid, the render's filled
    depth, the filter's settings. ``band(...)`` restores one band."""

    def __init__(self, lens: LensCamera, view: RenderedView, options: RestoreOptions = RestoreOptions()):
        self.lens, self.view, self.opt = lens, view, options
        self.grid = LensGrid(lens, tol=options.lens_tol)
        self.radius = (default_radius(lens, view.camera, view.pad) if options.radius is None
                       else int(options.radius))
        self.s = default_subsample(self.radius) if self.radius > 0 else 1
        self.halo = halo_rows(self.radius, self.s) if self.radius > 0 else 0
        # the misfit's window needs its rows' filtered depth exact: the filter's halo beyond it, in blocks of s
        self.misfit_radius = misfit_radius(lens, view.camera, view.pad) if view.J is not None else 0
        self.misfit_step = max(1, self.misfit_radius // MISFIT_SAMPLES)  # the misfit measured on every k-th pixel
        # rows the misfit needs beyond a band: the window's reach plus one sample step for the interpolation
        self.misfit_margin = ((max(1, round(self.misfit_radius / self.misfit_step)) + 1) * self.misfit_step
                              if self.misfit_radius else 0)
        self.halo += -(-self.misfit_margin // self.s) * self.s
        self.band_rows = -(-options.band_rows // self.s) * self.s
        depth = np.nan_to_num(np.asarray(view.depth, np.float64), nan=0.0, posinf=0.0)
        alpha = np.nan_to_num(np.asarray(view.alpha, np.float64), nan=0.0)
        ok = (alpha >= 0.5) & (depth > 0)
        z = fill_invalid(depth[..., None], ok)[..., 0]
        near = (reach_weight(ok, options.reach * (max(ok.shape) - 2 * view.pad)) if options.unseen == "extend"
                else np.zeros_like(z))
        self.maps = np.ascontiguousarray(np.stack([z, np.where(ok, alpha, 0.0), near], -1), np.float32)  # [h, w, 3]
        m = view.medium
        self.kmaps = None if m.constant else np.ascontiguousarray(np.concatenate(
            [np.broadcast_to(m.k_A, (*z.shape, 3)), np.broadcast_to(m.k_B, (*z.shape, 3))], -1), np.float32)
        self.jmap = None if view.J is None else np.ascontiguousarray(
            fill_invalid(np.asarray(view.J, np.float64), ok), np.float32)  # [h, w, 3], no holes to bleed in
        # every map stacked [h, w, 3 (+3 J) (+6 k)]: one sampling pass per band gathers them all (the same
        # bilinear weights per channel, so the same values as sampling each alone; two passes took ~1/5 of a
        # 27 MP frame's time)
        self.all_maps = np.ascontiguousarray(np.concatenate(
            [x for x in (self.maps, self.jmap, self.kmaps) if x is not None], -1), np.float32)
        self.lam2: np.ndarray | None = None  # the prior's weight per channel (calibrate); None: its floor
        self.noise2: np.ndarray | None = None  # the photo's noise variance per channel (calibrate); None: 0
        self.detail2: np.ndarray | None = None  # what the model lacks, as a variance of J (calibrate); None: 0
        # the same across channels, a covariance [3, 3] (calibrate): the channels are restored together
        self.detail_cov: np.ndarray | None = None
        logger.debug("restore %dx%d: lens grid step %d (%.4f px), filter r=%d s=%d halo=%d", lens.width,
                     lens.height, self.grid.step, self.grid.error, self.radius, self.s, self.halo)

    def bands(self) -> Iterator[tuple[int, int, int, int]]:
        """(e0, y0, y1, e1) for each band: its rows [y0, y1) and the rows [e0, e1) read with the halo."""
        H = self.lens.height
        for y0 in range(0, H, self.band_rows):
            y1 = min(H, y0 + self.band_rows)
            yield max(0, y0 - self.halo), y0, y1, min(H, y1 + self.halo)

    def calibration_bands(self, n: int = CALIBRATION_BANDS) -> list[tuple[int, int, int, int]]:
        """``n`` of :meth:`bands`, evenly spread over the photo: where :meth:`calibrate` measures."""
        all_bands = list(self.bands())
        if len(all_bands) <= n:
            return all_bands
        return [all_bands[round(i * (len(all_bands) - 1) / (n - 1))] for i in range(n)]

    def calibrate(self, rows_of: Callable[[int, int], np.ndarray]) -> np.ndarray | None:
        """Measure the photo's noise against what the model lacks (:func:`~pipeline.restore.dewater.prior_weights`)
        on :meth:`calibration_bands` (``rows_of(e0, e1)``: the photo's rows, read forwards) and set
        :attr:`lam2`. No prior: nothing to weigh, None."""
        if self.jmap is None:
            return None
        sq, lag, aa = np.zeros(3), np.zeros((3, 3)), np.zeros((3, 3))  # E[e²], E[e_c,x·e_k,x+1], E[A_c·A_k]
        n_sq, n_lag = 0, 0
        m = self.view.medium
        for e0, y0, y1, e1 in self.calibration_bands():
            rows = self.neutral(rows_of(e0, e1), e0)
            scale, r, surface, k_A, k_B, prior, _ = self._geometry(rows, e0, y0, y1)
            st = -(-r.size // CALIBRATION_PIXELS)  # every st-th row of a large photo's band
            s_sq, s_lag, s_aa, c_sq, c_lag = calibration_sums(
                np.ascontiguousarray(rows[y0 - e0:y1 - e0]), float(scale), np.ascontiguousarray(r, np.float32),
                np.ascontiguousarray(surface), _k(k_A), _k(k_B), np.asarray(m.B_inf, np.float64).reshape(3),
                self.opt.space == "linear", np.ascontiguousarray(prior, np.float32), int(st))
            sq, lag, aa = sq + s_sq, lag + s_lag, aa + s_aa
            n_sq, n_lag = n_sq + c_sq, n_lag + c_lag
        if n_lag < 100:
            return None
        lag, aa = lag / n_lag, aa / n_sq
        measured = (sq / n_sq, np.diag(lag).copy(), np.diag(aa).copy())
        self.lam2 = prior_weights(*measured, self.opt.max_gain)
        self.noise2, self.detail2 = noise_and_detail(*measured)  # for the confidence's expected error
        self.detail_cov = detail_covariance(lag, aa)
        return self.lam2

    def neutral(self, rows: np.ndarray, e0: int) -> np.ndarray:
        """The photo's rows [e0, e0 + len(rows)) as stored, or, when the view's exposure
        (``RenderedView.log_gain``) or the survey's fall-off (``RenderedView.fall_off``) is known, with them
        divided out: float32 sRGB-encoded in [0, 1] (:func:`pipeline.scene.exposure.neutral`)."""
        lg = self.view.log_gain
        if self.view.fall_off is not None:
            lg = (0.0 if lg is None else np.asarray(lg, np.float64)) + self.log_fall_off(e0, e0 + rows.shape[0])
        if lg is None:
            return rows
        scale = 1.0 / np.iinfo(rows.dtype).max if np.issubdtype(rows.dtype, np.integer) else 1.0
        return np.clip(neutral(rows.astype(np.float32) * np.float32(scale), lg, "srgb"), 0, 1).astype(np.float32)

    def log_fall_off(self, e0: int, e1: int) -> np.ndarray:
        """The survey's log fall-off [n, W, 1] at the photo's rows [e0, e1): the field of ``RenderedView.fall_off``
        (:func:`pipeline.medium.fall_off.log_fall_off_at`, a mean of 1 over the frame) at each pixel's place in
        the training image (its undistorted ray through the unpadded render camera, in half-widths and
        half-heights from the centre, as the sparse sightings it was fitted on)."""
        xn, yn = self.grid.rays(e0, e1)
        c, pad = self.view.camera, self.view.pad
        w0, h0 = c.width - 2 * pad, c.height - 2 * pad
        xy = np.stack([2 * (c.fx * xn + c.cx - pad) / w0 - 1, 2 * (c.fy * yn + c.cy - pad) / h0 - 1], -1)
        return log_fall_off_at(xy.reshape(-1, 2), self.view.fall_off).reshape(*xn.shape, 1)

    def _geometry(self, rows: np.ndarray, e0: int, y0: int, y1: int) -> tuple:
        """What the physics needs of rows [y0, y1) besides the photo (``rows``: its rows [e0, e0 + len(rows))):
        (the scale of the stored values, range r [n, W] float32, surface [n, W] bool, k_A, k_B, the prior
        [n, W, 3] or None, the reach weight [n, W] of pixels off the surface)."""
        e1 = e0 + rows.shape[0]
        scale = 1.0 / np.iinfo(rows.dtype).max if np.issubdtype(rows.dtype, np.integer) else 1.0
        xn, yn = self.grid.rays(e0, e1)
        vals, inside = sample_maps(self.all_maps, xn, yn, self.view.camera)  # [m, W, 3 (+3) (+6)]
        z = vals[..., 0]
        if self.radius > 0:
            z = fast_guided_filter(luminance(np.ascontiguousarray(rows), scale), z, self.radius, self.opt.eps,
                                   self.s)
        c = slice(y0 - e0, y1 - e0)
        r, surface, near = surface_range(np.ascontiguousarray(z[c], np.float32), xn[c], yn[c], inside[c], vals[c])
        m = self.view.medium
        k_A, k_B = m.k_A, m.k_B
        at = 3
        prior = None
        if self.jmap is not None:
            prior, at = np.ascontiguousarray(vals[c, :, 3:6]), 6  # copied once here, not in each kernel's call
        if self.kmaps is not None:
            k_A, k_B = vals[c, :, at:at + 3], vals[c, :, at + 3:at + 6]
        return scale, r, surface, k_A, k_B, prior, near

    def band(self, rows: np.ndarray, e0: int, y0: int, y1: int, out_max: int = 255
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """Restore rows [y0, y1) given the photo's rows [e0, e0 + len(rows)) (uint8/uint16/float [m, W, 3]).
        Returns (J [n, W, 3] uint8/uint16, confidence [n, W] float32, surface [n, W] bool, extension weight
        [n, W] float32, clipped count)."""
        rows = self.neutral(rows, e0)
        m = self.view.medium
        M = self.misfit_margin
        k0, k1 = max(e0, y0 - M), min(e0 + rows.shape[0], y1 + M)  # the rows the misfit's window reaches
        scale, r, surface, k_A, k_B, prior, near = self._geometry(rows, e0, k0, k1)
        misfit = None
        if prior is not None:
            misfit = local_misfit(rows[k0 - e0:k1 - e0], r, surface, k_A, k_B, m.B_inf, prior, self.misfit_radius,
                                  space=self.opt.space, scale=scale, step=self.misfit_step, row0=k0,
                                  out_rows=(y0 - k0, y1 - k0))
            c = slice(y0 - k0, y1 - k0)
            r, surface, prior, near = r[c], surface[c], prior[c], near[c]
            k_A, k_B = (k[c] if np.ndim(k) == 3 else k for k in (k_A, k_B))
        photo = rows[y0 - e0:y1 - e0]
        J, conf, clipped = dewater(photo, r, surface, k_A, k_B, m.B_inf, max_gain=self.opt.max_gain,
                                   space=self.opt.space, out_max=out_max, scale=scale, prior=prior, lam2=self.lam2,
                                   sigma=m.sigma, noise2=self.noise2, detail2=self.detail2,
                                   detail_cov=self.detail_cov, misfit=misfit)
        w = np.zeros_like(near)
        sel = near > 0  # off the surface but near it: only these pixels can be carried on
        if sel.any():
            x = photo[sel].astype(np.float32) * np.float32(scale)
            if self.opt.space == "linear":
                x = srgb_to_linear(np.clip(x, 0, 1))
            k = k_A[sel] if np.ndim(k_A) == 3 else k_A
            w[sel] = extension_weight(near[sel], r[sel], k, self.opt.min_transmission) * water_fade(
                x, m.B_inf, self.opt.water_margin)
            off = w > 0
            if off.any():  # the photo alone, at the carried-on depth, blended into the photo as taken
                Jx, _, _ = dewater(photo, r, off, k_A, k_B, m.B_inf, max_gain=self.opt.max_gain,
                                   space=self.opt.space, out_max=out_max, scale=scale)
                wo = w[off][:, None]
                J[off] = np.rint(wo * Jx[off].astype(np.float32) + (1 - wo) * J[off].astype(np.float32))
        return self.at_survey_exposure(J, out_max), conf, surface, w, clipped

    def at_survey_exposure(self, J: np.ndarray, out_max: int) -> np.ndarray:
        """The restored rows (integers to ``out_max``, sRGB-encoded) taken from the model's exposure to the
        survey's mean (``RenderedView.output_log_gain``); as they are without one."""
        lg = self.view.output_log_gain
        if lg is None or not np.any(lg):
            return J
        x = exposed(J.astype(np.float32) / np.float32(out_max), lg, "srgb")
        return np.rint(np.clip(x, 0, 1) * out_max).astype(J.dtype)


def restore_array(photo: np.ndarray, lens: LensCamera, view: RenderedView,
                  options: RestoreOptions = RestoreOptions(), out_max: int = 255) -> FrameResult:
    """Restore a photo held in memory, [H, W, 3] uint8/uint16 or float in [0, 1] (display orientation, the size
    of ``lens``). Returns J, confidence and surface as arrays."""
    t = time.perf_counter()
    H, W = photo.shape[:2]
    if (W, H) != (lens.width, lens.height):
        raise ValueError(f"photo is {W}x{H}, lens camera {lens.width}x{lens.height}")
    fr = FrameRestorer(lens, view, options)
    fr.calibrate(lambda e0, e1: photo[e0:e1])
    res = FrameResult(J=np.empty((H, W, 3), np.uint8 if out_max == 255 else np.uint16),
                      confidence=np.empty((H, W), np.float32), surface=np.empty((H, W), bool),
                      extended=np.empty((H, W), np.float32))
    for e0, y0, y1, e1 in fr.bands():
        J, conf, surf, ext, clipped = fr.band(photo[e0:e1], e0, y0, y1, out_max)
        res.J[y0:y1], res.confidence[y0:y1], res.surface[y0:y1], res.extended[y0:y1] = J, conf, surf, ext
        res.clipped += clipped
    res.surface_pixels = int(res.surface.sum())
    res.extended_pixels = float(res.extended.sum())
    res.seconds = time.perf_counter() - t
    res.lam2 = None if fr.lam2 is None else [float(x) for x in fr.lam2]
    return res


def restore_file(src: Path, lens: LensCamera, view: RenderedView, out_dir: Path,
                 options: RestoreOptions = RestoreOptions(), *, tiff16: bool = False,
                 confidence_bits: int = 8, confidence_dir: Path | None = None) -> FrameResult:
    """Restore the image file ``src`` band by band into ``out_dir``: the restored image (same name and format,
    metadata kept; :func:`~pipeline.restore.files.restored_path`), ``<stem>_confidence.png`` (8 or 16 bit, 0..max
    ↔ confidence 0..1) and ``<stem>_surface.png`` (8 bit, :func:`surface_code`); with ``confidence_dir``, those
    two there as ``<stem>.png`` and ``<stem>_surface.png`` (a job's layout). Returns counts, time and paths."""
    t = time.perf_counter()
    src, out_dir = Path(src), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    reader = BandReader(src)
    if (reader.width, reader.height) != (lens.width, lens.height):
        raise ValueError(f"{src} is {reader.width}x{reader.height}, lens camera {lens.width}x{lens.height}")
    fr = FrameRestorer(lens, view, options)
    if fr.jmap is not None:  # a first, forward pass over a few bands: the photo's noise against the model
        calib = BandReader(src)
        try:
            fr.calibrate(calib.rows)
        finally:
            calib.close()
    W, H = reader.width, reader.height
    j_path = restored_path(src, out_dir, tiff16)
    sixteen = j_path.suffix == ".tif"
    c_max = 65535 if confidence_bits == 16 else 255
    if confidence_dir is None:
        conf_path = out_dir / f"{src.stem}_confidence.png"
    else:
        confidence_dir = Path(confidence_dir)
        confidence_dir.mkdir(parents=True, exist_ok=True)
        conf_path = confidence_dir / f"{src.stem}.png"
    paths = {"J": j_path, "confidence": conf_path,
             "surface": (confidence_dir or out_dir) / f"{src.stem}_surface.png"}
    writers = {
        "J": BandWriter(j_path, output_spec(reader.spec, W, H, 3, oiio.UINT16 if sixteen else oiio.UINT8, j_path)),
        "confidence": BandWriter(paths["confidence"], output_spec(
            None, W, H, 1, oiio.UINT16 if c_max == 65535 else oiio.UINT8, paths["confidence"])),
        "surface": BandWriter(paths["surface"], output_spec(None, W, H, 1, oiio.UINT8, paths["surface"])),
    }
    res = FrameResult(paths=paths)
    try:
        for e0, y0, y1, e1 in fr.bands():
            J, conf, surf, ext, clipped = fr.band(reader.rows(e0, e1), e0, y0, y1, 65535 if sixteen else 255)
            writers["J"].write(J)
            writers["confidence"].write((conf * c_max + 0.5).astype(np.uint16 if c_max == 65535 else np.uint8))
            writers["surface"].write(surface_code(surf, ext))
            res.clipped += clipped
            res.surface_pixels += int(surf.sum())
            res.extended_pixels += float(ext.sum())
    finally:
        reader.close()
        for w in writers.values():
            w.close()
    res.seconds = time.perf_counter() - t
    res.lam2 = None if fr.lam2 is None else [float(x) for x in fr.lam2]
    logger.info("restored %s: %.2f s, %d surface pixels, %d clipped", src.name, res.seconds, res.surface_pixels,
                res.clipped)
    return res


def surface_range_reference(z: np.ndarray, xn: np.ndarray, yn: np.ndarray, inside: np.ndarray,
                            vals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slow twin of :func:`pipeline.restore._kernels.surface_range` (the numpy lines it replaced): (range r,
    surface, the reach weight off the surface) of a band, [n, W] each."""
    z, xn, yn = (np.asarray(a, np.float32) for a in (z, xn, yn))
    surface = inside & (vals[..., 1] >= 0.5) & (z > 0)
    r = z * np.sqrt(1.0 + xn * xn + yn * yn)
    near = np.where(surface | (z <= 0), 0.0, vals[..., 2]).astype(np.float32)
    return r, surface, near


def calibration_sums_reference(x: np.ndarray, r: np.ndarray, surface: np.ndarray, k_A: np.ndarray, k_B: np.ndarray,
                               B_inf: np.ndarray, prior: np.ndarray, st: int, space: str = "srgb") -> tuple:
    """Slow twin of :func:`pipeline.restore._kernels.calibration_sums` (numpy float64; the restorer's code until
    2026-12-01): x [n, W, 3] the photo in [0, 1] (float), r [n, W], surface [n, W] bool, k_A, k_B [3] or
    [n, W, 3], prior [n, W, 3]; every ``st``-th row. Returns (Σ e², Σ lag products [3, 3], Σ A·Aᵀ [3, 3],
    surface count, pair count)."""
    x = np.asarray(x, np.float64)[::st]
    if space == "linear":
        x = srgb_to_linear(np.clip(x, 0, 1))
    r, surface, prior = np.asarray(r, np.float64)[::st][..., None], surface[::st], prior[::st]
    k_A, k_B = (k[::st] if np.ndim(k) == 3 else k for k in (k_A, k_B))
    A = np.exp(-np.clip(np.asarray(k_A, np.float64) * r, 0, 80))
    B = np.asarray(B_inf, np.float64) * -np.expm1(-np.clip(np.asarray(k_B, np.float64) * r, 0, 80))
    e = x - (prior * A + B)
    both = surface[:, :-1] & surface[:, 1:]
    return ((e[surface] ** 2).sum(0), e[:, :-1][both].T @ e[:, 1:][both], A[surface].T @ A[surface],
            int(surface.sum()), int(both.sum()))


def misfit_radius(lens: LensCamera, camera: Camera, pad: int = 0) -> int:
    """The misfit window's radius in photo pixels: :data:`MISFIT_RADIUS` render pixels at the
    :func:`~pipeline.restore.guided.upsampling_factor`, at least 2."""
    return max(2, round(MISFIT_RADIUS * upsampling_factor(lens, camera, pad)))


def reach_weight(ok: np.ndarray, reach_px: float) -> np.ndarray:
    """[h, w] float32: 1 on and near the reconstructed surface ``ok`` [h, w] (chessboard distance ≤ reach/2),
    falling linearly to 0 at ``reach_px`` render pixels; 0 everywhere when nothing is reconstructed."""
    ok = np.asarray(ok, bool)
    d = np.full(ok.shape, np.inf)
    if not ok.any() or reach_px <= 0:
        return np.where(ok, 1.0, 0.0).astype(np.float32)
    steps = int(np.ceil(reach_px))
    grown = ok.copy()
    d[ok] = 0
    for k in range(1, steps + 1):  # one 3x3 dilation per pixel of distance; the maps are training-sized
        g = grown.copy()
        g[1:] |= grown[:-1]
        g[:-1] |= grown[1:]
        g[:, 1:] |= g[:, :-1].copy()
        g[:, :-1] |= g[:, 1:].copy()
        d[g & ~grown] = k
        if g.all():
            break
        grown = g
    return np.clip(2.0 * (1.0 - d / reach_px), 0.0, 1.0).astype(np.float32)


def extension_weight(near: np.ndarray, r: np.ndarray, k_A: np.ndarray, min_transmission: float) -> np.ndarray:
    """The weight (``near``'s shape, float32) of the photo-only restoration off the surface: the reach weight
    ``near`` times a fade on the mean transmission A = exp(−k_A·r) over the channels at the carried-on range
    ``r``: 1 from 2 x ``min_transmission`` up, 0 at ``min_transmission`` and below (there the water hides the
    bottom: open water, or seabed too far to tell from it)."""
    k = np.nan_to_num(np.asarray(k_A, np.float32), nan=0.0)  # [3] or per pixel [..., 3]
    a = np.exp(-np.clip(k * np.asarray(r, np.float32)[..., None], 0, 80)).mean(-1)
    fade = np.clip(a / min_transmission - 1.0, 0.0, 1.0)
    return (np.asarray(near, np.float32) * fade).astype(np.float32)


def water_fade(x: np.ndarray, B_inf: np.ndarray, margin: float) -> np.ndarray:
    """[...] float32: 0 where the photo ``x`` [..., 3] (physics space) is within ``margin`` of the water's colour
    ``B_inf`` in every channel (open water as far as the photo can tell), rising to 1 at 2 x ``margin``. Where it
    is 0 the pixel is left as taken, and rightly so: a seabed whose colour matches the water's looks the same
    through any amount of it (I − J = (1 − A)(B∞ − J) ≈ 0)."""
    d = np.abs(np.asarray(x, np.float32) - np.asarray(B_inf, np.float32).reshape(3)).max(-1)
    return np.clip(d / margin - 1.0, 0.0, 1.0).astype(np.float32)


def surface_code(surface: np.ndarray, extended: np.ndarray) -> np.ndarray:
    """The 8-bit surface mask: 255 on the reconstructed surface, round(127 x weight) where the seabed was carried
    on (at least 1 wherever the weight is above 0), 0 where the photo is left as taken."""
    ext = np.where(extended > 0, np.maximum(np.rint(127 * extended), 1), 0)
    return np.where(surface, 255, ext).astype(np.uint8)
