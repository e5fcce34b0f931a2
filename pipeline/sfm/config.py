"""The pycolmap SfM recipe's settings (the sfm package alone reads them; pipeline/config.py holds the shared ones)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Matcher = Literal["auto", "exhaustive", "sequential"]


@dataclass
class SfmConfig:
    """The pycolmap SfM recipe (``pipeline.sfm.recipe``)."""

    matcher: Matcher = "auto"  # auto: see pipeline.sfm.recipe.choose_matcher for the rule
    sequential_overlap: int = 10  # neighbours matched per frame in sequential mode (plus quadratic jumps)
    # Sequential mode also matches loop candidates from a vocabulary tree built from the survey's own features
    # (pipeline.sfm.loops), so lines that revisit the seabed are tied together.
    loop_detection: bool = True
    exhaustive_max_images: int = 60  # auto uses exhaustive up to this many images
    max_image_size: int = 1600  # SIFT works on images downscaled to this longest side
    max_num_features: int = 8192
    camera_model: str = "SIMPLE_RADIAL"  # model refined by bundle adjustment before undistortion
    single_camera: bool = True  # one shared camera for the whole set (one ROV camera)
    num_threads: int = 1  # matching and mapping on one thread: SfM repeats bit for bit (2 threads moved the model)
    # Feature extraction and undistortion treat each image alone (ids are assigned before, in name order), so
    # their threads cannot change the result (the model's files compared byte for byte): -1 = all cores.
    image_threads: int = -1
    seed: int = 0
    min_registered: int = 3  # fewer registered images than this is an error
    # Frames left out of the kept model: try the retry ladder (relaxed mapper thresholds on the kept model, a relaxed
    # remap, more features with guided matching; pipeline.sfm.recipe._retry_dropped) before reporting them dropped.
    retry_dropped: bool = True


__all__ = ["Matcher", "SfmConfig"]
