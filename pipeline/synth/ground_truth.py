"""Ground truth for a job whose images came from our scene generator (``pipeline.synth.procedural``).

A generated scene folder holds ``images/`` (what the job ingests), ``clean/`` (the true restored radiance J),
``depth/*.npy`` (camera-space z in metres), ``sparse_gt/`` (the true cameras, metres) and ``water.json`` (the
true β_D, β_B, B∞ and the generator's config: :data:`pipeline.synth.water.TRUE_WATER_FILE`, the scene's truth,
unrelated to the classifier's decision in a job folder). A job finds it either through
``JobOptions.ground_truth`` (the scene folder) or, when that is unset, because its source sits directly in such
a scene: its ``images/`` folder, or a video there (a generated video's truth, :mod:`pipeline.synth.video_truth`).
Nothing else counts as ground truth: a folder must carry the generator's ``water.json`` and ``clean/``.

A job's view is matched to the true view with the same file stem (:func:`load_ground_truth` ``names``): ingest
keeps a generated scene's names, but a video's keyframes are JPEGs (``transect_000123.jpg``) while the truth of
that frame is ``transect_000123.png`` / ``.npy``. The truth's files are always ``<stem>.png`` and ``<stem>.npy``.

A scene generated with lens distortion (``pipeline.synth.lens``) records images/, clean/, depth/ in the
distorted geometry of the true RADIAL camera (sparse_gt/) and holds pinhole companions in ``pinhole/`` (images/,
clean/, depth/, sparse/: the same views rendered through the ideal PINHOLE lens). :class:`GroundTruth` then reads
its pinhole-geometry truth (``scene``, ``clean``, ``depth``, ``seen_by``) from ``pinhole/``; the full-resolution
truth in the recorded geometry is ``original_camera``, ``clean_original`` and ``depth_original``. For an
undistorted scene both are the same files and camera.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.ingest.video import is_video
from pipeline.scene.colmap import lens_cameras
from pipeline.scene.images import read_image, resize_area_to
from pipeline.scene.loader import load_scene, load_view_image
from pipeline.scene.records import LensCamera, Scene, View
from pipeline.synth.procedural import PINHOLE_DIR
from pipeline.synth.water import TRUE_WATER_FILE

log = logging.getLogger(__name__)

FAR_DEPTH_M = 999.0  # the generator writes 1000 m where a ray hits nothing
SEEN_DEPTH_TOL = 0.03  # relative depth agreement for "the other view sees this surface point, not an occluder"


class GroundTruthError(ValueError):
    """A folder given as ground truth is not a generated scene."""


@dataclass
class GroundTruth:
    """A generated scene's truth."""

    root: Path  # the pinhole-geometry truth (images/, clean/, depth/): the scene folder, or its pinhole/
    scene: Scene  # the true PINHOLE cameras (world in metres), views named as the job names them (by stem)
    water: dict  # water.json: preset, beta_D, beta_B (1/m), B_inf, generator config
    scene_root: Path | None = None  # the generated scene folder (the recorded geometry); None = root

    @staticmethod
    def file(name: str, suffix: str = ".png") -> str:
        """The truth's file for view ``name`` (a job's name or the truth's own): images/ and clean/ hold
        ``<stem>.png``, depth/ ``<stem>.npy``."""
        return f"{Path(name).stem}{suffix}"

    @property
    def original_root(self) -> Path:
        """The scene folder whose images/, clean/, depth/ are in the true (possibly distorted) geometry."""
        return self.scene_root or self.root

    def original_camera(self, name: str) -> LensCamera:
        """The true camera of view ``name`` as recorded (sparse_gt/): RADIAL for a distorted scene, else
        PINHOLE; params in COLMAP order."""
        return lens_cameras(self.original_root / "sparse_gt")[self.file(name)]

    def clean_original(self, name: str) -> np.ndarray:
        """The true clean radiance of view ``name`` at full resolution in the recorded geometry.  # [H, W, 3]"""
        return read_image(self.original_root / "clean" / self.file(name))

    def depth_original(self, name: str) -> np.ndarray:
        """True camera-space z (metres) of view ``name`` at full resolution in the recorded geometry.  # [H, W]"""
        return np.load(self.original_root / "depth" / self.file(name, ".npy"))

    def clean(self, view: View) -> np.ndarray:
        """The true clean radiance of ``view.name`` at ``view.camera``'s size (area-averaged).  # [h, w, 3]"""
        path = self.root / "clean" / self.file(view.name)
        return load_view_image(View(view.name, view.camera, view.R, view.t, path))

    def photo(self, view: View) -> np.ndarray:
        """The underwater image as generated (a video's frame before the codec) of ``view.name`` at
        ``view.camera``'s size (area-averaged).  # [h, w, 3]"""
        path = self.root / "images" / self.file(view.name)
        return load_view_image(View(view.name, view.camera, view.R, view.t, path))

    def depth(self, view: View) -> np.ndarray:
        """True camera-space z (metres) of ``view.name`` at ``view.camera``'s size (area-averaged).  # [h, w]"""
        z = np.load(self.root / "depth" / self.file(view.name, ".npy"))
        return resize_area_to(z, (view.camera.height, view.camera.width))

    def seen_by(self, views: Sequence[View], others: Sequence[View]) -> list[np.ndarray]:
        """For each of ``views`` (true cameras, any size): the pixels whose true surface point one of ``others``
        (true cameras at their own size) sees, inside its frame and not hidden: the projected depth agrees with
        that view's true depth within ``SEEN_DEPTH_TOL``. Rays that hit nothing are never seen.  # [h, w] bool each

        Restoration scores over these pixels leave out seabed no training view showed, which no model can
        restore (it can only invent it). Each of ``others``' depth maps is read once."""
        surfaces, worlds = [], []
        for view in views:
            z = self.depth(view)
            cam = view.camera
            x = (np.arange(cam.width) + 0.5 - cam.cx) / cam.fx
            y = (np.arange(cam.height) + 0.5 - cam.cy) / cam.fy
            surface = z < FAR_DEPTH_M
            zs = z[surface].astype(np.float64)
            xc = np.stack([np.broadcast_to(x[None, :], z.shape)[surface] * zs,
                           np.broadcast_to(y[:, None], z.shape)[surface] * zs, zs], axis=1)
            surfaces.append(surface)
            worlds.append((xc - view.t) @ view.R)  # x_cam = R X + t  ->  X = R^T (x_cam - t)
        hits = [np.zeros(len(w), dtype=bool) for w in worlds]
        for o in others:
            z_map = self.depth(o)
            for world, hit in zip(worlds, hits, strict=True):
                u, v, zo = o.project(world)
                with np.errstate(invalid="ignore"):
                    inside = (u >= 0) & (u < o.camera.width) & (v >= 0) & (v < o.camera.height)
                ref = z_map[np.floor(v[inside]).astype(np.int64), np.floor(u[inside]).astype(np.int64)]
                hit[np.flatnonzero(inside)[np.abs(zo[inside] - ref) <= SEEN_DEPTH_TOL * ref]] = True
        out = []
        for surface, hit in zip(surfaces, hits, strict=True):
            seen = np.zeros(surface.shape, dtype=bool)
            seen[surface] = hit
            out.append(seen)
        return out


