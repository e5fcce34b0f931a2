"""A photo SfM placed in a separate model is listed as not restored with that reason, not 'no pose'."""

from pipeline.job.markers import run_marked
from pipeline.restore.stage import _split_models


def test_split_model_images_are_named(tmp_path):
    result = {"outcome": "split", "other_models": [{"index": 1, "registered": 4, "images": ["b1.jpg", "b2.jpg"]}]}
    run_marked(tmp_path, "sfm", {"seed": 0}, lambda: result)
    why = _split_models(tmp_path)
    assert set(why) == {"b1.jpg", "b2.jpg"}
    assert "separate model 1 (4 images)" in why["b1.jpg"]


def test_no_sfm_marker_means_no_split(tmp_path):
    assert _split_models(tmp_path) == {}
