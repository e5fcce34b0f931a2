"""Fixtures shared across the test packages."""

from __future__ import annotations

import pytest

from pipeline.config import SynthConfig
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import Scene
from pipeline.synth.procedural import generate_scene


@pytest.fixture(scope="session")
def small_medium_scene(tmp_path_factory):
    """A generated 8-view 96x72 `medium` scene with its true cameras, and its underwater images: for short
    training runs (train, export)."""
    root = generate_scene(SynthConfig(views=8, width=96, height=72, preset="medium", seed=2),
                          tmp_path_factory.mktemp("small-medium"))
    scene = load_scene(root)
    return Scene(scene.views, scene.points, scene.colors, root), [read_image(root / "images" / v.name)
                                                                   for v in scene.views]
