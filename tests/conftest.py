"""Fixtures shared across the test packages."""

from __future__ import annotations

import os
import tempfile

import pytest

from pipeline.config import SynthConfig
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.records import Scene
from pipeline.synth.procedural import generate_scene


def pytest_configure(config) -> None:
    """Undistortion caches (pipeline.scene.loader.default_undistort_cache) go to a scratch folder, not ~/.cache."""
    os.environ.setdefault("DUALPHYS_CACHE", tempfile.mkdtemp(prefix="dualphys-test-cache-"))


def _scope(nodeid: str) -> str:
    """The unit the two workers share out: a test module, or the whole service package."""
    module = nodeid.split("::", 1)[0]
    return "tests/service" if module.startswith("tests/service/") else module


def pytest_collection_modifyitems(config, items) -> None:
    """On an xdist worker, the scopes holding ``slow`` tests come first (each keeps its own order): the scheduler
    below deals scopes out in collection order. xdist's own order, most tests first, dealt the long trainings (few
    tests a module) last, and one worker ran alone for ~9 of the suite's 17 min."""
    if not hasattr(config, "workerinput"):
        return
    slow = {_scope(it.nodeid) for it in items if it.get_closest_marker("slow")}
    items.sort(key=lambda it: _scope(it.nodeid) not in slow)  # stable: scopes stay whole and in their order


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist's; without it installed, never called
def pytest_xdist_make_scheduler(config, log):
    """``make test`` runs two xdist workers (docs/DECISIONS.md, "The test suite on two workers"). Each worker takes
    whole modules, so a module's fixtures (trained jobs) are built once; the service package goes whole to one
    worker: its tests share the live stack's session fixtures and the browser, and some follow one another."""
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _scope(nodeid)

    config.option.loadscopereorder = False  # deal scopes in collection order (slow first), not by test count
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
