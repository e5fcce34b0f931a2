"""Issue 11's bar on real footage we did not make: the 19 frames of RUIE A188-A206 (green coastal water, a sandy
slope with urchins; shared/data/real), through the whole job (SfM, mode auto, the fast schedule compressed,
trained at 200 px wide). A medium model must be chosen, the restored views must move away from the green cast
(mean R/G up) without clipped red, and no part of the scene may be drawn far behind the seabed where it shows
only the veil: before ``depth_band_loss`` 24 % of the restored pixels of the full-size job were black sand.

Since runs repeat bit for bit (one-thread SfM, the backward summed by tile; docs/DECISIONS.md): homogeneous,
R/G 0.357 → 0.439, no clipped red, 2.1 % black (the urchins), far_share 0. Before that, the same code gave
far_share 1.4 %, 10.6 % and 18 % in different runs, and "9.5 % with ``depth_band_loss`` off" was one such run:
today the term off gives far_share 0 here too (R/G 0.439, 2.1 % black). At this size the test guards the
outcome, not that one term; the term's effect shows on the full-size job (24 % black sand before it, 2.1 %).

The design is in docs/DECISIONS.md, "The water must not eat the scene"; the current full-size real-set figures are
in docs/RESULTS.md, "Real surveys".
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions
from pipeline.job.runner import run_job
from pipeline.scene.images import read_image

N_FRAMES = 19
FRAMES = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "ruie-A188-A206" / "images"

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not FRAMES.is_dir(), reason="shared/data/real is not beside "
                                                                               "the repository")]


def _colour(folder: Path) -> tuple[float, float, float]:
    """Mean R/G over the views, share of clipped red, share of black pixels."""
    rg, red, black = [], [], []
    for f in sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")):
        a = read_image(f)
        rg.append(a[..., 0].mean() / max(a[..., 1].mean(), 1e-6))
        red.append((a[..., 0] > 0.98).mean())
        black.append((a.max(-1) < 0.04).mean())
    return float(np.mean(rg)), float(np.mean(red)), float(np.mean(black))


def test_real_green_water_gets_a_medium_and_its_colour_back(tmp_path, record_property):
    src = tmp_path / "frames"
    src.mkdir()
    for f in sorted(FRAMES.iterdir())[:N_FRAMES]:
        shutil.copy(f, src / f.name)
    run_job(tmp_path / "job", JobOptions(source=str(src), iterations=1500, max_width=200))
    job = JobLayout(tmp_path / "job")
    r = json.loads(job.report_json.read_text())
    q = r["quality"]
    rg_in, _, _ = _colour(job.render_folder("with_water"))
    rg, red, black = _colour(job.render_folder("restored"))
    record_property("result", {"mode": r["mode"], "reason": r["selection"]["reason"], "rg": [rg_in, rg],
                               "clipped_red": red, "black": black, "far_share_max": q["far_share_max"]})
    assert r["mode"] in ("homogeneous", "dualphys"), r["selection"]["reason"]
    assert not q["collapsed"] and q["point_coverage_min"] >= 0.98, q["warnings"]
    assert rg > rg_in + 0.02, (rg_in, rg)  # away from the green cast
    assert red < 0.002, red  # no clipped red
    assert black < 0.05, black  # no sand drawn as far-away veil
    assert q["far_share_max"] is not None and q["far_share_max"] <= 0.05, q["far_share_max"]
    # issue 14: the photos themselves come back de-watered at their own 400x300 in their own lens geometry,
    # with the same colour shift, and the report shows them
    restore = json.loads(job.restore_result.read_text())
    assert restore["restored"] >= 17 and all((v["width"], v["height"]) == (400, 300) for v in restore["views"])
    for v in restore["views"][:3]:
        assert read_image(job.restored / v["file"]).shape == read_image(src / v["name"]).shape == (300, 400, 3)
    rg_photos_in, _, _ = _colour(src)
    rg_photos, red_photos, _ = _colour(job.restored)
    record_property("photos", {"rg": [rg_photos_in, rg_photos], "clipped_red": red_photos})
    assert rg_photos > rg_photos_in + 0.02 and red_photos < 0.002, (rg_photos_in, rg_photos, red_photos)
    html = job.report_html.read_text()
    assert f"{restore['restored']} photos restored at their own resolution (400x300)" in html
