"""Keyframes of a video: reject motion blur, keep a frame each time the overlap with the last keyframe falls to a
target. Pure numpy on small grey frames; decoding lives in :mod:`pipeline.ingest.video`.

Per frame (the rule, its numbers and why: docs/DECISIONS.md, "Video keyframes"):

- **Sharpness** ``s = var(Laplacian(g)) / var(g)`` on the grey analysis frame (contrast-free, so slow light
  changes do not read as blur). The frame is *blurred* when ``s < blur_ratio · level``, where ``level`` is the
  ``level_percentile`` of ``s`` over the last ``level_seconds`` of frames (this one included): judged against the
  video's own recent level, so a video that is soft throughout is not emptied.
- **Motion** by phase correlation (Kuglin & Hines 1975) between consecutive frames, on the frame block-averaged
  to at most ``track_width`` pixels wide, low-pass weighted (robust to blur and noise), with a parabolic sub-pixel
  peak. The shifts add up since the last keyframe; the **overlap** with it is the shared area of the two frames
  under that translation, ``(1 - |dx|/w)(1 - |dy|/h)``. A correlation peak under ``min_peak`` means the frames do
  not overlap (a cut, lost track): overlap 0.
- A frame whose overlap is at most ``target_overlap + window`` is a **candidate**; once the overlap reaches
  ``target_overlap``, the sharpest unblurred candidate since the window opened is kept. A frame that is not a
  candidate is ``still`` (it moved less than ``still_motion`` of the frame width since the previous frame) or
  ``too_close``; candidates that lost to a sharper one are ``outsharpened``.

Only translation is measured: a forward-looking camera that flies straight ahead (zoom-like motion) or spins in
place changes the view faster than its measured overlap says (the limit is documented in DECISIONS).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

REJECT_REASONS = ("blur", "still", "too_close", "outsharpened")


@dataclass(frozen=True)
class KeyframeConfig:
    """The keyframe rule's numbers (module docstring)."""

    target_overlap: float = 0.7  # keep a frame once it shares this fraction of its area with the last keyframe
    window: float = 0.1  # candidates: frames with overlap in (target, target + window]; the sharpest is kept
    blur_ratio: float = 0.4  # sharper than this fraction of the recent level, or rejected as blurred
    level_seconds: float = 3.0  # the recent sharpness level spans this much video
    level_percentile: float = 80.0  # ... and is this percentile of the frames' sharpness there
    still_motion: float = 0.002  # frame-to-frame motion under this fraction of the frame width: the camera is still
    min_peak: float = 0.2  # phase-correlation peak (1 = identical frames) under which two frames do not overlap
    track_width: int = 160  # motion is measured on the frame block-averaged to at most this many pixels wide

    def __post_init__(self) -> None:
        if not 0.0 < self.target_overlap < 1.0:
            raise ValueError(f"target_overlap must lie in (0, 1), got {self.target_overlap}")
        if not 0.0 <= self.window < 1.0 - self.target_overlap:
            raise ValueError(f"window must lie in [0, 1 - target_overlap), got {self.window}")
        if not 0.0 < self.blur_ratio <= 1.0:
            raise ValueError(f"blur_ratio must lie in (0, 1], got {self.blur_ratio}")


@dataclass(frozen=True)
class Keyframe:
    index: int  # frame index in the video (decode order)
    time: float  # seconds from the stream's start
    sharpness: float
    overlap: float  # with the previous keyframe (1.0 for the first)
    why: str  # first | overlap | lost_track | end


