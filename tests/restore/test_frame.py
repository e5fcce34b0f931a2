"""A whole frame: the synthetic round trip, bands against one whole-frame band, files with their metadata."""

import dataclasses

import numpy as np
import OpenImageIO as oiio
import pytest

from pipeline.restore.frame import FrameRestorer, RestoreOptions, restore_array, restore_file
from pipeline.restore.synthetic import SynthFrame
from pipeline.scene.records import Camera


def _psnr(a, b, m):
    return -10 * np.log10(((a - b) ** 2)[m].mean())


@pytest.fixture(scope="module")
def frame():
    fr = SynthFrame(640, 480, factor=8, k1=-0.1)
    I, J, surf = fr.photo_rows(0, 480)
    return fr, I, J, surf, fr.render()


def test_round_trip_recovers_clean_image(frame):
    fr, I, J, surf, rv = frame
    photo = (I * 255 + 0.5).astype(np.uint8)
    res = restore_array(photo, fr.lens, rv)
    m = res.surface & surf
    assert m.mean() > 0.85
    got = _psnr(res.J / 255, J, m)
    assert got > 42.5, got  # measured 43.8 dB (bilinear depth: 42.7); the photo itself: 18.8 dB
    assert _psnr(I, J, m) < 20
    assert (res.surface & ~surf).mean() < 0.003  # surface beyond the truth: only along the open-water edge
    off = ~res.surface
    assert (res.confidence[off] == 0).all()
    kept = off & (res.extended == 0)
    assert (res.J[kept] == photo[kept]).all()
    # off the render's surface but carried on: the lens corners outside the render camera (seabed), never the
    # open water (its photo is the water's own colour); measured 32 % of the off-surface pixels
    ext = res.extended > 0
    assert 0.2 < ext[off].mean() < 0.5 and not (ext & ~surf).any()
    assert _psnr(res.J / 255, J, ext & surf) > _psnr(I, J, ext & surf) + 4


def test_unseen_seabed_is_carried_on_not_left_green(frame):
    """A hole in the reconstruction (seabed no training view saw): the photo alone is de-watered there at the
    depth carried on from around it, confidence 0, marked in ``extended``; ``unseen="keep"`` leaves it."""
    fr, I, J, surf, rv = frame
    photo = (I * 255 + 0.5).astype(np.uint8)
    alpha = rv.alpha.copy()
    alpha[30:50, 50:75] = 0  # a 20x25 render-pixel hole (160x200 photo pixels) in the seabed
    holed = dataclasses.replace(rv, alpha=alpha)
    res = restore_array(photo, fr.lens, holed)
    hole = ~res.surface & surf & restore_array(photo, fr.lens, rv).surface  # only the pixels the hole took
    assert hole.sum() > 30_000
    assert res.extended[hole].mean() > 0.95 and (res.confidence[hole] == 0).all()
    got, was = _psnr(res.J / 255, J, hole), _psnr(I, J, hole)
    assert got > was + 5, (got, was)  # measured 24.0 against 18.0 dB (the depth is carried on flat, no prior)
    keep = restore_array(photo, fr.lens, holed, RestoreOptions(unseen="keep"))
    assert (keep.J[hole] == photo[hole]).all() and (keep.extended == 0).all()


def test_bands_equal_one_band(frame):
    fr, I, J, surf, rv = frame
    photo = (I * 255 + 0.5).astype(np.uint8)
    a = restore_array(photo, fr.lens, rv, RestoreOptions(band_rows=64))
    b = restore_array(photo, fr.lens, rv, RestoreOptions(band_rows=480))
    assert (a.surface == b.surface).all()
    assert np.abs(a.J.astype(int) - b.J).max() <= 1 and (a.J != b.J).mean() < 1e-3  # float rounding only
    # with the model's J as the prior the confidence reads a window of rows around each pixel (the misfit); the
    # same calibration for both (it measures on bands, which differ)
    rp = fr.render(prior=True)
    out = []
    for rows in (64, 480):
        f = FrameRestorer(fr.lens, rp, RestoreOptions(band_rows=rows))
        if not out:
            f.calibrate(lambda e0, e1: photo[e0:e1])
            cal = (f.lam2, f.noise2, f.detail2, f.detail_cov)
        f.lam2, f.noise2, f.detail2, f.detail_cov = cal
        J, conf = np.empty_like(photo), np.empty(photo.shape[:2], np.float32)
        for e0, y0, y1, e1 in f.bands():
            J[y0:y1], conf[y0:y1], *_ = f.band(photo[e0:e1], e0, y0, y1)
        out.append((J, conf))
    (Ja, ca), (Jb, cb) = out
    assert np.abs(Ja.astype(int) - Jb).max() <= 1 and np.abs(ca - cb).max() < 1e-4


