"""A generated frame for the restorer's tests and bench: a known clean image J, a known depth and a homogeneous
medium, seen through a distorted lens, plus the low-resolution PINHOLE render the restorer gets.

Scene (all in the camera's ray space, so every quantity is exact per pixel): a seabed plane seen obliquely,
z = z0 / (1 + tilt·yn), a rock (an ellipse in ray space) standing ``step`` closer with its own albedo (a depth
edge that is also a photo edge), open water (no surface) above yn < ``sky``. J is a sum of sines plus seeded
per-pixel noise, strong texture in the flat areas. The photo is I = J·A + B with r = z·√(1 + xn² + yn²).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.restore.lens import exact_rays
from pipeline.restore.records import MediumMaps, RenderedView
from pipeline.scene.records import Camera, LensCamera

BETA_D = np.array([0.35, 0.12, 0.08])
BETA_B = np.array([0.30, 0.15, 0.10])
B_INF = np.array([0.05, 0.25, 0.35])


@dataclass
class SynthFrame:
    """The generator's parameters; methods evaluate its exact quantities at any photo rows."""

    width: int
    height: int
    factor: int = 8  # photo width / render width
    k1: float = -0.1
    z0: float = 4.0
    tilt: float = 0.5
    step: float = 1.5
    sky: float = -0.3
    seed: int = 0

    @property
    def lens(self) -> LensCamera:
        f = 1.1 * self.width
        return LensCamera("SIMPLE_RADIAL", self.width, self.height, (f, self.width / 2, self.height / 2, self.k1))

    @property
    def render_camera(self) -> Camera:
        w, h = self.width // self.factor, self.height // self.factor
        f = 1.1 * self.width / self.factor
        return Camera(w, h, f, f, w / 2, h / 2)

    @property
    def medium(self) -> MediumMaps:
        return MediumMaps(BETA_D.copy(), BETA_B.copy(), B_INF.copy())

    def depth_at(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(z, surface, rock) at rays xn, yn (any shape): camera z (0 where no surface), masks."""
        rock = ((xn - 0.1) / 0.25) ** 2 + ((yn - 0.1) / 0.18) ** 2 < 1
        surface = yn >= self.sky
        z = self.z0 / (1 + self.tilt * np.maximum(yn, self.sky)) - self.step * rock
        return np.where(surface, z, 0.0), surface, rock

    def clean_at(self, xn: np.ndarray, yn: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The clean image J [.., 3] in [0, 1] at rays xn, yn [n, W] of photo rows ``rows`` [n]."""
        _, _, rock = self.depth_at(xn, yn)
        t = 0.5 + 0.2 * np.sin(40 * xn) * np.sin(33 * yn) + 0.1 * np.sin(170 * (xn + 0.7 * yn))
        rng = np.random.default_rng([self.seed, int(rows[0]), len(rows)])
        t = t + 0.08 * rng.standard_normal(xn.shape)
        albedo = np.where(rock[..., None], [0.9, 0.8, 0.7], [0.5, 0.55, 0.45])
        return np.clip(albedo * t[..., None], 0, 1)

    def photo_rows(self, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(photo I, clean J, surface) of rows [y0, y1): [n, W, 3] float64, [n, W, 3], [n, W] bool. Open water
        shows B∞."""
        xn, yn = exact_rays(self.lens, y0, y1)
        z, surface, _ = self.depth_at(xn, yn)
        J = self.clean_at(xn, yn, np.arange(y0, y1))
        r = (z * np.sqrt(1 + xn**2 + yn**2))[..., None]
        I = J * np.exp(-BETA_D * r) + B_INF * (1 - np.exp(-BETA_B * r))
        I = np.where(surface[..., None], I, B_INF)
        return I, J, surface

    def render(self, supersample: int = 4, prior: bool = False) -> RenderedView:
        """The render the restorer gets: depth and alpha averaged over ``supersample``² sub-pixels of each render
        pixel (a rasterizer's alpha-normalised depth at an edge is such a blend); with ``prior``, the model's J too
        (the clean image averaged the same way: a model with the right colours and the render's resolution)."""
        cam, s = self.render_camera, supersample
        off = (np.arange(s) + 0.5) / s
        xs = ((np.arange(cam.width)[:, None] + off[None]).ravel() - cam.cx) / cam.fx
        ys = ((np.arange(cam.height)[:, None] + off[None]).ravel() - cam.cy) / cam.fy
        z, surface, _ = self.depth_at(xs[None, :], ys[:, None])
        surface = np.broadcast_to(surface, z.shape)
        a = surface.reshape(cam.height, s, cam.width, s).mean((1, 3))
        zs = z.reshape(cam.height, s, cam.width, s).sum((1, 3)) / np.maximum(surface.reshape(
            cam.height, s, cam.width, s).sum((1, 3)), 1)
        J = None
        if prior:
            rows = np.repeat(np.arange(cam.height), s)
            Jss = self.clean_at(np.broadcast_to(xs[None, :], z.shape), np.broadcast_to(ys[:, None], z.shape), rows)
            J = Jss.reshape(cam.height, s, cam.width, s, 3).mean((1, 3)).astype(np.float32)
        return RenderedView(cam, zs.astype(np.float32), a.astype(np.float32), self.medium, J)
