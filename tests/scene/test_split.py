"""Held-out split: every 8th view by sorted name."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.scene.records import Camera, View
from pipeline.scene.split import split_views


def _views(names: list[str]) -> list[View]:
    cam = Camera(8, 6, 5.0, 5.0, 4.0, 3.0)
    return [View(n, cam, np.eye(3), np.zeros(3)) for n in names]


def test_every_eighth_by_sorted_name_is_test() -> None:
    names = [f"f{i:02d}.png" for i in range(20)]
    shuffled = list(np.random.default_rng(0).permutation(names))
    train, test = split_views(_views(shuffled))
    assert [v.name for v in test] == ["f00.png", "f08.png", "f16.png"]
    assert len(train) == 17 and [v.name for v in train] == sorted(v.name for v in train)
    assert {v.name for v in train} | {v.name for v in test} == set(names)


def test_other_period_and_small_sets() -> None:
    train, test = split_views(_views(["c", "a", "b"]), every=2)
    assert [v.name for v in test] == ["a", "c"] and [v.name for v in train] == ["b"]
    train, test = split_views(_views(["x"]))
    assert (len(train), len(test)) == (0, 1)
    with pytest.raises(ValueError):
        split_views(_views(["a", "b"]), every=1)
