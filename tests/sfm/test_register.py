"""Registering the survey: the retry ladder recovers frames the first mapping pass drops, and every frame still
left out is reported with its reason (``SfmSummary.dropped``)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from pipeline.scene.align import align_to_reference
from pipeline.scene.images import write_image
from pipeline.scene.loader import load_scene
from pipeline.sfm.config import SfmConfig
from pipeline.sfm.recipe import choose_matcher, is_numbered_sequence, run_sfm

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"
RUIE_B = REAL / "ruie-B571-B597"


def _first(dst: Path, folder: Path, n: int) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    for p in sorted((folder / "images").iterdir())[:n]:
        shutil.copy(p, dst / p.name)
    return dst


def test_first_twelve_ruie_frames_register_without_the_ladder(tmp_path: Path) -> None:
    """The hazy, low-texture RUIE B slab at its 400x300 size: all of its first 12 frames register at once."""
    s = run_sfm(_first(tmp_path / "b12", RUIE_B, 12), tmp_path / "out", SfmConfig())
    assert (s.registered, s.total) == (12, 12)
    assert s.dropped == [] and s.retries == []


def test_retry_ladder_registers_the_frames_the_first_pass_drops(tmp_path: Path) -> None:
    """The same 12 frames seen through SIFT at 120 px (a tenth of a large frame's detail): COLMAP's thresholds
    leave B_580-B_582 out (each shares 29 inliers with its neighbours, fewer than the 30 2D-3D inliers a frame
    needs); continuing the kept model with the relaxed thresholds places all 12, in a fraction of a second."""
    src = _first(tmp_path / "b12", RUIE_B, 12)
    first = run_sfm(src, tmp_path / "first", SfmConfig(max_image_size=120, retry_dropped=False))
    assert (first.registered, first.retries) == (9, [])
    assert [d.name for d in first.dropped] == ["B_580.jpg", "B_581.jpg", "B_582.jpg"]
    assert all(d.reason.startswith("failed to register") for d in first.dropped), first.dropped

    s = run_sfm(src, tmp_path / "out", SfmConfig(max_image_size=120))
    assert (s.registered, s.total, s.dropped) == (12, 12, [])
    assert [(r["rung"], r["registered_before"], r["registered"], r["kept"]) for r in s.retries] == [
        ("extend", 9, 12, True)
    ]
    assert s.retries[0]["seconds"] < 5.0 and s.retries[0]["reproj_px"] < 1.0
    assert any("retry ladder ran extend and kept extend: 12 of 12" in w for w in s.warnings)
    # The frames sit where the reference reconstruction of the full-size frames puts them: centre error 0.030 of
    # the path at most (the same 12 frames at full size: 0.026). Twelve centres along a near-straight line leave
    # the fit's rotation about that line free, so orientations are not compared.
    m = align_to_reference(load_scene(tmp_path / "out"), load_scene(RUIE_B, workdir=tmp_path / "ref"))
    assert m["n_common"] == 12 and m["center_err_rel_max"] < 0.04, m
    d = json.loads(json.dumps(s.to_dict()))  # JSON-able: the stage's result, report.json's sfm
    assert d["retries"][0]["rung"] == "extend" and d["dropped"] == []


def test_frames_no_rung_can_place_are_reported_with_their_reason(tmp_path: Path) -> None:
    """A blank frame (no SIFT features) and a noise frame (features, but no match) among 6 RUIE B frames: every
    rung of the ladder runs, none places more, and each frame's reason says what went wrong."""
    src = _first(tmp_path / "mixed", RUIE_B, 6)
    write_image(src / "B_577.jpg", np.full((300, 400, 3), 0.4), bits=8)
    rng = np.random.default_rng(0)
    write_image(src / "B_578.jpg", np.clip(0.5 + 0.2 * rng.standard_normal((300, 400, 3)), 0, 1), bits=8)
    s = run_sfm(src, tmp_path / "out", SfmConfig(max_image_size=200))
    assert (s.registered, s.total) == (6, 8)
    assert [r["rung"] for r in s.retries] == ["extend", "relaxed", "features"]
    assert not any(r["kept"] for r in s.retries)
    reasons = {d.name: d.reason for d in s.dropped}
    assert reasons["B_577.jpg"] == "no features"
    assert reasons["B_578.jpg"].startswith("matched to no other frame"), reasons
    assert any("none placed more" in w for w in s.warnings)


def test_capture_time_names_count_as_a_sequence() -> None:
    """AIMS ReefScan names frames date_time_ms_counter: the prefix changes every second, yet name order is capture
    order, so a long survey is matched sequentially (with loops), not as n^2/2 exhaustive pairs."""
    aims = sorted(p.name for p in (REAL / "aims-erub-mt81" / "images").iterdir())
    assert aims[:2] == ["20230320_012253_000_0001.jpg", "20230320_012253_000_0002.jpg"]
    assert is_numbered_sequence(aims)
    long_survey = [f"20230320_01{2253 + i // 2:04d}_000_{i + 1:04d}.jpg" for i in range(80)]
    assert choose_matcher(long_survey, SfmConfig()) == "sequential"
    # The counter must still increase, and a prefix must be a time (digits and separators, never decreasing).
    assert not is_numbered_sequence(["20230320_012253_000_0002.jpg", "20230320_012254_000_0001.jpg"])
    assert not is_numbered_sequence(["20230320_012254_000_0001.jpg", "20230320_01225_000_0002.jpg"])
    assert not is_numbered_sequence([f"left_{i:03d}.jpg" for i in range(3)] + [f"right_{i:03d}.jpg" for i in (3, 4)])
