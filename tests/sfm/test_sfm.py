"""The SfM stage: matcher rule, hard inputs as typed errors, skipped files, real and synthetic scenes."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.scene.align import align_to_reference
from pipeline.scene.colmap import read_colmap
from pipeline.scene.images import read_image, write_image
from pipeline.scene.loader import load_images, load_scene
from pipeline.sfm.config import SfmConfig
from pipeline.sfm.recipe import (
    NoImagesError,
    NoModelError,
    SfmError,
    TooFewImagesError,
    TooFewRegisteredError,
    choose_matcher,
    is_numbered_sequence,
    run_sfm,
)

REPO = Path(__file__).resolve().parents[2]
RUIE = REPO.parent / "shared" / "data" / "real" / "ruie-A188-A206"
CFG = SfmConfig(num_threads=2, seed=0)


def _ruie_frames(dst: Path, names: list[str]) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    for n in names:
        shutil.copy(RUIE / "images" / n, dst / n)
    return dst


# ---------------------------------------------------------------- matcher rule (no pycolmap)


def test_choose_matcher_rule() -> None:
    padded = [f"frame_{i:04d}.jpg" for i in range(100)]
    assert choose_matcher(padded[:60], CFG) == "exhaustive"  # small sets: every pair
    assert choose_matcher(padded, CFG) == "sequential"  # long numbered sequence
    unpadded = [f"{i}.jpg" for i in range(100)]  # name order 0, 1, 10, 100, 11: not a sequence
    assert not is_numbered_sequence(unpadded) and choose_matcher(unpadded, CFG) == "exhaustive"
    mixed = [f"left_{i:03d}.jpg" for i in range(40)] + [f"right_{i:03d}.jpg" for i in range(40)]
    assert choose_matcher(mixed, CFG) == "exhaustive"
    assert is_numbered_sequence(["A_188.jpg", "A_190.jpg", "A_206.jpg"])  # gaps allowed
    assert choose_matcher(padded[:5], SfmConfig(matcher="sequential")) == "sequential"
    assert choose_matcher(padded, SfmConfig(matcher="exhaustive")) == "exhaustive"
    with pytest.raises(ValueError):
        choose_matcher(padded, SfmConfig(matcher="vocabtree"))  # type: ignore[arg-type]


def test_invalid_config_and_output_clash_fail_before_any_work(tmp_path: Path) -> None:
    bad_cfgs = [SfmConfig(matcher="aliked"), SfmConfig(camera_model="EQUIRECTANGULAR"), SfmConfig(num_threads=0),
                SfmConfig(image_threads=-2)]  # type: ignore[arg-type]
    for bad in bad_cfgs:
        with pytest.raises(ValueError):
            run_sfm(tmp_path, tmp_path / "out", bad)
    with pytest.raises(ValueError, match="overwrite"):
        run_sfm(tmp_path / "images", tmp_path, CFG)


# ---------------------------------------------------------------- hard inputs → typed errors


def test_missing_and_empty_folders(tmp_path: Path) -> None:
    with pytest.raises(NoImagesError, match="does not exist"):
        run_sfm(tmp_path / "nope", tmp_path / "out", CFG)
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("dive log")
    with pytest.raises(NoImagesError, match="no images"):
        run_sfm(tmp_path / "empty", tmp_path / "out", CFG)


def test_only_corrupt_files(tmp_path: Path) -> None:
    d = tmp_path / "imgs"
    d.mkdir()
    for n in ("a.jpg", "b.png"):
        (d / n).write_bytes(b"\x00" * 100)
    with pytest.raises(NoImagesError, match="none of the 2") as ei:
        run_sfm(d, tmp_path / "out", CFG)
    assert [n for n, _ in ei.value.skipped] == ["a.jpg", "b.png"]


def test_one_image_and_two_identical_images(tmp_path: Path) -> None:
    d = _ruie_frames(tmp_path / "one", ["A_190.jpg"])
    with pytest.raises(TooFewImagesError, match="only 1 readable"):
        run_sfm(d, tmp_path / "out", CFG)
    shutil.copy(d / "A_190.jpg", d / "A_190_copy.jpg")
    with pytest.raises(TooFewImagesError, match="only 2 readable"):
        run_sfm(d, tmp_path / "out", CFG)


def test_identical_images_give_no_model(tmp_path: Path) -> None:
    img = read_image(RUIE / "images" / "A_190.jpg")[50:200, 100:300]  # 200x150 crop keeps it quick
    d = tmp_path / "same"
    for i in range(3):
        write_image(d / f"s{i}.png", img)
    with pytest.raises(NoModelError, match="parallax"):
        run_sfm(d, tmp_path / "out", CFG)


def test_noise_images_give_no_model(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    d = tmp_path / "noise"
    for i in range(10):
        img = np.clip(np.array([0.1, 0.5, 0.6]) + 0.15 * rng.standard_normal((72, 96, 3)), 0, 1)
        write_image(d / f"n{i:02d}.png", img)
    with pytest.raises(NoModelError):
        run_sfm(d, tmp_path / "out", CFG)


# ---------------------------------------------------------------- messy folder: skipped and reported


def _messy_folder(d: Path) -> None:
    """Six consecutive RUIE frames, one stored sideways with EXIF Orientation=6, plus broken files."""
    import OpenImageIO as oiio

    _ruie_frames(d, [f"A_{i}.jpg" for i in (188, 189, 191, 192, 193)])
    upright = (read_image(RUIE / "images" / "A_190.jpg") * 255).round().astype(np.uint8)
    stored = np.ascontiguousarray(np.rot90(upright, k=1))  # displayed upright after a 90° clockwise turn
    spec = oiio.ImageSpec(stored.shape[1], stored.shape[0], 3, oiio.UINT8)
    spec.attribute("Orientation", 6)
    spec.attribute("Compression", "jpeg:95")
    out = oiio.ImageOutput.create(str(d / "A_190.jpg"))
    assert out.open(str(d / "A_190.jpg"), spec) and out.write_image(stored)
    out.close()
    (d / "A_194.jpg").write_bytes((RUIE / "images" / "A_194.jpg").read_bytes()[:15000])  # truncated
    (d / "A_195.jpg").write_bytes(np.random.default_rng(1).bytes(4000))  # garbage
    (d / "readme.txt").write_text("not an image")


def test_corrupt_files_are_skipped_and_reported(tmp_path: Path) -> None:
    d = tmp_path / "messy"
    _messy_folder(d)
    s = run_sfm(d, tmp_path / "out", CFG)
    assert s.total == 8  # 8 image-named files; readme.txt is not one
    assert sorted(n for n, _ in s.skipped) == ["A_194.jpg", "A_195.jpg"]
    assert "Premature end" in dict(s.skipped)["A_194.jpg"]
    assert s.registered == 6 and s.unregistered == [] and s.matcher == "exhaustive"
    assert any("EXIF rotation" in w for w in s.warnings) and any("2 file(s) skipped" in w for w in s.warnings)
    assert 0 < s.mean_reproj_error_px < 2.0 and s.num_points3D > 100
    scene = load_scene(tmp_path / "out")
    assert sorted(v.name for v in scene.views) == [f"A_{i}.jpg" for i in range(188, 194)]
    cams = {v.camera for v in scene.views}
    assert len(cams) == 1
    cam = cams.pop()
    assert cam.width > cam.height  # one landscape camera: the EXIF-rotated frame was matched upright
    assert all(im.shape == (cam.height, cam.width, 3) for im in load_images(scene))
    with pytest.raises(TooFewRegisteredError, match="only 6 of 6"):
        run_sfm(d, tmp_path / "out2", SfmConfig(num_threads=2, min_registered=7))


# ---------------------------------------------------------------- real and synthetic scenes


@pytest.mark.slow
def test_ruie_frames_register(tmp_path: Path, record_property: pytest.RecordProperty) -> None:
    out = tmp_path / "out"
    s = run_sfm(RUIE / "images", out, CFG)
    for k in ("seconds", "registered", "total", "mean_reproj_error_px", "num_points3D"):
        record_property(f"sfm_{k}", round(float(getattr(s, k)), 3))
    assert s.total == 19 and s.registered >= 17 and s.skipped == []
    assert s.mean_reproj_error_px < 2.0 and s.num_points3D > 800
    written = {p.name for p in (out / "sparse" / "0").glob("*.bin")}
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= written
    assert (out / "distorted" / "database.db").is_file() and (out / "distorted" / "sparse" / "0").is_dir()
    est = read_colmap(out / "sparse" / "0", out / "images")
    assert all(v.image_path is not None and v.image_path.is_file() for v in est.views)
    ref = load_scene(RUIE, workdir=tmp_path / "ref")
    m = align_to_reference(est, ref)
    record_property("align", {k: round(v, 5) for k, v in m.items()})
    # sparse_ref is another self-calibrated run on the same frames, not ground truth: loose bounds.
    assert m["n_common"] >= 17 and m["rot_err_deg_mean"] < 2.0 and m["center_err_rel_max"] < 0.02


@pytest.mark.slow
def test_image_threads_do_not_change_a_byte(tmp_path: Path) -> None:
    """Extraction and undistortion on 2 threads (SfmConfig.image_threads) against 1: the model files and the
    undistorted images are the same bytes (matching and mapping stay on one thread)."""
    src = _ruie_frames(tmp_path / "src", sorted(p.name for p in (RUIE / "images").iterdir())[:8])
    outs = []
    for n in (1, 2):
        run_sfm(src, tmp_path / f"out{n}", SfmConfig(num_threads=1, image_threads=n, seed=0))
        outs.append({p.relative_to(tmp_path / f"out{n}"): p.read_bytes()
                     for p in sorted((tmp_path / f"out{n}").glob("**/*")) if p.is_file() and p.suffix != ".db"})
    assert any(k.suffix == ".bin" for k in outs[0]) and any(k.parts[0] == "images" for k in outs[0])
    assert outs[0] == outs[1]


@pytest.mark.slow
def test_synthetic_scene_matches_ground_truth(tmp_path: Path, record_property: pytest.RecordProperty) -> None:
    from pipeline.config import SynthConfig
    from pipeline.synth.procedural import generate_scene

    root = generate_scene(SynthConfig(views=20, supersample=1), tmp_path / "synth")
    s = run_sfm(Path(root) / "images", tmp_path / "out", CFG)
    for k in ("seconds", "registered", "total", "mean_reproj_error_px", "num_points3D"):
        record_property(f"sfm_{k}", round(float(getattr(s, k)), 3))
    assert s.total == 20 and s.registered >= 18
    m = align_to_reference(load_scene(tmp_path / "out"), load_scene(root))
    record_property("align", {k: round(v, 5) for k, v in m.items()})
    assert m["n_common"] >= 18
    assert m["rot_err_deg_max"] < 1.0 and m["center_err_rel_max"] < 0.01


def test_sfm_error_is_the_common_base() -> None:
    for cls in (NoImagesError, TooFewImagesError, NoModelError, TooFewRegisteredError):
        assert issubclass(cls, SfmError)


@pytest.mark.slow
def test_low_contrast_murky_frames_register_on_stretched_features(tmp_path: Path) -> None:
    """Dark, hazy frames (luminance within ~20 grey levels, like the photo family's turbid water) leave SIFT
    too few features to match; SfM then extracts them again from contrast-stretched copies."""
    src = tmp_path / "murky"
    src.mkdir()
    for p in sorted((RUIE / "images").iterdir())[:10]:
        img = read_image(p)
        write_image(src / f"{p.stem}.png", 0.30 + 0.07 * (img - img.mean()), bits=8)  # ~18 grey levels of range
    s = run_sfm(src, tmp_path / "out", CFG)
    assert s.registered >= 9, s
    assert any("contrast-stretched" in w for w in s.warnings), s.warnings
    assert (tmp_path / "out" / "distorted" / "stretched").is_dir()
    # The model's points keep the colours of the photos, not of the stretched copies.
    est = read_colmap(tmp_path / "out" / "sparse" / "0", tmp_path / "out" / "images")
    assert 0.2 < float(np.median(est.colors)) < 0.4
