"""The SfM stage: a short, seeded pycolmap recipe from a folder of photos to the 3DGS trainer layout.

Recipe: decode-check every file (pycolmap silently drops unreadable ones) → SIFT on the CPU → exhaustive or
sequential matching (:func:`choose_matcher`) → incremental mapping (seeded) → keep the model with the most
registered images → undistort to PINHOLE. When readable frames are left out, the retry ladder
(:func:`_retry_dropped`) tries COLMAP's remedies, cheapest first, and keeps a rung's model only if it places more
frames; every frame still left out is reported with its reason (``SfmSummary.dropped``). Output folder ``OUT``::

    OUT/images/                              undistorted images (the names of the input files)
    OUT/sparse/0/{cameras,images,points3D}.bin   PINHOLE model (+ rigs.bin, frames.bin from pycolmap 4)
    OUT/distorted/database.db                features and matches
    OUT/distorted/sparse/0/                  the model before undistortion (cfg.camera_model cameras)
    OUT/distorted/sparse/1, 2, ...           the other models when the survey broke apart (1 is the second
                                             largest, and so on), kept for separate processing
    OUT/distorted/vocab_tree.bin             sequential matching only: the survey's own tree for loops
    OUT/distorted/database_features.db       the ladder's last rung only: more features, guided matching

pycolmap "warns and returns an empty result" on hopeless input; here every such case is a typed
:class:`SfmError` whose message says what to fix. Only SIFT is used: this pycolmap wheel aborts the whole
process for ALIKED / LightGlue (no ONNX), so the extractor type is never configurable.

Reproducibility: seeded, and image ids follow the sorted names, so features and matches are identical run to
run. With ``num_threads=1`` (the default) the whole output is bit-identical; with 2 threads the model
moved run to run (the mapper alone on one thread was not enough), and training amplified the difference. One
thread costs about a quarter more SfM time (the measurements: docs/DECISIONS.md, "SfM"). Feature extraction and
undistortion work on one image at a time and use ``image_threads`` (all cores): the same bytes on any count.
"""

from __future__ import annotations

import copy
import logging
import os
import re
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

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
from pipeline.sfm.config import SfmConfig
from pipeline.sfm.dropped import DroppedFrame, drop_reasons
from pipeline.sfm.loops import LOOP_NUM_IMAGES, LOOP_PERIOD, build_vocab_tree
from pipeline.sfm.mapping import MIN_MODEL_IMAGES, RELAXED_MIN_NUM_MATCHES, map_models, mapper_options

log = logging.getLogger(__name__)

MIN_IMAGES = MIN_MODEL_IMAGES
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
class SubModel:
    """A model SfM built besides the kept one: where it is on disk and which images it placed that the kept model
    did not (:func:`separate_models`)."""

    index: int  # written to distorted/sparse/<index>
    registered: int  # len(images)
    images: list[str]


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
    # The survey broke into several models: the largest is kept (sparse/0), the others are listed here
    # (largest first) and written to distorted/sparse/1, 2, ... Their images are in ``unregistered`` too.
    other_models: list[SubModel] = field(default_factory=list)
    pairs_matched: int = 0  # image pairs with geometrically verified inliers
    loop_pairs: int = 0  # of those, pairs further apart in name order than the sequential window (loops)
    phase_seconds: dict[str, float] = field(default_factory=dict)  # extract, vocab, match, map, undistort
    dropped: list[DroppedFrame] = field(default_factory=list)  # each readable frame not in the kept model, and why
    # The retry ladder's rungs that ran, in order: {rung, registered, models, reproj_px, seconds, kept}
    retries: list[dict[str, Any]] = field(default_factory=list)

    @property
    def outcome(self) -> str:
        """``"split"`` when the images formed several models (the largest kept), else ``"single"``."""
        return "split" if self.other_models else "single"

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "outcome": self.outcome}


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
    """True when every name is ``<prefix><number>.<ext>`` and, in plain name order (the order COLMAP's sequential
    matcher uses), the numbers strictly increase (gaps allowed), with either one common prefix or a capture time
    as the prefix: digits and separators only, never decreasing (``20230320_012253_000_0001.jpg``, AIMS
    ReefScan's date_time_ms_counter names)."""
    parsed = []
    for n in sorted(names):
        m = re.fullmatch(r"(.*?)(\d+)", Path(n).stem)
        if m is None:
            return False
        parsed.append((m.group(1), int(m.group(2))))
    if len(parsed) < 2:
        return False
    prefixes = [p for p, _ in parsed]
    if len(set(prefixes)) != 1 and not _is_time_prefix_sequence(prefixes):
        return False
    nums = [k for _, k in parsed]
    return all(b > a for a, b in zip(nums, nums[1:], strict=False))