def sharpness(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian over the variance of the image ([H, W] float): 0 for a flat frame."""
    g = np.asarray(grey, dtype=np.float32)
    if g.ndim != 2 or min(g.shape) < 3:
        raise ValueError(f"sharpness needs a grey frame [H, W] of at least 3x3, got {g.shape}")
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1]
    v = float(g.var())
    return float(lap.var()) / v if v > 1e-12 else 0.0


def block_mean(grey: np.ndarray, max_width: int) -> np.ndarray:
    """``grey`` [H, W] averaged over k x k blocks, k the smallest factor that makes it at most ``max_width`` wide."""
    k = max(1, -(-grey.shape[1] // max_width))
    if k == 1:
        return np.asarray(grey, dtype=np.float32)
    h, w = grey.shape[0] // k * k, grey.shape[1] // k * k
    return grey[:h, :w].astype(np.float32).reshape(h // k, k, w // k, k).mean(axis=(1, 3))


class _Correlator:
    """Phase correlation on frames of one size: the window and the low-pass weight are made once."""

    def __init__(self, shape: tuple[int, int]):
        h, w = shape
        self.window = np.outer(np.hanning(h), np.hanning(w)).astype(np.float32)  # no wrap-around edges
        fy, fx = np.fft.fftfreq(h)[:, None], np.fft.rfftfreq(w)[None, :]
        f2 = fx * fx + fy * fy
        # Gaussian low-pass (sigma 0.15 cycles/pixel): blur and noise live in the high frequencies, where
        # whitening would otherwise give them the same say as the structure; and a high-pass below ~2 cycles per
        # frame: lights and vignetting move with the camera and would pull the estimate towards "no motion"
        lo = 2.0 / min(h, w)
        self.weight = (np.exp(-f2 / (2 * 0.15 ** 2)) * (1.0 - np.exp(-f2 / (2 * lo * lo)))).astype(np.float32)
        full = 2 * self.weight.sum() - self.weight[:, 0].sum() - (self.weight[:, -1].sum() if w % 2 == 0 else 0)
        self.norm = h * w / float(full)  # the weight's sum over the full spectrum: identical frames give peak 1

    def spectrum(self, g: np.ndarray) -> np.ndarray:
        return np.fft.rfft2((g - g.mean()) * self.window)

    def shift(self, fa: np.ndarray, fb: np.ndarray, shape: tuple[int, int]) -> tuple[float, float, float]:
        """(dy, dx, peak): frame b is frame a moved by (dy, dx) pixels (b(x) = a(x - d)); peak 1 = identical."""
        cross = np.conj(fa) * fb
        cross = cross / (np.abs(cross) + 1e-9) * self.weight
        r = np.fft.irfft2(cross, s=shape)
        iy, ix = np.unravel_index(int(np.argmax(r)), r.shape)
        h, w = shape
        dy = iy + _parabola(r[(iy - 1) % h, ix], r[iy, ix], r[(iy + 1) % h, ix])
        dx = ix + _parabola(r[iy, (ix - 1) % w], r[iy, ix], r[iy, (ix + 1) % w])
        dy = dy - h if dy > h / 2 else dy
        dx = dx - w if dx > w / 2 else dx
        return float(dy), float(dx), float(r[iy, ix] * self.norm)


def _parabola(a: float, b: float, c: float) -> float:
    den = a - 2 * b + c
    return 0.0 if abs(den) < 1e-12 else float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))


def overlap_of(dy: float, dx: float, h: int, w: int) -> float:
    """The fraction of a frame's area shared with a copy moved by (dy, dx) pixels."""
    return max(0.0, 1.0 - abs(dx) / w) * max(0.0, 1.0 - abs(dy) / h)


@dataclass
class Offer:
    """What :meth:`KeyframeSelector.offer` tells its caller about one frame."""

    hold: bool  # keep this frame's pixels: it is now the best candidate (the previously held one can go)
    kept: Keyframe | None = None  # a keyframe was decided: the held frame, or this one when its index matches
    rejected: str | None = None  # why this frame is not a candidate (REJECT_REASONS), or None


@dataclass
class _Candidate:
    index: int
    time: float
    sharpness: float
    overlap: float
    shift: tuple[float, float]  # its accumulated shift from the last keyframe


@dataclass
class KeyframeSelector:
    """The rule of the module docstring, fed one frame at a time (streaming: it keeps the previous small frame's
    spectrum and the recent sharpness values, never the frames)."""

    cfg: KeyframeConfig
    fps: float
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECT_REASONS, 0))
    _levels: deque = field(default_factory=deque)
    _corr: _Correlator | None = None
    _shape: tuple[int, int] = (0, 0)
    _prev: np.ndarray | None = None  # spectrum of the previous frame
    _shift: tuple[float, float] = (0.0, 0.0)  # accumulated since the last keyframe
    _have_key: bool = False
    _best: _Candidate | None = None

    def __post_init__(self) -> None:
        self._levels = deque(maxlen=max(1, round(self.cfg.level_seconds * max(self.fps, 1.0))))

    def offer(self, index: int, time: float, grey: np.ndarray) -> Offer:
        """One decoded frame as a grey analysis image [H, W] (any scale: uint8 or float)."""
        s = sharpness(grey)
        self._levels.append(s)
        blurred = s < self.cfg.blur_ratio * float(np.percentile(self._levels, self.cfg.level_percentile))
        small = block_mean(np.asarray(grey, dtype=np.float32), self.cfg.track_width)
        if self._corr is None or small.shape != self._shape:
            self._corr, self._shape = _Correlator(small.shape), small.shape
            self._prev = None
        spec = self._corr.spectrum(small)
        h, w = self._shape
        step = 0.0
        if self._prev is None:
            lost = self._have_key  # a size change mid-stream: no motion estimate, treat as a cut
        else:
            dy, dx, peak = self._corr.shift(self._prev, spec, self._shape)
            lost = peak < self.cfg.min_peak
            step = float(np.hypot(dy, dx))
            self._shift = (self._shift[0] + dy, self._shift[1] + dx)
        self._prev = spec
        if lost:
            self._shift = (float(h), float(w))  # overlap 0 from here on, until the next keyframe
        if not self._have_key:
            if blurred:
                return self._reject("blur")
            return self._keep(_Candidate(index, time, s, 1.0, self._shift), "first", current=True)
        overlap = overlap_of(*self._shift, h, w)
        if blurred:
            return self._reject("blur")
        if overlap > self.cfg.target_overlap + self.cfg.window:
            return self._reject("still" if step < self.cfg.still_motion * w else "too_close")
        me = _Candidate(index, time, s, overlap, self._shift)
        hold = self._best is None or s > self._best.sharpness
        if hold:
            if self._best is not None:
                self.counts["outsharpened"] += 1
            self._best = me
        else:  # a candidate that loses at once: a still camera in the window reads as "still"
            self.counts["still" if step < self.cfg.still_motion * w else "outsharpened"] += 1
        if overlap > self.cfg.target_overlap:
            return Offer(hold=hold)
        best = self._best
        assert best is not None
        why = "lost_track" if overlap == 0.0 and lost else "overlap"
        return self._keep(best, why, current=hold)

    def finish(self) -> Keyframe | None:
        """At the end of the video: the pending candidate (the held frame), if any, is kept to cover the end."""
        if self._best is None:
            return None
        best, self._best = self._best, None
        return Keyframe(best.index, best.time, best.sharpness, best.overlap, "end")

    def _reject(self, why: str) -> Offer:
        self.counts[why] += 1
        return Offer(hold=False, rejected=why)

    def _keep(self, c: _Candidate, why: str, current: bool) -> Offer:
        """``c`` becomes the keyframe; the motion since it is what was accumulated after it."""
        self._shift = (self._shift[0] - c.shift[0], self._shift[1] - c.shift[1])
        self._have_key, self._best = True, None
        return Offer(hold=current, kept=Keyframe(c.index, c.time, c.sharpness, c.overlap, why))
