"""Load a posed scene folder as a :class:`Scene`, whatever common layout it has.

Layouts recognised under ``root`` (first match wins, in this order):

- image folder: ``images/`` (3DGS / COLMAP, our generator), then ``images_wb/`` or ``Images_wb/``
  (SeaThru-NeRF's white-balanced images);
- model folder: ``sparse/0/`` (3DGS / COLMAP), ``sparse/``, ``sparse_gt/`` (our generator's true poses),
  ``sparse_ref/`` (reference models of the shared real fixtures); binary or text, any of them.

A model with PINHOLE / SIMPLE_PINHOLE cameras is read directly. Any other camera model (OPENCV in the
SeaThru-NeRF sets, SIMPLE_RADIAL from a plain COLMAP run, ...) is undistorted to PINHOLE with
``pycolmap.undistort_images`` into a cache folder (``workdir``, default :func:`default_undistort_cache`: the
user's cache, never the survey folder, which may be read-only and is the user's) holding ``images/`` and
``sparse/``, which is then loaded; the cache is reused while the source model and image files are unchanged
(size and mtime fingerprint).

Resolution: ``downscale`` is a divisor (2 = half width and height, like 3DGS's ``-r 2``). It scales the
cameras with :meth:`~pipeline.scene.records.Camera.scaled` (:func:`~pipeline.scene.records.scaled_view`); the view's
camera is then the single source of truth for the image size, and :func:`load_view_image` / :func:`load_images`
read each file and area-average it down to that size.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from pipeline.scene.colmap import UnsupportedCameraError, has_model, quiet_pycolmap, read_colmap
from pipeline.scene.images import read_image, resize_area_to
from pipeline.scene.records import Scene, View, scaled_view

log = logging.getLogger(__name__)

IMAGE_DIRS = ("images", "images_wb", "Images_wb")
SPARSE_DIRS = ("sparse/0", "sparse", "sparse_gt", "sparse_ref")
_CACHE_MARKER = "dualphys-undistorted.json"


class SceneLayoutError(FileNotFoundError):
    """The folder does not look like a posed scene (missing images or model, or images missing)."""


class ImageSizeError(ValueError):
    """An image file's size does not match its camera."""


def find_layout(root: str | os.PathLike[str]) -> tuple[Path, Path]:
    """(images_dir, sparse_dir) of a scene folder; raises :class:`SceneLayoutError` saying what is missing."""
    root = Path(root)
    if not root.is_dir():
        raise SceneLayoutError(f"scene folder {root} does not exist")
    images = next((root / n for n in IMAGE_DIRS if (root / n).is_dir()), None)
    sparse = next((root / n for n in SPARSE_DIRS if has_model(root / n)), None)
    missing = []
    if images is None:
        missing.append(f"an image folder ({', '.join(n + '/' for n in IMAGE_DIRS)})")
    if sparse is None:
        missing.append(
            f"a COLMAP model ({', '.join(n + '/' for n in SPARSE_DIRS)} "
            f"with cameras, images, points3D .bin or .txt)"
        )
    if missing:
        raise SceneLayoutError(
            f"{root} is not a posed scene: it lacks {' and '.join(missing)}. For a folder of unposed images "
            f"run the SfM stage first (pipeline.sfm.recipe.run_sfm)."
        )
    assert images is not None and sparse is not None
    return images, sparse


def default_undistort_cache(sparse_dir: str | os.PathLike[str]) -> Path:
    """Where a model in ``sparse_dir`` is undistorted when the caller names no folder: ``$DUALPHYS_CACHE`` (else
    ``$XDG_CACHE_HOME/dualphys``, else ``~/.cache/dualphys``) ``/undistorted/<hash of the model's path>``."""
    xdg = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    base = os.environ.get("DUALPHYS_CACHE") or xdg / "dualphys"
    key = hashlib.sha1(str(Path(sparse_dir).resolve()).encode()).hexdigest()[:16]
    return Path(base) / "undistorted" / key


