"""Compile the restorer's numba kernels (``pipeline.restore._kernels``) into their on-disk cache ahead of the first job.

On an empty cache they compile inside the first job's restore stage: 33-77 s on our 2 shared cores against ~6 s
warm (docs/DECISIONS.md, "Whole-job speed"). This restores a tiny generated frame (:mod:`pipeline.restore.synthetic`)
written to files, through the restore stage's own entry point (:func:`pipeline.restore.views.restore_photo`), once
per argument-type combination a job can produce. Those follow from how the stage reaches the kernels:

- the photo's rows come from :class:`~pipeline.restore.files.BandReader` as uint8 or uint16 (16-bit and float
  files are read as uint16): ``luminance`` and ``dewater`` take that dtype;
- ``dewater`` writes J as uint8 or uint16 by the *output* file (8-bit JPEG/PNG keeps the input's format, anything
  else and ``restore_format=tiff16`` is a 16-bit TIFF), independent of the input's depth: four combinations;
- every other argument is converted before the call (float32/float64 C-contiguous arrays, Python floats and
  ints), and the colour space and the model's prior are Python bools (numba types them as ``boolean``, not as
  literals), the prior an array whether it is used or not, a medium's coefficients [1, 1, 3] or [n, W, 3]
  float32: neither the space, the prior, the lens's distortion nor the medium mode changes a kernel's types.

``guided_apply`` (the plain guided filter's last step) is not on a job's path and is not compiled here.
tests/restore/test_warmup.py checks that after this a restore of every such combination compiles nothing.
Idempotent: with the cache filled it only loads it.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.restore.synthetic import SynthFrame
from pipeline.restore.views import restore_photo
from pipeline.scene.images import write_image

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Case:
    """One argument-type combination: the photo's bit depth and file type, and the restore format."""

    bits: int  # 8 or 16: the photo's stored depth, the dtype BandReader hands the kernels
    suffix: str  # the photo's file type (.jpg is 8-bit only)
    fmt: str  # the job's restore_format: "auto" keeps JPEG/PNG (8-bit J), "tiff16" writes uint16 J

    @property
    def name(self) -> str:
        return f"{self.bits}-bit {self.suffix[1:]} -> {self.fmt}"


CASES = (Case(8, ".jpg", "auto"), Case(8, ".jpg", "tiff16"), Case(16, ".png", "auto"), Case(16, ".png", "tiff16"))


def compile_restore_kernels(width: int = 64, height: int = 48) -> dict[str, float]:
    """Restore a ``width`` x ``height`` generated photo once per :data:`CASES`; returns seconds per case (the
    first includes the kernels every case shares)."""
    fr = SynthFrame(width, height, factor=8)
    I, _, _ = fr.photo_rows(0, height)
    view = fr.render(prior=True)  # a job always has the model's J as the prior
    seconds = {}
    with tempfile.TemporaryDirectory(prefix="dualphys-restore-warmup-") as tmp:
        for k, case in enumerate(CASES):
            top = 255 if case.bits == 8 else 65535
            src = write_image(Path(tmp) / f"photo{k}{case.suffix}",
                              (I * top + 0.5).astype(np.uint8 if case.bits == 8 else np.uint16))
            t0 = time.perf_counter()
            restore_photo(src, Path(tmp) / "restored", Path(tmp) / "confidence_maps", fr.lens, view, max_gain=8.0,
                          fmt=case.fmt, space="srgb")
            seconds[case.name] = round(time.perf_counter() - t0, 2)
    log.info("restore kernels compiled or loaded: %s", seconds)
    return seconds