def _is_time_prefix_sequence(prefixes: list[str]) -> bool:
    """Every prefix is digits and separators (``_-.T``) with the same digit count, and their digits read as one
    number never decrease in name order: a timestamp of capture."""
    if not all(re.fullmatch(r"[\d_\-.T]*\d[\d_\-.T]*", p) for p in prefixes):
        return False
    digits = [re.sub(r"\D", "", p) for p in prefixes]
    if len({len(d) for d in digits}) != 1:
        return False
    times = [int(d) for d in digits]
    return all(b >= a for a, b in zip(times, times[1:], strict=False))


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
    cfg = cfg or SfmConfig()
    _check_config(cfg)
    t0 = time.perf_counter()
    images_dir, out = Path(images_dir), Path(out_dir)
    good, skipped, total = _readable_images(images_dir, out)
    distorted = _fresh_output(out)
    warnings: list[str] = []
    src_dir = _stage_oriented(images_dir, good, distorted / "oriented", warnings)
    names = [p.name for p in good]
    matcher = choose_matcher(names, cfg)
    sizes = set(good.values())
    camera_mode = _camera_mode(sizes, cfg, warnings)
    log.info("sfm: %d readable of %d images, %s matching, %s", len(good), total, matcher, cfg.camera_model)

    with quiet_pycolmap(log):
        attempt = _first_attempt(src_dir, names, camera_mode, matcher, cfg, cancellation_token, skipped)
        found = _map_or_stretch(attempt, names, distorted, images_dir, warnings)
        retries = _retry_or_fail(found, attempt, distorted, sizes, cfg)
        rec, names = found.recs[0], found.names
        registered = rec.num_reg_images()
        reproj = float(rec.compute_mean_reprojection_error())
        placed = {im.name for im in rec.images.values() if im.has_pose}
        others = separate_models(_write_models(found.recs, distorted / "sparse"), placed)
        t_und = time.perf_counter()
        undistort_model(distorted / "sparse" / "0", src_dir, out, distorted / "_undistort", cfg, cancellation_token)
        attempt.phases["undistort"] = time.perf_counter() - t_und

    min_matches = RELAXED_MIN_NUM_MATCHES if retries else mapper_options(cfg).min_num_matches
    dropped = drop_reasons(found.db, names, placed, [(m.index, m.images) for m in others], min_matches)
    warnings += _outcome_warnings(names, registered, retries, others, skipped)
    summary = SfmSummary(
        registered=registered, total=total, mean_reproj_error_px=reproj, num_points3D=rec.num_points3D(),
        seconds=time.perf_counter() - t0, matcher=matcher, skipped=skipped, warnings=warnings,
        unregistered=[n for n in names if n not in placed], other_models=others, pairs_matched=attempt.stats[0],
        loop_pairs=attempt.stats[1], phase_seconds={k: round(v, 3) for k, v in attempt.phases.items()},
        dropped=dropped, retries=retries,
    )  # fmt: skip
    _log_outcome(summary)
    return summary


def _readable_images(images_dir: Path, out: Path) -> tuple[dict[Path, tuple[int, int]], list[tuple[str, str]], int]:
    """The images of ``images_dir`` that decode ({path: (width, height)}), the files that do not ([(name,
    reason)]) and the count of image files; raises ValueError when ``out`` would overwrite them, NoImagesError
    or TooFewImagesError when too few decode."""
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
    if not good:
        raise NoImagesError(
            f"none of the {len(files)} image files in {images_dir} can be decoded", skipped=skipped
        )
    if len(good) < MIN_IMAGES:
        raise TooFewImagesError(_too_few_msg(len(good), images_dir), skipped=skipped)
    return good, skipped, len(files)


