"""Small test videos with known camera motion: crops of one seeded texture, moved, held still and blurred."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.synth.video import encode_video

H, W = 96, 128  # frame size
STEP = 3  # pixels the camera moves per frame in the moving segments
# (kind, frames): the segments of SEGMENT_VIDEO, in order
SEGMENTS = (("moving", 40), ("still", 30), ("blurred", 20), ("moving", 40))
BLUR_PX = 9  # box motion blur length of the blurred segment, pixels along the motion
FPS = 10


def texture(seed: int, h: int, w: int) -> np.ndarray:
    """Seeded multi-scale value noise in [0, 1], [h, w, 3] float32: detail at every scale, like a seabed."""
    rng = np.random.default_rng(seed)
    out = np.zeros((h, w, 3), np.float32)
    for k in (1, 2, 4, 8, 16, 32):
        small = rng.random((h // k + 2, w // k + 2, 3)).astype(np.float32)
        up = np.repeat(np.repeat(small, k, 0), k, 1)[:h, :w]
        for _ in range(2):
            up = (up + np.roll(up, 1, 0) + np.roll(up, 1, 1) + np.roll(up, -1, 0) + np.roll(up, -1, 1)) / 5
        out += up / k ** 0.5
    return (out - out.min()) / (out.max() - out.min())


def _box_blur_x(img: np.ndarray, n: int) -> np.ndarray:
    c = np.cumsum(np.pad(img, ((0, 0), (n // 2 + 1, n // 2), (0, 0)), mode="edge"), axis=1)
    return (c[:, n:] - c[:, :-n]) / n


def segment_frames(segments=SEGMENTS, blur_px: int = BLUR_PX, soft_px: int = 0, seed: int = 0
                   ) -> Iterator[tuple[int, np.ndarray]]:
    """(camera x in texture pixels, uint8 frame) per frame: ``segments`` of moving / still / blurred (moving with
    a box motion blur of ``blur_px``) camera; ``soft_px`` > 0 blurs every frame (a soft video). Sensor noise
    (std 2/255) is added after the blur, as a camera does."""
    total = sum(n for kind, n in segments if kind != "still") * STEP + W + 2 * blur_px + 2
    tex = texture(seed, H + 16, total)
    rng = np.random.default_rng(seed + 1)
    x = blur_px + 1
    for kind, n in segments:
        for _ in range(n):
            pad = max(blur_px if kind == "blurred" else 0, soft_px)
            im = tex[8:8 + H, x - pad:x + W + pad]
            if kind == "blurred":
                im = _box_blur_x(im, blur_px)
            if soft_px:
                im = _box_blur_x(im, soft_px)
            im = im[:, pad:pad + W] + rng.normal(0, 2 / 255, (H, W, 3))
            yield x, (np.clip(im, 0, 1) * 255).round().astype(np.uint8)
            if kind != "still":
                x += STEP


def write_segment_video(path: Path, **kw) -> tuple[Path, list[int]]:
    """The segment video at ``path``; returns (path, camera x of every frame)."""
    xs: list[int] = []

    def frames():
        for x, f in segment_frames(**kw):
            xs.append(x)
            yield f

    return encode_video(frames(), path, FPS), xs


def segment_of(index: int, segments=SEGMENTS) -> int:
    """The number of the segment that frame ``index`` belongs to."""
    end = 0
    for k, (_, n) in enumerate(segments):
        end += n
        if index < end:
            return k
    raise IndexError(index)
