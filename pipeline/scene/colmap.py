"""COLMAP sparse models <-> our :class:`Scene`.

Reading goes through pycolmap (imported lazily), which reads binary and text models, both the pycolmap 4
layout (with ``rigs`` and ``frames`` files) and the classic three-file layout (``cameras``, ``images``,
``points3D``) written by COLMAP 3.x, 3DGS tools and our synthetic generator — checked with pycolmap 4.2.1.
Only undistorted cameras (PINHOLE, SIMPLE_PINHOLE) map onto :class:`Camera`; any other model raises
:class:`UnsupportedCameraError` (``pipeline.scene.loader`` undistorts such models for you).

Writing text needs no pycolmap: :func:`write_colmap_text` emits the classic three-file layout with empty
2D observation lists and empty tracks (our Scene does not keep them), which pycolmap and 3DGS loaders read.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.scene.records import Camera, LensCamera, Scene, Sightings, View

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")


class ColmapModelError(Exception):
    """A COLMAP model folder that is missing or cannot be parsed."""


class UnsupportedCameraError(ColmapModelError):
    """The model uses a distorted camera model; it must be undistorted to PINHOLE first."""

    def __init__(self, sparse_dir: Path, models: list[str]) -> None:
        self.sparse_dir = Path(sparse_dir)
        self.models = models
        super().__init__(
            f"COLMAP model {sparse_dir} uses camera model(s) {', '.join(models)}; the renderer needs "
            f"undistorted PINHOLE cameras. Undistort it first: pipeline.scene.loader.load_scene() does this "
            f"automatically, or run pycolmap.undistort_images / `colmap image_undistorter`."
        )


@contextlib.contextmanager
def quiet_pycolmap(logger: logging.Logger = log) -> Iterator[None]:
    """Silence pycolmap's glog INFO and WARNING lines (about 10 per image) unless ``logger`` is at DEBUG.

    glog's level is process-global, so the previous value is restored on exit.
    """
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if logger.isEnabledFor(logging.DEBUG) else 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def has_model(sparse_dir: str | os.PathLike[str]) -> bool:
    """True when ``sparse_dir`` holds cameras/images/points3D as .bin or .txt."""
    d = Path(sparse_dir)
    return any(
        all((d / f"{n}.{ext}").is_file() for n in ("cameras", "images", "points3D")) for ext in ("bin", "txt")
    )


def read_reconstruction(sparse_dir: str | os.PathLike[str]):  # -> pycolmap.Reconstruction
    """Load a model with pycolmap, turning its C++ check failures into :class:`ColmapModelError`."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    d = Path(sparse_dir)
    if not has_model(d):
        raise ColmapModelError(
            f"no COLMAP model in {d}: expected cameras, images and points3D as .bin or .txt files"
        )
    try:
        with quiet_pycolmap():
            return pycolmap.Reconstruction(str(d))
    except (ValueError, RuntimeError) as e:
        raise ColmapModelError(f"cannot parse the COLMAP model in {d}: {e}") from e


def lens_cameras(sparse_dir: str | os.PathLike[str]) -> dict[str, LensCamera]:
    """Image name -> its camera as the model in ``sparse_dir`` holds it, distortion included (any camera model,
    binary or text)."""
    rec = read_reconstruction(sparse_dir)
    cams = {cid: LensCamera(c.model.name, int(c.width), int(c.height), tuple(float(p) for p in c.params))
            for cid, c in rec.cameras.items()}
    return {img.name: cams[img.camera_id] for img in rec.images.values()}


def camera_models(sparse_dir: str | os.PathLike[str]) -> list[str]:
    """Sorted distinct camera model names used by the model in ``sparse_dir``."""
    rec = read_reconstruction(sparse_dir)
    return sorted({c.model.name for c in rec.cameras.values()})


def read_colmap(
    sparse_dir: str | os.PathLike[str], images_dir: str | os.PathLike[str] | None = None
) -> Scene:
    """Read a COLMAP model (binary or text) as a :class:`Scene`.

    Views are the registered images, sorted by name, with ``image_path = images_dir / name`` when
    ``images_dir`` is given (existence is not checked here). Points are the model's 3D points [P, 3] with
    colours [P, 3] in [0, 1]. Raises :class:`ColmapModelError` for a missing or broken model and
    :class:`UnsupportedCameraError` for distorted cameras.
    """
    sparse_dir = Path(sparse_dir)
    rec = read_reconstruction(sparse_dir)
    bad = sorted({c.model.name for c in rec.cameras.values() if c.model.name not in PINHOLE_MODELS})
    if bad:
        raise UnsupportedCameraError(sparse_dir, bad)
    cams = {cid: _to_camera(c) for cid, c in rec.cameras.items()}
    views = []
    for im in rec.images.values():
        if not im.has_pose:
            continue
        pose = im.cam_from_world()
        views.append(
            View(
                name=im.name,
                camera=cams[im.camera_id],
                R=np.asarray(pose.rotation.matrix(), dtype=np.float64),
                t=np.asarray(pose.translation, dtype=np.float64),
                image_path=Path(images_dir) / im.name if images_dir is not None else None,
            )
        )
    views.sort(key=lambda v: v.name)
    ids = list(rec.points3D.keys())
    row = {pid: i for i, pid in enumerate(ids)}
    points = np.array([rec.points3D[p].xyz for p in ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[p].color for p in ids], dtype=np.float64).reshape(-1, 3) / 255.0
    log.debug("read %d views, %d points from %s", len(views), len(points), sparse_dir)
    return Scene(views=views, points=points, colors=colors, root=sparse_dir, sightings=_sightings(rec, row))