def _fresh_output(out: Path) -> Path:
    """Remove a previous run's ``images/``, ``sparse/`` and ``distorted/`` from ``out``; returns the new, empty
    ``distorted/``."""
    distorted = out / "distorted"
    for old in (out / "images", out / "sparse", distorted):
        if old.exists():
            shutil.rmtree(old)
    distorted.mkdir(parents=True)
    return distorted


def _camera_mode(sizes: set[tuple[int, int]], cfg: SfmConfig, warnings: list[str]) -> Any:
    """One camera for all images when ``cfg.single_camera`` and they share one size (else a warning), otherwise
    COLMAP's AUTO."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    if cfg.single_camera and len(sizes) == 1:
        return pycolmap.CameraMode.SINGLE
    if cfg.single_camera:
        warnings.append(
            f"images have {len(sizes)} different sizes, so they cannot share one camera: "
            f"separate cameras are estimated instead"
        )
    return pycolmap.CameraMode.AUTO


def _first_attempt(src_dir: Path, names: list[str], camera_mode: Any, matcher: str, cfg: SfmConfig, token: Any,
                   skipped: list[tuple[str, str]]) -> _Attempt:
    """The pass's settings from ``cfg`` (camera model, SIFT threads, image size and feature count), with
    pycolmap's random seed set."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    pycolmap.set_random_seed(cfg.seed)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = cfg.image_threads
    ext.max_image_size = cfg.max_image_size
    ext.sift.max_num_features = cfg.max_num_features
    return _Attempt(src_dir, names, camera_mode, reader, ext, matcher, cfg, token, skipped)


@dataclass
class _Models:
    """The models the passes built so far (largest first; None: no pass built one) and where they came from."""

    recs: list | None
    names: list[str]  # the images the models' pass read
    db: Path  # its database
    feature_dir: Path  # the folder its features were extracted from
    first_error: SfmError | None  # why the first pass built no usable model, if it did not


def _map_or_stretch(attempt: _Attempt, names: list[str], distorted: Path, images_dir: Path,
                    warnings: list[str]) -> _Models:
    """Extract, match and map; when fewer than :data:`RETRY_BELOW_REGISTERED` of the images are placed in any
    model, again from contrast-stretched copies, whose models are kept when their largest places more."""
    found = _Models(None, names, distorted / "database.db", attempt.src_dir, None)
    try:
        found.recs, found.names = attempt.run(found.db, attempt.src_dir, distorted, images_dir)
    except (NoModelError, TooFewRegisteredError) as e:
        found.first_error = e
    placed_anywhere = sum(r.num_reg_images() for r in found.recs) if found.recs is not None else 0
    if placed_anywhere >= RETRY_BELOW_REGISTERED * len(found.names):
        return found
    # Murky water: SIFT's contrast threshold leaves too few features on a dark, hazy frame. Extract them again
    # from contrast-stretched copies (mapping still reads the originals for point colours). Images placed in any
    # model count: a survey split into well-registered parts is not murky.
    stretched = _stage_stretched(attempt.src_dir, found.names, distorted / "stretched")
    first_stats = attempt.stats
    try:
        recs2, names2 = attempt.run(distorted / "database_stretched.db", stretched, distorted, images_dir)
    except (NoModelError, TooFewRegisteredError):
        recs2 = None
    n_before = found.recs[0].num_reg_images() if found.recs is not None else 0
    if recs2 is not None and recs2[0].num_reg_images() > n_before:
        warnings.append(f"low-contrast images: features were extracted from contrast-stretched copies "
                        f"({recs2[0].num_reg_images()} registered, {n_before} without)")
        found.recs, found.names = recs2, names2
        found.db, found.feature_dir = distorted / "database_stretched.db", stretched
    else:
        attempt.stats = first_stats
    return found


