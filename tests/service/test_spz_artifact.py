"""The export's reconstruction.spz as a job artifact: listed once export is done, its media type, stored (not
deflated again) in the bundle, the same bytes out of the zip."""

from __future__ import annotations

import hashlib
import io
import zipfile

import torch

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_json
from pipeline.splat.spz import export_spz, read_spz
from service.jobs.artifacts import find_artifact, list_artifacts, zip_stream


def test_the_spz_is_listed_after_export_and_zipped_as_is(tmp_path):
    layout = JobLayout(tmp_path / "job")
    layout.output.mkdir(parents=True)
    g = torch.Generator().manual_seed(0)
    n = 500
    params = {"means": torch.randn(n, 3, generator=g), "scales": torch.randn(n, 3, generator=g) - 4,
              "quats": torch.randn(n, 4, generator=g), "opacities": torch.randn(n, generator=g),
              "sh0": torch.randn(n, 1, 3, generator=g), "shN": torch.zeros(n, 15, 3)}
    data = export_spz(params, layout.spz)
    assert list_artifacts(layout.root) == []  # no export marker yet: a half-written file is never offered
    atomic_write_json(layout.marker("export"), {})
    (art,) = list_artifacts(layout.root)
    assert (art.path, art.size, art.media_type) == ("output/reconstruction.spz", len(data), "application/x-spz")
    assert art.sha256 == hashlib.sha256(data).hexdigest() and find_artifact(layout.root, art.path) == layout.spz
    with zipfile.ZipFile(io.BytesIO(b"".join(zip_stream(layout.root, [art])))) as z:
        (info,) = z.infolist()
        assert info.compress_type == zipfile.ZIP_STORED  # already gzip: deflating it again only costs time
        assert z.read(art.path) == data
    assert torch.equal(read_spz(layout.spz)["shN"], torch.zeros(n, 15, 3))