def test_confidence_is_low_where_the_model_is_wrong(frame):
    """A patch of the model's J off by a third (what a held-out photo shows where the model is wrong): the
    restored pixels there lean on it and are wrong, and the confidence says so (the photo's local disagreement
    with the model, ``local_misfit``); the rest of the frame keeps its confidence."""
    fr, I, J, surf, rv = frame
    photo = (I * 255 + 0.5).astype(np.uint8)
    rp = fr.render(prior=True)
    rp = dataclasses.replace(rp, medium=dataclasses.replace(rp.medium, sigma=np.full((3, 3), 0.02)))  # well measured
    wrong = rp.J.copy()
    wrong[30:50, 50:75] *= 0.67  # render pixels; x8 in the photo: rows ~240-400, columns ~400-600
    bad = dataclasses.replace(rp, J=wrong)
    good, res = restore_array(photo, fr.lens, rp), restore_array(photo, fr.lens, bad)
    patch = np.zeros_like(surf)
    patch[260:380, 420:580] = True
    m = res.surface & surf
    err = np.abs(res.J / 255 - J).mean(-1)
    assert err[patch & m].mean() > 2 * err[~patch & m].mean()  # the restoration is wrong there
    c_in, c_out = res.confidence[patch & m].mean(), res.confidence[~patch & m].mean()
    # measured 0.34 against 0.83 (without the misfit term 0.92, above the rest)
    assert c_in < 0.5 * c_out, (c_in, c_out)
    # elsewhere it moves only by the photo's calibration (σ_d, λ² per photo, which the wrong patch raises):
    # measured 0.888 -> 0.826
    assert c_out > 0.9 * good.confidence[~patch & m].mean()
    assert np.corrcoef(res.confidence[m], err[m])[0, 1] < -0.3


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_file_keeps_format_and_exif(frame, tmp_path, ext):
    fr, I, J, surf, rv = frame
    src = tmp_path / f"in{ext}"
    spec = oiio.ImageSpec(fr.width, fr.height, 3, oiio.UINT8)
    spec.attribute("Make", "DiveCam")
    spec.attribute("Exif:DateTimeOriginal", "2024:05:06 07:08:09")
    out = oiio.ImageOutput.create(str(src))
    assert out.open(str(src), spec)
    out.write_image((I * 255 + 0.5).astype(np.uint8))
    out.close()
    res = restore_file(src, fr.lens, rv, tmp_path / "out")
    inp = oiio.ImageInput.open(str(res.paths["J"]))
    s = inp.spec()
    assert res.paths["J"].suffix == ext and inp.format_name() == ("jpeg" if ext == ".jpg" else "png")
    assert s.get_string_attribute("Make") == "DiveCam"
    assert s.get_string_attribute("Exif:DateTimeOriginal") == "2024:05:06 07:08:09"
    img = inp.read_image(oiio.UINT8)
    inp.close()
    mem = restore_array(oiio.ImageBuf(str(src)).get_pixels(oiio.UINT8), fr.lens, rv)  # the decoded source
    if ext == ".png":
        assert (img == mem.J).all()
    else:  # JPEG q95 4:4:4 of a per-pixel-noise texture (mean abs error 2.8 levels)
        assert _psnr(img / 255, mem.J / 255, np.ones(img.shape[:2], bool)) > 36
    conf = oiio.ImageBuf(str(res.paths["confidence"])).get_pixels(oiio.UINT8)[..., 0]
    assert np.abs(conf.astype(int) - np.round(mem.confidence * 255)).max() <= 1
    tif = restore_file(src, fr.lens, rv, tmp_path / "tif", tiff16=True)
    buf = oiio.ImageBuf(str(tif.paths["J"]))
    assert buf.spec().format == oiio.UINT16 and buf.spec().get_string_attribute("Make") == "DiveCam"


