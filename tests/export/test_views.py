"""The export's per-view images (``pipeline.export.views``) against the trained model they come from."""

from __future__ import annotations

import pytest

from pipeline.config import DensifyConfig, MediumConfig, TrainConfig
from pipeline.export.views import export_views
from pipeline.scene.images import read_image
from pipeline.train.checkpoint import load_checkpoint
from pipeline.train.trainer import Trainer


def _cfg(mode: str, iterations: int) -> TrainConfig:
    densify = DensifyConfig(refine_start=20, refine_stop=50, refine_every=15, reset_every=10_000)
    return TrainConfig(mode=mode, iterations=iterations, sh_degree_interval=20, densify=densify, backend="cpu",
                       log_every=0, medium=MediumConfig(start_fraction=0.25))


@pytest.mark.parametrize("mode", ["3dgs", "dualphys"])
def test_export_writes_every_view_and_matches_the_trainer(small_medium_scene, tmp_path, mode):
    scene, images = small_medium_scene
    tr = Trainer(scene, images, _cfg(mode, 40))
    tr.run([])
    tr.save(tmp_path / "ckpt.pt")
    counts = export_views(load_checkpoint(tmp_path / "ckpt.pt"), scene.views, tmp_path / "out")
    assert counts["views"] == len(scene.views)
    # mode 3dgs restores nothing: no "restored" render that would only repeat the with-water image
    folders = {"with_water", "depth"} | ({"restored", "attenuation", "backscatter"} if mode == "dualphys" else set())
    assert set(counts["folders"]) == folders and {p.name for p in (tmp_path / "out").iterdir()} == folders
    for v in scene.views:
        stem = v.name.rsplit(".", 1)[0]
        I = read_image(tmp_path / "out" / "with_water" / f"{stem}.png")  # noqa: E741
        expect = tr.predict(v).numpy()
        assert abs(I - expect).max() <= 0.5 / 255 + 1e-6  # the same model, only 8-bit rounding between them
        assert (tmp_path / "out" / "depth" / f"{stem}.npy").is_file()