def _retry_or_fail(found: _Models, attempt: _Attempt, distorted: Path, sizes: set[tuple[int, int]],
                   cfg: SfmConfig) -> list[dict[str, Any]]:
    """The retry ladder (:func:`_retry_dropped`, into ``found``) while frames are left out; raises the first
    pass's error when still no model places ``cfg.min_registered`` images. Returns the rungs that ran."""
    retries: list[dict[str, Any]] = []
    if cfg.retry_dropped and (found.recs is None or found.recs[0].num_reg_images() < len(found.names)):
        # No model at all (no initial pair passed COLMAP's thresholds) is where the ladder starts too.
        largest = max(max(wh) for wh in sizes)
        found.recs, found.db = _retry_dropped(found.recs or [], found.names, found.db, found.feature_dir, distorted,
                                              attempt, largest, retries)  # fmt: skip
    if not found.recs or found.recs[0].num_reg_images() < cfg.min_registered:
        first_error = found.first_error
        assert first_error is not None  # a model the first pass accepted is only ever replaced by a larger one
        if retries:
            first_error.args = (f"{first_error} (the retry ladder ran "
                                f"{', '.join(r['rung'] for r in retries)} and did not help either)",)  # fmt: skip
        raise first_error
    return retries


def _outcome_warnings(names: list[str], registered: int, retries: list[dict[str, Any]], others: list[SubModel],
                      skipped: list[tuple[str, str]]) -> list[str]:
    """What the user should know about the kept model: the retries, a split survey, few registered, skipped
    files."""
    warnings = []
    if retries:
        kept = [r["rung"] for r in retries if r["kept"]]
        warnings.append(
            f"{len(names) - retries[0]['registered_before']} frame(s) were left out at first; the retry ladder "
            f"ran {', '.join(r['rung'] for r in retries)}"
            + (f" and kept {kept[-1]}" if kept else ", none placed more")
            + f": {registered} of {len(names)} registered"
        )
    if others:
        warnings.append(
            f"the images formed {len(others) + 1} separate models that share no matches: the largest "
            f"({registered} images) is used, the others ("
            + ", ".join(f"{m.registered} images: {_name_range(m.images)}" for m in others)
            + ") are left out and kept in distorted/sparse/1.. for separate processing. Photos must overlap "
            "along the whole survey (about 60 % between neighbours)."
        )
    if registered < 0.5 * len(names):
        warnings.append(
            f"only {registered} of {len(names)} readable images were registered; the scene "
            f"may be split into parts that do not overlap"
        )
    if skipped:
        warnings.append(f"{len(skipped)} file(s) skipped: " + "; ".join(f"{n}: {r}" for n, r in skipped))
    return warnings


def _log_outcome(s: SfmSummary) -> None:
    log.info("sfm: registered %d/%d, %d points, reprojection error %.3f px, %d pairs (%d loop), %.1f s (%s)",
             s.registered, s.total, s.num_points3D, s.mean_reproj_error_px, s.pairs_matched, s.loop_pairs,
             s.seconds, ", ".join(f"{k} {v:.1f}" for k, v in s.phase_seconds.items()))  # fmt: skip
    for w in s.warnings:
        log.warning("sfm: %s", w)
    for d in s.dropped:
        log.warning("sfm: dropped %s: %s", d.name, d.reason)


