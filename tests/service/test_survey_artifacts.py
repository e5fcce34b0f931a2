"""The survey stage's products as job artifacts (no server, no browser): the files in output/survey/ are listed and
served once export is done (like everything in output/), survey.json once the survey stage is (its
``publishes``), and a half-written product is never offered."""

from __future__ import annotations

import hashlib
import io
import zipfile

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from service.jobs.artifacts import find_artifact, list_artifacts, zip_stream


def _products(layout: JobLayout) -> dict[str, bytes]:
    """Stand-ins with the products' names (the listing reads names and bytes, not formats)."""
    files = {layout.ortho: b"II*\x00ortho", layout.ortho_water: b"II*\x00water", layout.ortho_confidence: b"II*\x00c",
             layout.dem: b"II*\x00dem", layout.ortho_preview: b"\xff\xd8ortho",
             layout.ortho_water_preview: b"\xff\xd8w", layout.hillshade_preview: b"\x89PNGshade"}
    layout.survey.mkdir(parents=True)
    for path, data in files.items():
        path.write_bytes(data)
    return {layout.relative(p): data for p, data in files.items()}


def test_survey_products_are_listed_once_export_is_done(tmp_path):
    layout = JobLayout(tmp_path / "job")
    products = _products(layout)
    assert list_artifacts(layout.root) == []  # written, but export has not finished: not offered yet
    atomic_write_json(layout.marker("export"), {})
    listed = {a.path: a for a in list_artifacts(layout.root)}
    assert set(listed) == set(products)
    for path, data in products.items():
        assert listed[path].size == len(data) and listed[path].sha256 == hashlib.sha256(data).hexdigest()
        assert find_artifact(layout.root, path) == layout.root / path
    assert listed[layout.relative(layout.dem)].media_type == "image/tiff"
    assert listed[layout.relative(layout.ortho_preview)].media_type == "image/jpeg"
    assert listed[layout.relative(layout.hillshade_preview)].media_type == "image/png"
    with zipfile.ZipFile(io.BytesIO(b"".join(zip_stream(layout.root, list(listed.values()))))) as z:
        assert {n: z.read(n) for n in z.namelist()} == products


def test_survey_json_is_listed_once_the_survey_stage_is_done(tmp_path):
    layout = JobLayout(tmp_path / "job")
    atomic_write_json(layout.survey_result, {"grid": {"gsd": 0.002}})
    assert list_artifacts(layout.root) == []
    atomic_write_json(layout.marker("survey"), {})
    (art,) = list_artifacts(layout.root)
    assert (art.path, art.media_type) == (layout.relative(layout.survey_result), "application/json")
    assert find_artifact(layout.root, art.path) == layout.survey_result