def load_scene(
    root: str | os.PathLike[str], *, downscale: float = 1.0, workdir: str | os.PathLike[str] | None = None
) -> Scene:
    """Load the scene under ``root`` (layouts in the module docstring) with PINHOLE cameras.

    ``downscale`` >= 1 divides the image size (cameras scaled accordingly); ``workdir`` is where distorted
    models are undistorted to (default :func:`default_undistort_cache`). Every view's image file must exist.
    Returns views sorted by name with ``image_path`` set and ``root`` = ``root``.
    """
    if not downscale >= 1.0:
        raise ValueError(f"load_scene: downscale is a divisor >= 1 (2 = half size), got {downscale}")
    root = Path(root)
    images_dir, sparse_dir = find_layout(root)
    try:
        scene = read_colmap(sparse_dir, images_dir)
    except UnsupportedCameraError as e:
        cache = Path(workdir) if workdir is not None else default_undistort_cache(sparse_dir)
        log.info(
            "model %s has %s cameras: undistorting to PINHOLE into %s", sparse_dir, "/".join(e.models), cache
        )
        images_dir, sparse_dir = undistort_cached(sparse_dir, images_dir, cache)
        scene = read_colmap(sparse_dir, images_dir)
    if not scene.views:
        raise SceneLayoutError(f"the COLMAP model in {sparse_dir} has no registered images")
    missing = [v.name for v in scene.views if v.image_path is None or not v.image_path.is_file()]
    if missing:
        raise SceneLayoutError(
            f"{len(missing)} of {len(scene.views)} images of the model in {sparse_dir} are missing from "
            f"{images_dir} (e.g. {', '.join(missing[:3])})"
        )
    if downscale != 1.0:
        scene.views = [scaled_view(v, downscale) for v in scene.views]
    scene.root = root
    log.info(
        "loaded %d views, %d points from %s (images %s)",
        len(scene.views),
        len(scene.points),
        sparse_dir,
        images_dir,
    )
    return scene


def undistort_cached(
    sparse_dir: Path, images_dir: Path, cache: Path, *, num_threads: int = 2
) -> tuple[Path, Path]:
    """Undistort a model and its images into ``cache`` (reused while the inputs are unchanged).

    Returns (cache/images, cache/sparse). Refuses to write into a non-empty folder that is not one of its
    own caches, so a mistyped ``workdir`` never gets wiped.
    """
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    key = {
        "sparse": str(sparse_dir.resolve()),
        "images": str(images_dir.resolve()),
        "fingerprint": _fingerprint(sparse_dir, images_dir),
    }
    marker = cache / _CACHE_MARKER
    out_images, out_sparse = cache / "images", cache / "sparse"
    if marker.is_file():
        try:
            same = json.loads(marker.read_text()) == key
        except (OSError, ValueError):
            same = False
        if same and has_model(out_sparse) and out_images.is_dir():
            log.info("reusing undistorted scene in %s", cache)
            return out_images, out_sparse
        shutil.rmtree(cache)
    elif cache.exists() and any(cache.iterdir()):
        raise SceneLayoutError(
            f"cannot undistort into {cache}: the folder exists, is not empty and is not a dualphys cache; "
            f"pass another workdir"
        )
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SceneLayoutError(
            f"cannot create the undistortion cache {cache} ({e}); pass a writable workdir"
        ) from e
    try:
        with quiet_pycolmap(log):
            pycolmap.undistort_images(str(cache), str(sparse_dir), str(images_dir), num_threads=num_threads)
    except (ValueError, RuntimeError) as e:
        raise SceneLayoutError(f"undistorting {sparse_dir} with images {images_dir} failed: {e}") from e
    for extra in ("stereo", "run-colmap-geometric.sh", "run-colmap-photometric.sh"):  # MVS leftovers
        p = cache / extra
        shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
    marker.write_text(json.dumps(key))
    return out_images, out_sparse


def load_view_image(view: View) -> np.ndarray:
    """The view's image at its camera's resolution (area-averaged when the file is larger).  # [h, w, 3]

    Raises :class:`ImageSizeError` when the file is smaller than the camera or has another aspect ratio.
    """
    if view.image_path is None:
        raise ValueError(f"view {view.name} has no image_path")
    img = read_image(view.image_path)
    H, W = img.shape[:2]
    h, w = view.camera.height, view.camera.width
    if (H, W) == (h, w):
        return img
    if h > H or w > W or abs(H * w / W - h) > 1.0:
        raise ImageSizeError(
            f"{view.image_path} is {W}x{H} but its camera is {w}x{h} (not a downscaled copy)"
        )
    return resize_area_to(img, (h, w))


def load_images(scene: Scene) -> list[np.ndarray]:
    """All view images in view order, each [h, w, 3] float32 at its camera's resolution."""
    return [load_view_image(v) for v in scene.views]


def _fingerprint(*dirs: Path) -> str:
    h = hashlib.sha1()
    for d in dirs:
        for p in sorted(d.iterdir()):
            if p.is_file():
                st = p.stat()
                h.update(f"{p.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


__all__ = [
    "IMAGE_DIRS",
    "ImageSizeError",
    "SPARSE_DIRS",
    "SceneLayoutError",
    "find_layout",
    "load_images",
    "load_scene",
    "load_view_image",
    "undistort_cached",
]