def is_generated_scene(root: str | Path) -> bool:
    """True when ``root`` looks like the generator's output (water.json with its config, clean/, sparse_gt/)."""
    root = Path(root)
    try:
        meta = json.loads((root / TRUE_WATER_FILE).read_text())  # the generator's true water
    except (OSError, json.JSONDecodeError):
        return False
    return (isinstance(meta, dict) and "generator" in meta and "beta_D" in meta
            and (root / "clean").is_dir() and (root / "sparse_gt").is_dir())


def find_ground_truth(source: str | Path | None, explicit: str | Path | None = None) -> Path | None:
    """The ground-truth scene folder of a job: ``explicit`` if given (it must be a generated scene), else the
    folder the source sits in when the source is that generated scene's ``images/`` or a video in it (a generated
    video's truth is written beside it), else None."""
    if explicit:
        if not is_generated_scene(explicit):
            raise GroundTruthError(f"ground truth {explicit} is not a generated scene folder ({TRUE_WATER_FILE} "
                                   f"with the generator's config, clean/, sparse_gt/)")
        return Path(explicit)
    if source:
        src = Path(source)
        in_scene = (src.is_dir() and src.name == "images") or (src.is_file() and is_video(src))
        if in_scene and is_generated_scene(src.parent):
            log.info("ground truth found next to the source: %s", src.parent)
            return src.parent
    return None


def load_ground_truth(root: str | Path, names: Iterable[str] = ()) -> GroundTruth:
    """The truth of generated scene ``root``; a distorted scene's pinhole-geometry truth comes from pinhole/.
    ``names``: the job's view names; a true view takes the job's name of the same stem, so the job's scene and
    the truth's match by name (a video's ``transect_000123.jpg`` is the truth's ``transect_000123.png``)."""
    root = Path(root)
    if not is_generated_scene(root):
        raise GroundTruthError(f"{root} is not a generated scene folder")
    water = json.loads((root / TRUE_WATER_FILE).read_text())
    pinhole = root / PINHOLE_DIR
    truth_root = pinhole if pinhole.is_dir() else root
    scene = named_as(load_scene(truth_root), names)
    return GroundTruth(truth_root, scene, water, scene_root=root)


def named_as(scene: Scene, names: Iterable[str]) -> Scene:
    """``scene`` with each view renamed to the one of ``names`` that has its stem (views without one, or whose
    stem two names share, keep their own name)."""
    by_stem: dict[str, list[str]] = {}
    for n in names:
        by_stem.setdefault(Path(n).stem, []).append(n)
    ambiguous = sorted(s for s, ns in by_stem.items() if len(ns) > 1)
    if ambiguous:
        log.warning("%d job image stems name two images each (e.g. %s): those views are matched only by their "
                    "full name", len(ambiguous), by_stem[ambiguous[0]])

    def name_of(name: str) -> str:
        match = by_stem.get(Path(name).stem, [])
        return match[0] if len(match) == 1 else name

    sightings = None if scene.sightings is None else {name_of(k): v for k, v in scene.sightings.items()}
    return replace(scene, views=[replace(v, name=name_of(v.name)) for v in scene.views], sightings=sightings)


__all__ = ["GroundTruth", "GroundTruthError", "find_ground_truth", "is_generated_scene", "load_ground_truth",
           "named_as"]
