"""Fixtures shared across the test packages."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.config import SynthConfig
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import Scene
from pipeline.synth.procedural import generate_scene

TESTS = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config, items) -> None:
    """Under pytest-xdist's ``--dist loadgroup`` (``make test`` runs two workers: docs/DECISIONS.md, "The test
    suite on two workers"), a module runs whole on one worker, so its module-scoped fixtures (trained jobs) are
    built once; and every service test runs on the same worker: they share the live stack's session fixtures,
    the browser and the machine's Redis."""
    if getattr(config.option, "dist", "no") != "loadgroup":
        return
    for item in items:
        rel = Path(item.path).resolve().relative_to(TESTS)
        group = "service" if rel.parts[0] == "service" else rel.as_posix()
        item.add_marker(pytest.mark.xdist_group(group))


@pytest.fixture(scope="session")
def small_medium_scene(tmp_path_factory):
    """A generated 8-view 96x72 `medium` scene with its true cameras, and its underwater images: for short
    training runs (train, export)."""
    root = generate_scene(SynthConfig(views=8, width=96, height=72, preset="medium", seed=2),
                          tmp_path_factory.mktemp("small-medium"))
    scene = load_scene(root)
    return Scene(scene.views, scene.points, scene.colors, root), [read_image(root / "images" / v.name)
                                                                   for v in scene.views]
