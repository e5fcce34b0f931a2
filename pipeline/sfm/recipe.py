"""The SfM stage: a short, seeded pycolmap recipe from a folder of photos to the 3DGS trainer layout.

Recipe: decode-check every file (pycolmap silently drops unreadable ones) → SIFT on the CPU → exhaustive or
sequential matching (:func:`choose_matcher`) → incremental mapping (seeded) → keep the model with the most
registered images → undistort to PINHOLE. Output folder ``OUT``::

    OUT/images/                              undistorted images (the names of the input files)
    OUT/sparse/0/{cameras,images,points3D}.bin   PINHOLE model (+ rigs.bin, frames.bin from pycolmap 4)
    OUT/distorted/database.db                features and matches
    OUT/distorted/sparse/0/                  the model before undistortion (cfg.camera_model cameras)

pycolmap "warns and returns an empty result" on hopeless input; here every such case is a typed
:class:`SfmError` whose message says what to fix. Only SIFT is used: this pycolmap wheel aborts the whole
process for ALIKED / LightGlue (no ONNX), so the extractor type is never configurable.

Reproducibility: seeded, and image ids follow the sorted names, so features and matches are identical run to
run. With ``num_threads=1`` (the default) the whole output is bit-identical; with 2 threads the model
moved run to run (the mapper alone on one thread was not enough), and training amplified the difference. One
thread costs about a quarter more SfM time (the measurements: docs/DECISIONS.md, "SfM").
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from pipeline.config import SfmConfig
from pipeline.scene.colmap import quiet_pycolmap
from pipeline.scene.images import (
    IMAGE_EXTENSIONS,
    JPEG_EXTENSIONS,
    ImageReadError,
    image_orientation,
    list_images,
    read_image,
    write_image,
)

log = logging.getLogger(__name__)

MIN_IMAGES = 3  # pycolmap never built a model from 2 views (docs/DECISIONS.md, "Numbers behind code comments")
# Camera models SfM may refine before undistortion (all undistortable to PINHOLE by COLMAP).
CAMERA_MODELS = (
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
    "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE",
)  # fmt: skip


class SfmError(RuntimeError):
    """SfM could not produce a usable model. ``skipped`` lists unreadable input files (name, reason)."""

    def __init__(self, message: str, *, skipped: list[tuple[str, str]] | None = None) -> None:
        super().__init__(message)
        self.skipped = list(skipped or [])


class NoImagesError(SfmError):
    """The folder is missing, empty, or none of its image files decodes."""


class TooFewImagesError(SfmError):
    """Fewer than :data:`MIN_IMAGES` readable images."""


class NoModelError(SfmError):
    """No reconstruction could be started (no matches, or no image pair with enough parallax)."""


class TooFewRegisteredError(SfmError):
    """A model was built but it places fewer than ``cfg.min_registered`` images."""


@dataclass
class SfmSummary:
    """What the SfM stage did; JSON-able through :meth:`to_dict`."""

    registered: int  # images with a pose in the kept model
    total: int  # image files found in the input folder (including skipped ones)
    mean_reproj_error_px: float  # of the kept model, before undistortion
    num_points3D: int
    seconds: float  # wall time of the whole stage
    matcher: str  # "exhaustive" or "sequential"
    skipped: list[tuple[str, str]] = field(default_factory=list)  # (file name, reason) not used at all
    warnings: list[str] = field(default_factory=list)
    unregistered: list[str] = field(default_factory=list)  # readable images the model could not place

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def choose_matcher(names: list[str], cfg: SfmConfig) -> Literal["exhaustive", "sequential"]:
    """The matcher for a set of image names.

    Rule for ``cfg.matcher == "auto"``: exhaustive (every pair; the most robust) when there are at most
    ``cfg.exhaustive_max_images`` images; above that, sequential (each image with its
    ``cfg.sequential_overlap`` successors, plus quadratic jumps) when the names form a numbered sequence
    (:func:`is_numbered_sequence`: video frames, an ROV's interval shots), otherwise still exhaustive, since
    unordered names give sequential matching no meaning. An explicit ``cfg.matcher`` is obeyed.
    """
    if cfg.matcher in ("exhaustive", "sequential"):
        return cfg.matcher
    if cfg.matcher != "auto":
        raise ValueError(f"SfmConfig.matcher must be auto, exhaustive or sequential; got {cfg.matcher!r}")
    if len(names) <= cfg.exhaustive_max_images:
        return "exhaustive"
    return "sequential" if is_numbered_sequence(names) else "exhaustive"


def is_numbered_sequence(names: list[str]) -> bool:
    """True when every name is ``<prefix><number>.<ext>`` with one common prefix and, in plain name order
    (the order COLMAP's sequential matcher uses), the numbers strictly increase (gaps allowed)."""
    parsed = []
    for n in sorted(names):
        m = re.fullmatch(r"(.*?)(\d+)", Path(n).stem)
        if m is None:
            return False
        parsed.append((m.group(1), int(m.group(2))))
    if len(parsed) < 2 or len({p for p, _ in parsed}) != 1:
        return False
    nums = [k for _, k in parsed]
    return all(b > a for a, b in zip(nums, nums[1:], strict=False))


def run_sfm(
    images_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    cfg: SfmConfig | None = None,
    *,
    cancellation_token: Any = None,
) -> SfmSummary:
    """Reconstruct cameras and sparse points from the photos in ``images_dir`` into ``out_dir``.

    Writes the layout of the module docstring (previous ``images/``, ``sparse/`` and ``distorted/`` in
    ``out_dir`` are replaced). ``cancellation_token`` (a ``pycolmap.CancellationToken``) makes the running
    pycolmap step raise ``InterruptedError`` when cancelled. Raises a subclass of :class:`SfmError` when
    no usable model results, ``ValueError`` for an invalid config.
    """
    import pycolmap

    cfg = cfg or SfmConfig()
    _check_config(cfg)
    t0 = time.perf_counter()
    images_dir, out = Path(images_dir), Path(out_dir)
    if (out / "images").resolve() == images_dir.resolve():
        raise ValueError(
            f"run_sfm would overwrite its input {images_dir} with undistorted images; pick another out_dir"
        )
    try:
        files = list_images(images_dir)
    except FileNotFoundError as e:
        raise NoImagesError(f"image folder {images_dir} does not exist") from e
    if not files:
        raise NoImagesError(
            f"no images in {images_dir} (looked for {', '.join(sorted(IMAGE_EXTENSIONS))}, any case)"
        )
    good, skipped = _probe(files)
    warnings: list[str] = []
    total = len(files)
    if not good:
        raise NoImagesError(
            f"none of the {total} image files in {images_dir} can be decoded", skipped=skipped
        )
    if len(good) < MIN_IMAGES:
        raise TooFewImagesError(_too_few_msg(len(good), images_dir), skipped=skipped)

    distorted = out / "distorted"
    for old in (out / "images", out / "sparse", distorted):
        if old.exists():
            shutil.rmtree(old)
    distorted.mkdir(parents=True)
    src_dir = _stage_oriented(images_dir, good, distorted / "oriented", warnings)
    names = [p.name for p in good]
    matcher = choose_matcher(names, cfg)
    sizes = set(good.values())
    camera_mode = pycolmap.CameraMode.AUTO
    if cfg.single_camera and len(sizes) == 1:
        camera_mode = pycolmap.CameraMode.SINGLE
    elif cfg.single_camera:
        warnings.append(
            f"images have {len(sizes)} different sizes, so they cannot share one camera: "
            f"separate cameras are estimated instead"
        )
    log.info("sfm: %d readable of %d images, %s matching, %s", len(good), total, matcher, cfg.camera_model)

    with quiet_pycolmap(log):
        pycolmap.set_random_seed(cfg.seed)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = cfg.camera_model
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = cfg.num_threads
        ext.max_image_size = cfg.max_image_size
        ext.sift.max_num_features = cfg.max_num_features
        attempt = _Attempt(src_dir, names, camera_mode, reader, ext, matcher, cfg, cancellation_token, skipped)
        rec, first_error = None, None
        try:
            rec, names = attempt.run(distorted / "database.db", src_dir, distorted, images_dir)
        except (NoModelError, TooFewRegisteredError) as e:
            first_error = e
        if rec is None or rec.num_reg_images() < RETRY_BELOW_REGISTERED * len(names):
            # Murky water: SIFT's contrast threshold leaves too few features on a dark, hazy frame. Extract
            # them again from contrast-stretched copies (mapping still reads the originals for point colours).
            stretched = _stage_stretched(src_dir, names, distorted / "stretched")
            try:
                rec2, names2 = attempt.run(distorted / "database_stretched.db", stretched, distorted, images_dir)
            except (NoModelError, TooFewRegisteredError):
                rec2 = None
            if rec2 is not None and (rec is None or rec2.num_reg_images() > rec.num_reg_images()):
                warnings.append(f"low-contrast images: features were extracted from contrast-stretched copies "
                                f"({rec2.num_reg_images()} registered, "
                                f"{rec.num_reg_images() if rec is not None else 0} without)")
                rec, names = rec2, names2
        if rec is None:
            assert first_error is not None
            raise first_error
        registered = rec.num_reg_images()
        reproj = float(rec.compute_mean_reprojection_error())
        model_dir = distorted / "sparse" / "0"
        model_dir.mkdir(parents=True)
        rec.write(str(model_dir))
        _undistort(model_dir, src_dir, out, distorted / "_undistort", cfg, cancellation_token)

    placed = {im.name for im in rec.images.values() if im.has_pose}
    unregistered = [n for n in names if n not in placed]
    if registered < 0.5 * len(names):
        warnings.append(
            f"only {registered} of {len(names)} readable images were registered; the scene "
            f"may be split into parts that do not overlap"
        )
    if skipped:
        warnings.append(f"{len(skipped)} file(s) skipped: " + "; ".join(f"{n}: {r}" for n, r in skipped))
    summary = SfmSummary(
        registered=registered, total=total, mean_reproj_error_px=reproj, num_points3D=rec.num_points3D(),
        seconds=time.perf_counter() - t0, matcher=matcher, skipped=skipped, warnings=warnings,
        unregistered=unregistered,
    )  # fmt: skip
    log.info("sfm: registered %d/%d, %d points, reprojection error %.3f px, %.1f s", registered, total,
             summary.num_points3D, reproj, summary.seconds)  # fmt: skip
    for w in warnings:
        log.warning("sfm: %s", w)
    return summary


def _check_config(cfg: SfmConfig) -> None:
    if cfg.matcher not in ("auto", "exhaustive", "sequential"):
        raise ValueError(f"SfmConfig.matcher must be auto, exhaustive or sequential; got {cfg.matcher!r}")
    if cfg.camera_model not in CAMERA_MODELS:
        raise ValueError(
            f"SfmConfig.camera_model must be one of {', '.join(CAMERA_MODELS)}; got {cfg.camera_model!r}"
        )
    if cfg.num_threads == 0 or cfg.num_threads < -1:
        raise ValueError(f"SfmConfig.num_threads must be >= 1 or -1 (all cores); got {cfg.num_threads}")
    if cfg.sequential_overlap < 1 or cfg.max_image_size < 64 or cfg.max_num_features < 100:
        raise ValueError(f"SfmConfig values out of range: {cfg}")


def _too_few_msg(n: int, images_dir: Path) -> str:
    return (f"only {n} readable image(s) in {images_dir}; SfM needs at least {MIN_IMAGES} overlapping photos "
            f"taken from different positions")  # fmt: skip


def _probe(files: list[Path]) -> tuple[dict[Path, tuple[int, int]], list[tuple[str, str]]]:
    """Decode every file: ({path: (width, height)} of the good ones, [(name, reason)] of the others)."""
    good: dict[Path, tuple[int, int]] = {}
    skipped: list[tuple[str, str]] = []
    for p in files:
        try:
            img = read_image(p)  # [H, W, 3], orientation applied
        except ImageReadError as e:
            skipped.append((p.name, e.reason))
            continue
        good[p] = (img.shape[1], img.shape[0])
    return good, skipped


def _stage_oriented(
    images_dir: Path, good: dict[Path, tuple[int, int]], stage: Path, warnings: list[str]
) -> Path:
    """The folder pycolmap should read: ``images_dir`` itself, or, when some files carry an EXIF rotation
    (pycolmap ignores it, our reader applies it), a folder of links with rotated copies of those files."""
    rotated = [p for p in good if image_orientation(p) != 1]
    if not rotated:
        return images_dir
    warnings.append(f"{len(rotated)} image(s) carry an EXIF rotation; SfM ran on upright copies "
                    f"(re-encoded) so poses match the images as displayed")  # fmt: skip
    stage.mkdir(parents=True)
    for p in good:
        if p in rotated:
            write_image(
                stage / p.name, read_image(p), bits=8 if p.suffix.lower() in JPEG_EXTENSIONS else None
            )
        else:
            os.symlink(p.resolve(), stage / p.name)
    return stage


RETRY_BELOW_REGISTERED = 0.8  # fewer registered images than this share: try again on contrast-stretched copies
STRETCH_PERCENTILES = (1.0, 99.0)  # each channel is stretched linearly so these percentiles map to 0 and 1


@dataclass
class _Attempt:
    """One feature extraction + matching + mapping pass over the same images (the retry changes only where the
    features are read from)."""

    src_dir: Path
    names: list[str]
    camera_mode: Any
    reader: Any
    ext: Any
    matcher: str
    cfg: SfmConfig
    token: Any
    skipped: list[tuple[str, str]]

    def run(self, db_path: Path, feature_dir: Path, distorted: Path, images_dir: Path) -> tuple[Any, list[str]]:
        """(the largest model, the names that were read); raises NoModelError / TooFewRegisteredError."""
        import pycolmap

        if db_path.exists():
            db_path.unlink()
        names = list(self.names)
        # Register the images first, one thread, in name order: image ids then follow the names. Letting the
        # multi-threaded extractor create them numbers them in completion order, which changes match and
        # mapping order and makes runs differ (docs/DECISIONS.md, "Numbers behind code comments").
        pycolmap.Database.open(str(db_path)).close()  # import_images needs an existing database
        pycolmap.import_images(db_path, feature_dir, camera_mode=self.camera_mode, image_names=names,
                               options=self.reader)
        pycolmap.extract_features(
            db_path, feature_dir, image_names=names, camera_mode=self.camera_mode, reader_options=self.reader,
            extraction_options=self.ext, device=pycolmap.Device.cpu, cancellation_token=self.token,
        )  # fmt: skip
        in_db = _db_image_names(db_path)
        for n in names:
            if n not in in_db and (n, "pycolmap could not read it") not in self.skipped:
                self.skipped.append((n, "pycolmap could not read it"))
        names = [n for n in names if n in in_db]
        if len(names) < MIN_IMAGES:
            raise TooFewImagesError(_too_few_msg(len(names), images_dir), skipped=self.skipped)
        _match(db_path, self.matcher, self.cfg, self.token)
        if _num_inlier_matches(db_path) == 0:
            raise NoModelError(
                f"no two of the {len(names)} images in {images_dir} share enough features to be matched. "
                f"Photos must overlap (about 60 % between neighbours) and show texture; open water, sand or "
                f"very turbid water gives too few features.",
                skipped=self.skipped,
            )
        rec = _map(db_path, self.src_dir, distorted, self.cfg, self.token)
        if rec is None:
            raise NoModelError(
                f"pycolmap could not start a 3D model from the {len(names)} images in {images_dir}: no "
                f"pair of images with enough parallax. The camera must move between shots (identical or "
                f"rotation-only photos cannot be triangulated).",
                skipped=self.skipped,
            )
        if rec.num_reg_images() < self.cfg.min_registered:
            raise TooFewRegisteredError(
                f"only {rec.num_reg_images()} of {len(names)} images in {images_dir} could be placed in the 3D "
                f"model (at least {self.cfg.min_registered} needed). Check the overlap between consecutive photos.",
                skipped=self.skipped,
            )
        return rec, names


def _stage_stretched(src_dir: Path, names: list[str], stage: Path) -> Path:
    """Contrast-stretched 8-bit copies of ``names`` (same names) for feature extraction: each channel linearly
    from its ``STRETCH_PERCENTILES`` to [0, 1]."""
    import numpy as np

    stage.mkdir(parents=True, exist_ok=True)
    for n in names:
        img = read_image(src_dir / n)  # [H, W, 3] in [0, 1]
        lo, hi = np.percentile(img.reshape(-1, img.shape[-1]), STRETCH_PERCENTILES, axis=0)
        out = np.clip((img - lo) / np.maximum(hi - lo, 1.0 / 255.0), 0.0, 1.0)
        write_image(stage / n, out, bits=8)
    return stage


def _db_image_names(db_path: Path) -> set[str]:
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        return {im.name for im in db.read_all_images()}
    finally:
        db.close()


def _num_inlier_matches(db_path: Path) -> int:
    """Inlier correspondences over all pairs (``num_verified_image_pairs`` counts 0-inlier pairs too)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        return int(db.num_inlier_matches())
    finally:
        db.close()


def _match(db_path: Path, matcher: str, cfg: SfmConfig, token: Any) -> None:
    import pycolmap

    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = cfg.num_threads
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = cfg.seed
    if matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.sequential_overlap
        pairing.num_threads = cfg.num_threads
        pairing.loop_detection = False  # needs a vocabulary tree file we do not ship
        pycolmap.match_sequential(db_path, matching_options=mopts, pairing_options=pairing,
                                  verification_options=verify, device=pycolmap.Device.cpu,
                                  cancellation_token=token)  # fmt: skip
    else:
        pycolmap.match_exhaustive(db_path, matching_options=mopts, verification_options=verify,
                                  device=pycolmap.Device.cpu, cancellation_token=token)  # fmt: skip


def _map(db_path: Path, image_dir: Path, distorted: Path, cfg: SfmConfig, token: Any):
    """Incremental mapping; the model with the most registered images, or None when there is none."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.mapper.random_seed = cfg.seed
    opts.triangulation.random_seed = cfg.seed
    # Default 10 would discard every model of a small set; we pick the largest model ourselves anyway.
    opts.min_model_size = max(MIN_IMAGES, min(opts.min_model_size, cfg.min_registered))
    tmp = distorted / "_models"
    tmp.mkdir()
    try:
        recs = pycolmap.incremental_mapping(db_path, image_dir, tmp, options=opts, cancellation_token=token)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    recs = [r for r in recs.values() if r.num_reg_images() > 0]
    if not recs:
        return None
    if len(recs) > 1:
        log.info("sfm: %d separate models (%s images); keeping the largest", len(recs),
                 ", ".join(str(r.num_reg_images()) for r in recs))  # fmt: skip
    return max(recs, key=lambda r: r.num_reg_images())


def _undistort(model_dir: Path, image_dir: Path, out: Path, tmp: Path, cfg: SfmConfig, token: Any) -> None:
    """PINHOLE undistortion into ``out/images`` and ``out/sparse/0`` (MVS leftovers dropped)."""
    import pycolmap

    pycolmap.undistort_images(str(tmp), str(model_dir), str(image_dir), num_threads=cfg.num_threads,
                              cancellation_token=token)  # fmt: skip
    (out / "sparse").mkdir(parents=True, exist_ok=True)
    shutil.move(str(tmp / "images"), str(out / "images"))
    shutil.move(str(tmp / "sparse"), str(out / "sparse" / "0"))
    shutil.rmtree(tmp)


__all__ = [
    "CAMERA_MODELS",
    "MIN_IMAGES",
    "NoImagesError",
    "NoModelError",
    "SfmError",
    "SfmSummary",
    "TooFewImagesError",
    "TooFewRegisteredError",
    "choose_matcher",
    "is_numbered_sequence",
    "run_sfm",
]