def _check_config(cfg: SfmConfig) -> None:
    if cfg.matcher not in ("auto", "exhaustive", "sequential"):
        raise ValueError(f"SfmConfig.matcher must be auto, exhaustive or sequential; got {cfg.matcher!r}")
    if cfg.camera_model not in CAMERA_MODELS:
        raise ValueError(
            f"SfmConfig.camera_model must be one of {', '.join(CAMERA_MODELS)}; got {cfg.camera_model!r}"
        )
    for name in ("num_threads", "image_threads"):
        n = getattr(cfg, name)
        if n == 0 or n < -1:
            raise ValueError(f"SfmConfig.{name} must be >= 1 or -1 (all cores); got {n}")
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
    phases: dict[str, float] = field(default_factory=dict)  # seconds per phase, summed over attempts
    guided: bool = False  # guided matching (the retry ladder's feature rung)
    stats: tuple[int, int] = (0, 0)  # (verified pairs, loop pairs) of the last attempt's database

    def _timed(self, phase: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        t = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.phases[phase] = self.phases.get(phase, 0.0) + time.perf_counter() - t

    def run(self, db_path: Path, feature_dir: Path, distorted: Path, images_dir: Path) -> tuple[list, list[str]]:
        """(the models, largest first; the names that were read); raises NoModelError / TooFewRegisteredError."""
        import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

        if db_path.exists():
            db_path.unlink()
        names = list(self.names)
        # Register the images first, one thread, in name order: image ids then follow the names. Letting the
        # multi-threaded extractor create them numbers them in completion order, which changes match and
        # mapping order and makes runs differ (docs/DECISIONS.md, "Numbers behind code comments").
        pycolmap.Database.open(str(db_path)).close()  # import_images needs an existing database
        pycolmap.import_images(db_path, feature_dir, camera_mode=self.camera_mode, image_names=names,
                               options=self.reader)
        self._timed(
            "extract", pycolmap.extract_features, db_path, feature_dir, image_names=names,
            camera_mode=self.camera_mode, reader_options=self.reader, extraction_options=self.ext,
            device=pycolmap.Device.cpu, cancellation_token=self.token,
        )  # fmt: skip
        in_db = _db_image_names(db_path)
        for n in names:
            if n not in in_db and (n, "pycolmap could not read it") not in self.skipped:
                self.skipped.append((n, "pycolmap could not read it"))
        names = [n for n in names if n in in_db]
        if len(names) < MIN_IMAGES:
            raise TooFewImagesError(_too_few_msg(len(names), images_dir), skipped=self.skipped)
        if self.matcher == "sequential" and self.cfg.loop_detection:
            self._timed("vocab", build_vocab_tree, db_path, distorted / "vocab_tree.bin", self.cfg.seed)
        self._timed("match", _match, db_path, self.matcher, self.cfg, self.token, distorted / "vocab_tree.bin",
                    guided=self.guided)
        self.stats = _pair_stats(db_path, self.cfg.sequential_overlap)
        if _num_inlier_matches(db_path) == 0:
            raise NoModelError(
                f"no two of the {len(names)} images in {images_dir} share enough features to be matched. "
                f"Photos must overlap (about 60 % between neighbours) and show texture; open water, sand or "
                f"very turbid water gives too few features.",
                skipped=self.skipped,
            )
        recs = self._timed("map", map_models, db_path, self.src_dir, distorted, self.cfg, self.token)
        if not recs:
            raise NoModelError(
                f"pycolmap could not start a 3D model from the {len(names)} images in {images_dir}: no "
                f"pair of images with enough parallax. The camera must move between shots (identical or "
                f"rotation-only photos cannot be triangulated).",
                skipped=self.skipped,
            )
        if recs[0].num_reg_images() < self.cfg.min_registered:
            raise TooFewRegisteredError(
                f"only {recs[0].num_reg_images()} of {len(names)} images in {images_dir} could be placed in the 3D "
                f"model (at least {self.cfg.min_registered} needed). Check the overlap between consecutive photos.",
                skipped=self.skipped,
            )
        return recs, names


# The retry ladder's feature rung: SIFT on images up to this many times cfg.max_image_size (never above the
# frames' own size), with this many times the features and half the peak threshold (more, weaker features).
RETRY_SIZE_FACTOR = 2
RETRY_FEATURE_FACTOR = 2


def _retry_dropped(
    recs: list, names: list[str], db: Path, feature_dir: Path, distorted: Path, attempt: _Attempt, largest: int,
    record: list[dict[str, Any]],
) -> tuple[list, Path]:
    """The retry ladder, run only while readable frames are left out of the kept model; cheapest rung first:

    1. ``extend``: continue the kept model with the relaxed mapper thresholds (``pipeline.sfm.mapping``): frames
       the first pass gave up on, and side models' frames that match it, are registered into it (mapping only);
    2. ``relaxed``: map again from nothing with the relaxed thresholds (another initial pair, laxer registration);
    3. ``features``: extract again with more features (:data:`RETRY_FEATURE_FACTOR`, half the peak threshold) on
       larger images for frames bigger than ``cfg.max_image_size`` (:data:`RETRY_SIZE_FACTOR`), match with guided
       matching, map, and extend the kept model with the relaxed thresholds.

    A rung's models replace the current ones only when their largest places more frames. ``recs`` may be empty
    (the first pass built no model): the ladder then runs ``relaxed`` alone. Each rung that ran is appended to
    ``record``. Returns (the models, the database they came from)."""
    cfg, token = attempt.cfg, attempt.token

    def placed(models: list) -> int:
        return models[0].num_reg_images() if models else 0

    def rung(name: str, fn: Any) -> None:
        nonlocal recs, db
        before, t = placed(recs), time.perf_counter()
        try:
            new, new_db = fn()
        except (NoModelError, TooFewRegisteredError):
            new, new_db = [], db
        kept = placed(new) > before
        record.append({"rung": name, "registered_before": before,
                       "registered": new[0].num_reg_images() if new else 0, "models": len(new),
                       "reproj_px": round(float(new[0].compute_mean_reprojection_error()), 4) if new else None,
                       "seconds": round(time.perf_counter() - t, 3), "kept": kept})  # fmt: skip
        log.info("sfm retry %s: %s", name, record[-1])
        if kept:
            recs, db = new, new_db

    def extend(models: list, database: Path) -> tuple[list, Path]:
        seed = distorted / "_seed"
        shutil.rmtree(seed, ignore_errors=True)
        seed.mkdir()
        try:
            models[0].write(str(seed))
            return attempt._timed("map", map_models, database, attempt.src_dir, distorted, cfg, token,
                                  relaxed=True, start_from=seed), database  # fmt: skip
        finally:
            shutil.rmtree(seed, ignore_errors=True)

    def remap(database: Path) -> tuple[list, Path]:
        return attempt._timed("map", map_models, database, attempt.src_dir, distorted, cfg, token,
                              relaxed=True), database  # fmt: skip

    def more_features() -> tuple[list, Path]:
        ext = copy.deepcopy(attempt.ext)  # pycolmap's options are mutable C++ objects
        ext.max_image_size = max(cfg.max_image_size, min(largest, RETRY_SIZE_FACTOR * cfg.max_image_size))
        ext.sift.max_num_features = RETRY_FEATURE_FACTOR * cfg.max_num_features
        ext.sift.peak_threshold = attempt.ext.sift.peak_threshold / 2
        again = replace(attempt, ext=ext, guided=True, skipped=[])
        new_db = distorted / "database_features.db"
        models, _ = again.run(new_db, feature_dir, distorted, attempt.src_dir)
        if models[0].num_reg_images() < len(names):
            extended, _ = extend(models, new_db)
            if extended and extended[0].num_reg_images() > models[0].num_reg_images():
                models = extended
        if placed(models) > placed(recs):
            attempt.stats = again.stats  # the summary's pair counts describe the database the model came from
        return models, new_db

    ladder = (("extend", lambda: extend(recs, db)), ("relaxed", lambda: remap(db)), ("features", more_features))
    for name, fn in ladder:
        if placed(recs) >= len(names):
            break
        # Nothing to extend without a model. Re-extracting features costs minutes on large frames (every third
        # AIMS Erub frame: 12.5 min, still no model), so it runs only for a survey that did build a model:
        # input that no relaxed mapping could start from is not made hopeful by more features.
        if (name == "extend" or name == "features") and not recs:
            continue
        rung(name, fn)
    return recs, db


def _stage_stretched(src_dir: Path, names: list[str], stage: Path) -> Path:
    """Contrast-stretched 8-bit copies of ``names`` (same names) for feature extraction: each channel linearly
    from its ``STRETCH_PERCENTILES`` to [0, 1]."""
    stage.mkdir(parents=True, exist_ok=True)
    for n in names:
        img = read_image(src_dir / n)  # [H, W, 3] in [0, 1]
        lo, hi = np.percentile(img.reshape(-1, img.shape[-1]), STRETCH_PERCENTILES, axis=0)
        out = np.clip((img - lo) / np.maximum(hi - lo, 1.0 / 255.0), 0.0, 1.0)
        write_image(stage / n, out, bits=8)
    return stage


def _db_image_names(db_path: Path) -> set[str]:
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    db = pycolmap.Database.open(str(db_path))
    try:
        return {im.name for im in db.read_all_images()}
    finally:
        db.close()


def _num_inlier_matches(db_path: Path) -> int:
    """Inlier correspondences over all pairs (``num_verified_image_pairs`` counts 0-inlier pairs too)."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    db = pycolmap.Database.open(str(db_path))
    try:
        return int(db.num_inlier_matches())
    finally:
        db.close()


def _pair_stats(db_path: Path, overlap: int) -> tuple[int, int]:
    """(image pairs with inliers, those of them the sequential window does not propose: loop pairs).

    Image ids follow the sorted names, so the sequential matcher pairs ids ``d`` apart for ``d <= overlap`` and
    (quadratic overlap) ``d = 2**k``; any other verified pair came from loop detection (or from exhaustive
    matching across the survey)."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    db = pycolmap.Database.open(str(db_path))
    try:
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    pairs = loops = 0
    for pid, n in zip(pair_ids, inliers, strict=True):
        if n <= 0:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pid)
        d = abs(int(a) - int(b))
        pairs += 1
        loops += d > overlap and d & (d - 1) != 0
    return pairs, loops


