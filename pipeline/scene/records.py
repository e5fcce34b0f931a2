"""Plain scene records shared by the generator, the loaders, SfM and training.

Conventions (fixed for the whole project):
- Poses are ``cam_from_world`` (COLMAP's): ``x_cam = R @ x_world + t``; camera looks down +z, x right, y down.
- Intrinsics are PINHOLE: ``fx, fy, cx, cy`` in pixels, with the pixel-centre convention of COLMAP (the centre
  of the top-left pixel is at (0.5, 0.5)).
- Depth means camera-space z (what a rasterizer renders), in scene units. The distance along a pixel's ray is
  ``depth * ray_length_factor(camera)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A PINHOLE camera."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:  # [3, 3]
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (e.g. 0.5 for half size)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Camera(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)


@dataclass(frozen=True)
class LensCamera:
    """A camera as COLMAP models it, lens distortion included, at the photo's own resolution: the model name
    (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``PINHOLE``, ``SIMPLE_PINHOLE`` ...), size and ``params`` in
    COLMAP's order for that model. SfM's model of a job's photos, a generated scene's true camera."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def colmap(self):
        """The same camera as a ``pycolmap.Camera`` (whose ``cam_from_img`` undistorts pixel-centre coordinates
        [N, 2] into normalised rays [N, 2])."""
        import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

        return pycolmap.Camera(model=self.model, width=self.width, height=self.height,
                               params=np.asarray(self.params, dtype=np.float64))

    def cameras_txt_line(self, camera_id: int = 1) -> str:
        """The camera as a line of COLMAP's cameras.txt."""
        return f"{camera_id} {self.model} {self.width} {self.height} {' '.join(repr(float(p)) for p in self.params)}"


@dataclass
class View:
    """One posed image."""

    name: str  # file name relative to the image folder, e.g. "frame_0001.png"
    camera: Camera
    R: np.ndarray  # [3, 3] cam_from_world rotation
    t: np.ndarray  # [3] cam_from_world translation
    image_path: Path | None = None

    @property
    def center(self) -> np.ndarray:  # [3] camera centre in world coordinates
        return -self.R.T @ self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points [N, 3] → (u, v, z) [N] each: pixel coordinates (pixel-centre convention) and camera z.
        Points with z ≤ 0 get u = v = NaN."""
        cam = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ self.R.T + self.t
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            zs = np.where(z > 1e-6, z, np.nan)
            return self.camera.fx * cam[:, 0] / zs + self.camera.cx, self.camera.fy * cam[:, 1] / zs + self.camera.cy, z

    @property
    def viewmat(self) -> np.ndarray:  # [4, 4] world -> camera
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m


def scaled_view(view: View, downscale: float) -> View:
    """``view`` with its camera for the image shrunk ``downscale`` times (``Camera.scaled(1 / downscale)``): the
    resolution a job trained at. ``view`` itself when ``downscale`` is 1."""
    return view if downscale == 1 else replace(view, camera=view.camera.scaled(1.0 / downscale))


@dataclass(frozen=True)
class Sightings:
    """Where one view saw the sparse points (the model's tracks): point indices into ``Scene.points`` and their
    pixel positions in an image ``width`` pixels wide (the model's camera; rescale for other resolutions)."""

    point: np.ndarray  # [K] int
    xy: np.ndarray  # [K, 2] float, pixel-centre convention (top-left pixel centre at 0.5, 0.5)
    width: int


@dataclass
class Scene:
    """Posed views plus sparse points; what a trainer needs."""

    views: list[View]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [P, 3] world xyz
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [P, 3] in [0, 1]
    root: Path | None = None
    sightings: dict[str, Sightings] | None = None  # view name -> its track observations, when the model has them

    def subset(self, views: list[View]) -> Scene:
        """The same points and tracks with only ``views`` (e.g. the training split)."""
        return Scene(views, self.points, self.colors, self.root, self.sightings)

    def view(self, name: str) -> View:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(f"no view named {name!r} in scene {self.root}")


def ray_length_factor(camera: Camera) -> np.ndarray:
    """Per-pixel ratio between distance along the ray and camera-space z.  # [H, W]"""
    u = (np.arange(camera.width) + 0.5 - camera.cx) / camera.fx
    v = (np.arange(camera.height) + 0.5 - camera.cy) / camera.fy
    return np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)


def view_ranges(points: np.ndarray, views: Sequence[View]) -> np.ndarray:
    """Median distance from each view's camera to the sparse points it sees (inside its image, in front);
    NaN for a view that sees none. [V]"""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(views), np.nan)
    for k, v in enumerate(views):
        u, w, _ = v.project(pts)  # NaN behind the camera: fails the test below
        inside = (u >= 0) & (u < v.camera.width) & (w >= 0) & (w < v.camera.height)
        if inside.any():
            out[k] = float(np.median(np.linalg.norm(pts[inside] - v.center, axis=1)))
    return out
