"""Fixtures shared across the test packages."""

from __future__ import annotations

import pytest

from pipeline.config import SynthConfig
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import Scene
from pipeline.synth.procedural import generate_scene


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist's; without it installed, never called
def pytest_xdist_make_scheduler(config, log):
    """``make test`` runs two xdist workers (docs/DECISIONS.md, "The test suite on two workers"). Each worker takes
    whole modules, so a module's fixtures (trained jobs) are built once; the service package goes whole to one
    worker: its tests share the live stack's session fixtures and the browser, and some follow one another."""
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "tests/service" if module.startswith("tests/service/") else module

    return ModuleScheduling(config, log)


@pytest.fixture(scope="session")
def small_medium_scene(tmp_path_factory):
    """A generated 8-view 96x72 `medium` scene with its true cameras, and its underwater images: for short
    training runs (train, export)."""
    root = generate_scene(SynthConfig(views=8, width=96, height=72, preset="medium", seed=2),
                          tmp_path_factory.mktemp("small-medium"))
    scene = load_scene(root)
    return Scene(scene.views, scene.points, scene.colors, root), [read_image(root / "images" / v.name)
                                                                   for v in scene.views]
