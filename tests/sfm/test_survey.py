"""SfM at survey size: loop detection on the survey's own vocabulary tree, and a survey that breaks apart."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pycolmap
import pytest

from pipeline.sfm.config import SfmConfig
from pipeline.sfm.loops import MAX_WORDS, MIN_WORDS, build_vocab_tree, num_words
from pipeline.sfm.recipe import run_sfm

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"


def _copy(dst: Path, folder: str, names: list[str]) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    for n in names:
        shutil.copy(REAL / folder / "images" / n, dst / n)


def test_vocabulary_size_rule() -> None:
    assert num_words(0) == MIN_WORDS == 64
    assert num_words(64 * 39 * 2 - 1) == 64 and num_words(64 * 39 * 2) == 128  # >= 39 descriptors per word
    assert num_words(37_124) == 512  # 48 views at 320x240 (~770 SIFT features each)
    assert num_words(10**7) == MAX_WORDS == 1024


def test_two_unrelated_sites_give_two_models_largest_kept(tmp_path: Path) -> None:
    """Six RUIE A frames and four of another site (B): no match between the sites, so the mapper builds two
    models. The larger is trained on; the other is reported by name and kept on disk, not a crash."""
    src = tmp_path / "mixed"
    a = [f"A_{i}.jpg" for i in range(188, 194)]
    b = [f"B_{i}.jpg" for i in range(571, 575)]
    _copy(src, "ruie-A188-A206", a)
    _copy(src, "ruie-B571-B597", b)
    out = tmp_path / "out"
    s = run_sfm(src, out, SfmConfig(num_threads=2, max_image_size=480))
    assert s.outcome == "split" and s.total == 10
    assert s.registered == 6 and s.unregistered == b
    assert len(s.other_models) == 1
    assert not (out / "distorted" / "stretched").exists()  # every image placed somewhere: no murky-water retry
    other = s.other_models[0]
    assert other.index == 1 and other.registered == 4 and other.images == b
    assert any("2 separate models" in w and "B_571.jpg .. B_574.jpg" in w for w in s.warnings)
    # The retry ladder tried to place B in A's model and could not (nothing matches); each B frame says why.
    assert [r["rung"] for r in s.retries] == ["extend", "relaxed", "features"]
    assert not any(r["kept"] for r in s.retries)
    side = "in a side model of 4 frames (distorted/sparse/1)"
    assert [(d.name, d.reason) for d in s.dropped] == [(n, side) for n in b]
    kept = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert sorted(im.name for im in kept.images.values()) == a
    side = pycolmap.Reconstruction(str(out / "distorted" / "sparse" / "1"))
    assert sorted(im.name for im in side.images.values()) == b and side.num_points3D() > 50
    d = json.loads(json.dumps(s.to_dict()))  # JSON-able, as the stage's result
    assert d["outcome"] == "split" and d["other_models"][0]["images"] == b
    assert set(d["phase_seconds"]) == {"extract", "match", "map", "undistort"}
    assert d["pairs_matched"] >= 15 + 6 - 2  # A's 15 pairs nearly all verified, plus B's neighbours


def test_sequential_matching_finds_loops_on_its_own_vocabulary(tmp_path: Path) -> None:
    """Twelve consecutive RUIE frames matched sequentially with a window of 2: pairs further apart (the
    frames overlap over most of the sequence) are only found by loop detection on the tree built from these
    frames' own descriptors."""
    src = tmp_path / "seq"
    _copy(src, "ruie-A188-A206", [f"A_{i}.jpg" for i in range(188, 200)])
    cfg = SfmConfig(num_threads=2, matcher="sequential", sequential_overlap=2, max_image_size=480)
    s = run_sfm(src, tmp_path / "out", cfg)
    assert s.outcome == "single" and s.registered >= 11
    tree = tmp_path / "out" / "distorted" / "vocab_tree.bin"
    assert tree.stat().st_size > 10_000
    # Seeded: the same database gives the same tree, byte for byte (unseeded builds differed).
    again = tmp_path / "again.bin"
    build_vocab_tree(tmp_path / "out" / "distorted" / "database.db", again, seed=cfg.seed)
    assert again.read_bytes() == tree.read_bytes()
    assert "vocab" in s.phase_seconds
    # Window 2 plus quadratic jumps pair 12 frames 2+... ways; loop pairs are those at other distances (3, 5, 6..)
    assert s.loop_pairs >= 5, s
    assert s.mean_reproj_error_px < 2.0


@pytest.mark.parametrize("bad", [SfmConfig(sequential_overlap=0)])
def test_bad_overlap_is_refused(tmp_path: Path, bad: SfmConfig) -> None:
    with pytest.raises(ValueError, match="out of range"):
        run_sfm(tmp_path, tmp_path / "out", bad)


def test_side_models_list_only_images_the_kept_model_lacks() -> None:
    """pycolmap may start a further model from images the first one places later (the 27 RUIE B frames: kept
    model 27, side models of 8 and 5 of the same frames). Those are not a split survey: nothing was left out."""
    from pipeline.sfm.recipe import SubModel, separate_models

    kept = {f"B_{i}.jpg" for i in range(571, 598)}
    dup = [SubModel(1, 8, [f"B_{i}.jpg" for i in range(584, 592)]),
           SubModel(2, 5, [f"B_{i}.jpg" for i in range(592, 597)])]
    assert separate_models(dup, kept) == []
    part = SubModel(1, 4, ["A_1.jpg", "B_571.jpg", "B_900.jpg", "B_901.jpg"])
    assert separate_models([part], kept) == [SubModel(1, 3, ["A_1.jpg", "B_900.jpg", "B_901.jpg"])]
    assert separate_models([SubModel(1, 2, ["x.jpg", "y.jpg"])], set()) == [SubModel(1, 2, ["x.jpg", "y.jpg"])]