def separate_models(models: list[SubModel], kept: set[str]) -> list[SubModel]:
    """The side models as far as they hold images the kept model does not: each lists only those, and one whose
    images the kept model placed too is no separate part of the survey (dropped from the list; still on disk).

    pycolmap's mapper may start a further model from images the first one places later: on the 27 RUIE B frames
    the kept model held all 27 while two side models held 8 and 5 of them, and the job said 13 photos were left
    out (docs/DECISIONS.md, "SfM at survey size")."""
    out = []
    for m in models:
        outside = [n for n in m.images if n not in kept]
        if outside:
            out.append(SubModel(index=m.index, registered=len(outside), images=outside))
    return out


def _write_models(recs: list, sparse: Path) -> list[SubModel]:
    """Write the models (largest first) to ``sparse/0, 1, ...``; the :class:`SubModel` records of all but the
    first, which is the one used."""
    others = []
    for i, r in enumerate(recs):
        d = sparse / str(i)
        d.mkdir(parents=True)
        r.write(str(d))
        if i:
            names = sorted(im.name for im in r.images.values() if im.has_pose)
            others.append(SubModel(index=i, registered=r.num_reg_images(), images=names))
    return others


def _name_range(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"{names[0]} .. {names[-1]}"


def _match(db_path: Path, matcher: str, cfg: SfmConfig, token: Any, vocab_tree: Path, *, guided: bool = False) -> None:
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = cfg.num_threads
    mopts.guided_matching = guided
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = cfg.seed
    if matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.sequential_overlap
        pairing.num_threads = cfg.num_threads
        pairing.loop_detection = cfg.loop_detection
        if cfg.loop_detection:  # the tree run() built from this survey's descriptors (pipeline.sfm.loops)
            pairing.vocab_tree_path = str(vocab_tree)
            pairing.loop_detection_period = LOOP_PERIOD
            pairing.loop_detection_num_images = LOOP_NUM_IMAGES
        pycolmap.match_sequential(db_path, matching_options=mopts, pairing_options=pairing,
                                  verification_options=verify, device=pycolmap.Device.cpu,
                                  cancellation_token=token)  # fmt: skip
    else:
        pycolmap.match_exhaustive(db_path, matching_options=mopts, verification_options=verify,
                                  device=pycolmap.Device.cpu, cancellation_token=token)  # fmt: skip


def undistort_model(model_dir: Path, image_dir: Path, out: Path, tmp: Path, cfg: SfmConfig, token: Any = None) -> None:
    """PINHOLE undistortion of ``image_dir``'s images through the model ``model_dir`` into ``out/images`` and
    ``out/sparse/0`` (MVS leftovers dropped; ``tmp`` is the scratch folder)."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    pycolmap.undistort_images(str(tmp), str(model_dir), str(image_dir), num_threads=cfg.image_threads,
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
    "SubModel",
    "TooFewImagesError",
    "TooFewRegisteredError",
    "choose_matcher",
    "is_numbered_sequence",
    "run_sfm",
    "undistort_model",
]
