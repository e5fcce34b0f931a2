"""The restore kernels' warm-up (``pipeline.restore.warmup``) leaves nothing for a job to compile.

In a fresh interpreter (a kernel's compiled signatures are per process, and other tests in this one have called
the kernels already): run the warm-up, note every numba dispatcher's signatures in ``pipeline.restore._kernels``,
then restore a small photo in every combination a job can produce — 8-bit JPEG/PNG/TIFF, 16-bit PNG/TIFF and
float TIFF photos, each restore format, both colour spaces, with and without the model's prior, a distorted and
a PINHOLE lens, a homogeneous and a per-pixel medium, several row bands — and check that no signature was added.
A second run leaves one warm-up case out and checks that the restores then do add one (the check can fail).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CHECK = """
import itertools, json, sys, tempfile
from pathlib import Path
import numpy as np
from numba.core.dispatcher import Dispatcher
from pipeline.restore import _kernels, warmup
from pipeline.restore.frame import RestoreOptions, restore_file
from pipeline.restore.records import MediumMaps, RenderedView
from pipeline.restore.synthetic import SynthFrame
from pipeline.scene.images import write_image
from pipeline.scene.records import LensCamera

def signatures():
    return {n: sorted(map(str, d.signatures)) for n, d in vars(_kernels).items() if isinstance(d, Dispatcher)}

warmup.CASES = tuple(c for c in warmup.CASES if c.name not in sys.argv[1:])
warmup.compile_restore_kernels()
before = signatures()

fr = SynthFrame(64, 48, factor=8)
I, _, _ = fr.photo_rows(0, 48)
f = 1.1 * 64
lenses = {"distorted": fr.lens, "pinhole": LensCamera("PINHOLE", 64, 48, (f, f, 32.0, 24.0))}
base = fr.render(prior=True)
h, w = base.depth.shape
maps = MediumMaps(*(np.ascontiguousarray(np.broadcast_to(k, (h, w, 3)), np.float32)
                    for k in (base.medium.k_A, base.medium.k_B)), base.medium.B_inf)
views = {(prior, medium): RenderedView(base.camera, base.depth, base.alpha, maps if medium == "maps" else base.medium,
                                       base.J if prior else None)
         for prior in (True, False) for medium in ("homogeneous", "maps")}
photos = {"8-bit jpg": (255, np.uint8, ".jpg"), "16-bit png": (65535, np.uint16, ".png"),
          "8-bit png": (255, np.uint8, ".png"), "8-bit tif": (255, np.uint8, ".tif"),
          "16-bit tif": (65535, np.uint16, ".tif"), "float tif": (1, np.float32, ".tif")}
runs = [*itertools.product(["8-bit jpg", "16-bit png"], ["auto", "tiff16"], ["srgb", "linear"], [True, False],
                           ["distorted", "pinhole"], ["homogeneous", "maps"]),
        *itertools.product(["8-bit png", "8-bit tif", "16-bit tif", "float tif"], ["auto", "tiff16"], ["srgb"],
                           [True], ["distorted"], ["homogeneous"])]
with tempfile.TemporaryDirectory() as tmp:
    src = {k: write_image(Path(tmp) / f"{k.replace(' ', '_')}{ext}",
                          I.astype(dt) if dt == np.float32 else (I * top + 0.5).astype(dt))
           for k, (top, dt, ext) in photos.items()}
    for k, (photo, fmt, space, prior, lens, medium) in enumerate(runs):
        # the stage's call (pipeline.restore.views.restore_photo) with 16-row bands: several bands per photo
        restore_file(src[photo], lenses[lens], views[prior, medium], Path(tmp) / f"out{k}",
                     RestoreOptions(max_gain=8.0, space=space, band_rows=16), tiff16=fmt == "tiff16",
                     confidence_dir=Path(tmp) / f"conf{k}")
after = signatures()
print(json.dumps({"before": before, "added": {n: sorted(set(after[n]) - set(before[n])) for n in after
                                              if set(after[n]) - set(before[n])}, "runs": len(runs)}))
"""


def _check(*drop: str) -> dict:
    # one numba thread: a parallel region on these tiny arrays costs ~12 ms of thread wake-ups on a loaded machine,
    # 40x the work (the threads are not part of a signature)
    env = dict(os.environ, NUMBA_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    out = subprocess.run([sys.executable, "-c", CHECK, *drop], env=env, cwd=REPO, capture_output=True, text=True,
                         timeout=800)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_warmup_leaves_nothing_for_a_restore_to_compile():
    res = _check()
    assert res["added"] == {}, res["added"]
    assert res["runs"] == 72
    before = res["before"]
    # not vacuous: every kernel a job calls was compiled (or loaded), dewater for each (photo, J) dtype pair
    used = set(before) - {"guided_apply", "_srgb_to_linear", "_linear_to_srgb", "_gain_matrix", "_optical_depths"}
    kernels = {"interp_grid_rows", "sample_bilinear", "box_mean", "guided_stats", "guided_coeffs", "luminance",
               "dewater", "misfit_terms", "misfit_upsample", "block_mean", "upsample_apply", "calibration_sums",
               "surface_range"}
    assert used == kernels, sorted(before)
    assert all(before[n] for n in used), before
    assert len(before["dewater"]) == 4 and len(before["luminance"]) == 2, before
    assert len(before["calibration_sums"]) == 2, before  # the photo's rows as read: uint8 or uint16


def test_check_notices_a_missing_case():
    res = _check("16-bit png -> tiff16")
    assert set(res["added"]) == {"dewater"}, res["added"]
    (sig,) = res["added"]["dewater"]
    assert sig.startswith("(Array(uint16, 3, 'C'") and "Array(uint16, 3, 'C', False, aligned=True), int64" in sig, sig