def _sightings(rec, row: dict[int, int]) -> dict[str, Sightings]:  # rec: pycolmap.Reconstruction
    """Per registered image, the 2D observations that belong to a 3D point (the model's tracks)."""
    out = {}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        obs = [(row[p.point3D_id], p.xy) for p in im.points2D if p.has_point3D() and p.point3D_id in row]
        point = np.array([o[0] for o in obs], dtype=np.int64)
        xy = np.array([o[1] for o in obs], dtype=np.float64).reshape(-1, 2)
        out[im.name] = Sightings(point, xy, int(rec.cameras[im.camera_id].width))
    return out


def write_colmap_text(scene: Scene, out_dir: str | os.PathLike[str]) -> Path:
    """Write ``scene`` as a classic three-file COLMAP text model (PINHOLE cameras). Returns ``out_dir``.

    Identical cameras share one camera id; image ids follow the view order (1-based); point errors are
    written as 0 and tracks / 2D observations as empty (the Scene does not carry them).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam_ids: dict[Camera, int] = {}
    for v in scene.views:
        cam_ids.setdefault(v.camera, len(cam_ids) + 1)
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(cam_ids)}",
    ]
    for c, cid in cam_ids.items():
        lines.append(f"{cid} PINHOLE {int(c.width)} {int(c.height)} {_f(c.fx)} {_f(c.fy)} {_f(c.cx)} {_f(c.cy)}")
    _write_lines(out / "cameras.txt", lines)

    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(scene.views)}",
    ]
    for i, v in enumerate(scene.views, start=1):
        q = rotmat_to_qvec(v.R)
        t = np.asarray(v.t, dtype=np.float64).reshape(3)
        nums = " ".join(_f(x) for x in (*q, *t))
        lines += [f"{i} {nums} {cam_ids[v.camera]} {v.name}", ""]
    _write_lines(out / "images.txt", lines)

    pts = np.asarray(scene.points, dtype=np.float64).reshape(-1, 3)
    cols = np.asarray(scene.colors, dtype=np.float64).reshape(-1, 3)
    if len(cols) != len(pts):
        raise ValueError(f"scene.colors {cols.shape} does not match scene.points {pts.shape}")
    rgb = np.clip(np.rint(cols * 255.0), 0, 255).astype(int)
    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {len(pts)}",
    ]
    for j, (p, c) in enumerate(zip(pts, rgb, strict=True), start=1):
        lines.append(f"{j} {_f(p[0])} {_f(p[1])} {_f(p[2])} {c[0]} {c[1]} {c[2]} 0")
    _write_lines(out / "points3D.txt", lines)
    return out


def write_colmap_binary(scene: Scene, out_dir: str | os.PathLike[str]) -> Path:
    """Write ``scene`` as a binary COLMAP model (via a temporary text model read back by pycolmap).

    pycolmap 4 writes ``rigs.bin`` and ``frames.bin`` beside the classic three files; 3DGS-style readers
    ignore them. Returns ``out_dir``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="colmap-txt-", dir=out) as tmp:
        write_colmap_text(scene, tmp)
        read_reconstruction(tmp).write(str(out))
    return out


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> unit quaternion [4] (w, x, y, z) with w >= 0 (COLMAP's order)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"rotmat_to_qvec expects [3, 3]; got {R.shape}")
    # Symmetric 4x4 whose top eigenvector is the quaternion (Bar-Itzhack): stable for every rotation.
    # COLMAP's unpacking: the letter pairs name (column, row), i.e. xy = R[1, 0].
    xx, yx, zx, xy, yy, zy, xz, yz, zz = R.flat
    K = (
        np.array(
            [
                [xx - yy - zz, 0, 0, 0],
                [yx + xy, yy - xx - zz, 0, 0],
                [zx + xz, zy + yz, zz - xx - yy, 0],
                [yz - zy, zx - xz, xy - yx, xx + yy + zz],
            ]
        )
        / 3.0
    )
    w, V = np.linalg.eigh(K)
    x, y, z, qw = V[:, np.argmax(w)]
    q = np.array([qw, x, y, z])
    return q if q[0] >= 0 else -q


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Quaternion [4] (w, x, y, z), any norm > 0 -> rotation matrix [3, 3]."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _to_camera(c) -> Camera:  # c: pycolmap.Camera with a PINHOLE or SIMPLE_PINHOLE model
    p = [float(x) for x in c.params]
    if c.model.name == "SIMPLE_PINHOLE":
        f, cx, cy = p
        return Camera(int(c.width), int(c.height), f, f, cx, cy)
    fx, fy, cx, cy = p
    return Camera(int(c.width), int(c.height), fx, fy, cx, cy)


def _f(x: float) -> str:
    """Shortest text that reads back to the same float64 (``repr`` of a Python float)."""
    return repr(float(x))


def _write_lines(path: Path, lines: list[str]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)


__all__ = [
    "ColmapModelError",
    "PINHOLE_MODELS",
    "UnsupportedCameraError",
    "camera_models",
    "has_model",
    "lens_cameras",
    "quiet_pycolmap",
    "qvec_to_rotmat",
    "read_colmap",
    "read_reconstruction",
    "rotmat_to_qvec",
    "write_colmap_binary",
    "write_colmap_text",
]