def test_a_photos_exposure_is_removed_and_the_survey_mean_given(frame):
    """A photo taken at other gains (log_gain: removed before de-watering) restores as the fixed camera's does;
    with the survey's mean exposure (output_log_gain) the restored photo is that exposure of the same J."""
    from pipeline.scene.exposure import exposed

    fr, I, J, surf, rv = frame
    lg, survey = np.log([1.2, 0.9, 1.1]), np.log([1.3, 1.0, 0.75])
    photo = (np.clip(exposed(I, lg, "srgb"), 0, 1) * 255 + 0.5).astype(np.uint8)
    res = restore_array(photo, fr.lens, dataclasses.replace(rv, log_gain=lg))
    m = res.surface & surf
    assert _psnr(res.J / 255, J, m) > 40  # measured 43.8 dB at neutral exposure
    out = restore_array(photo, fr.lens, dataclasses.replace(rv, log_gain=lg, output_log_gain=survey))
    assert _psnr(out.J / 255, np.clip(exposed(J, survey, "srgb"), 0, 1), m) > 40
    assert _psnr(out.J / 255, J, m) < 35  # not the neutral one


def test_the_surveys_fall_off_is_divided_out_with_the_exposure(frame):
    """A photo darkened towards its edges by the survey's fall-off (a grey log field over the training image's
    coordinates, as the sparse points' fit measures it, at a mean of 1 over the frame) restores as the even-lit
    photo does when the field is given (``fall_off``), and not without it. The field is placed through the lens:
    a pixel's undistorted ray in the training camera, here x = 2·f·xn / w, y = 2·f·yn / h (pad 0, centred
    principal point); a padded render camera places it at the same pixels."""
    from pipeline.medium.fall_off import log_fall_off_at
    from pipeline.restore.lens import exact_rays
    from pipeline.scene.exposure import exposed

    fr, I, J, surf, rv = frame
    cam = rv.camera
    theta = np.array([0.1, -0.15, -0.35, -0.25, 0.05])  # spans ~2x over the frame
    xn, yn = exact_rays(fr.lens, 0, fr.height)
    xy = np.stack([2 * cam.fx * xn / cam.width, 2 * cam.fy * yn / cam.height], -1)
    lf = log_fall_off_at(xy.reshape(-1, 2), theta).reshape(*xn.shape, 1)
    lg = np.log([1.2, 0.9, 1.1])
    photo = (np.clip(exposed(I, lg + lf, "srgb"), 0, 1) * 255 + 0.5).astype(np.uint8)
    res = restore_array(photo, fr.lens, dataclasses.replace(rv, log_gain=lg, fall_off=theta))
    left = restore_array(photo, fr.lens, dataclasses.replace(rv, log_gain=lg))
    m = res.surface & surf
    got, was = _psnr(res.J / 255, J, m), _psnr(left.J / 255, J, m)
    assert got > 40 and was < got - 10, (got, was)  # measured 43.8 and 25.1 dB
    p = 3
    padded = Camera(cam.width + 2 * p, cam.height + 2 * p, cam.fx, cam.fy, cam.cx + p, cam.cy + p)
    pv = dataclasses.replace(rv, camera=padded, pad=p, depth=np.pad(rv.depth, p), alpha=np.pad(rv.alpha, p),
                             fall_off=theta)
    a = FrameRestorer(fr.lens, dataclasses.replace(rv, fall_off=theta)).log_fall_off(0, fr.height)
    b = FrameRestorer(fr.lens, pv).log_fall_off(0, fr.height)
    assert np.abs(a - lf).max() < 1e-3 and np.abs(b - lf).max() < 1e-3
