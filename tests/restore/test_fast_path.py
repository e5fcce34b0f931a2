"""The whole frame's fast path against the same frame restored with the slow twins swapped in for the hot ops
(one sampling pass over every map, the range and surface pass, the calibration's fused sums, the misfit and the
dewater kernels): the
restored photo and the confidence map agree within 1/255 (issue 43, item 3: faster, not different)."""

import numpy as np
import pytest

import pipeline.restore.frame as frame
from pipeline.restore.dewater import dewater_reference, local_misfit_reference
from pipeline.restore.records import MediumMaps
from pipeline.restore.sample import sample_maps_reference
from pipeline.restore.synthetic import SynthFrame


def _medium(k_A, k_B, B_inf, sigma=None):
    return MediumMaps(np.asarray(k_A, np.float64), np.asarray(k_B, np.float64), np.asarray(B_inf, np.float64),
                      sigma)


def _float(img, scale):
    return np.asarray(img, np.float64) * (1.0 if scale is None else scale)


def _calibration_twin(img, scale, r, surface, k_A, k_B, B_inf, linear, prior, st):
    k_A, k_B = (k.reshape(3) if k.shape[:2] == (1, 1) else k for k in (k_A, k_B))
    return frame.calibration_sums_reference(np.asarray(img, np.float64) * scale, r, surface, k_A, k_B, B_inf,
                                            prior, st, "linear" if linear else "srgb")


def _misfit_twin(img, r, surface, k_A, k_B, B_inf, prior, radius, *, space, scale, step, row0, out_rows):
    return local_misfit_reference(_float(img, scale), r, surface, _medium(k_A, k_B, B_inf), prior, radius,
                                  space=space, step=step, row0=row0, out_rows=out_rows)


def _dewater_twin(img, r, surface, k_A, k_B, B_inf, *, max_gain, space, out_max, scale, prior=None, lam2=None,
                  sigma=None, noise2=None, detail2=None, detail_cov=None, misfit=None):
    J, conf, clipped = dewater_reference(_float(img, scale), r, surface, _medium(k_A, k_B, B_inf, sigma),
                                         max_gain=max_gain, space=space, prior=prior, lam2=lam2, noise2=noise2,
                                         detail2=detail2, detail_cov=detail_cov, misfit=misfit)
    return np.rint(J * out_max).astype(np.uint8 if out_max == 255 else np.uint16), conf.astype(np.float32), clipped


@pytest.fixture(scope="module")
def scene():
    fr = SynthFrame(320, 240, factor=8, k1=-0.1)  # render 40x30: the misfit's window on every 3rd pixel
    I, _, _ = fr.photo_rows(0, 240)
    return fr, (I * 255 + 0.5).astype(np.uint8), fr.render(prior=True)


def test_fast_path_equals_the_twins_within_one_level(scene, monkeypatch):
    fr, photo, view = scene
    opt = frame.RestoreOptions(band_rows=64)  # several bands, each with its halo
    fast = frame.restore_array(photo, fr.lens, view, opt)
    with monkeypatch.context() as m:
        m.setattr(frame, "sample_maps", sample_maps_reference)
        m.setattr(frame, "calibration_sums", _calibration_twin)
        m.setattr(frame, "surface_range", frame.surface_range_reference)
        m.setattr(frame, "local_misfit", _misfit_twin)
        m.setattr(frame, "dewater", _dewater_twin)
        slow = frame.restore_array(photo, fr.lens, view, opt)
    assert 0.5 < fast.surface.mean() < 0.99 and (fast.surface == slow.surface).all()
    assert fast.extended_pixels > 100  # the photo-only restoration off the surface ran too
    np.testing.assert_allclose(fast.lam2, slow.lam2, rtol=1e-6)
    dJ = np.abs(fast.J.astype(int) - slow.J.astype(int))
    assert dJ.max() <= 1 and (dJ > 0).mean() < 0.01
    assert np.abs(fast.confidence - slow.confidence).max() < 1 / 255
    changed = np.abs(fast.J.astype(int) - photo.astype(int)).max(-1) > 10
    assert changed[fast.surface].mean() > 0.5  # the comparison is of restored pixels, not of copies of the photo
