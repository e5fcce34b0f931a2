"""Train / held-out split of a scene's views."""

from __future__ import annotations

from pipeline.scene.records import View


def split_views(views: list[View], every: int = 8) -> tuple[list[View], list[View]]:
    """Split views into (train, test): sorted by name, index % ``every`` == 0 is a test view.

    This is the convention of 3DGS, Mip-NeRF 360 and the underwater papers (``every=8``), so our held-out
    numbers are comparable with theirs. Both lists are sorted by name; with fewer than ``every`` views the
    only test view is the first one.
    """
    if every < 2:
        raise ValueError(f"split_views: every must be >= 2, got {every}")
    ordered = sorted(views, key=lambda v: v.name)
    train = [v for i, v in enumerate(ordered) if i % every != 0]
    test = [v for i, v in enumerate(ordered) if i % every == 0]
    return train, test


__all__ = ["split_views"]
