"""Where a training step's time goes: named wall-clock sections, collected only while a profile is open.

Off (the default, and always in jobs), :func:`section` returns one shared no-op context manager: the cost is a
global read and a function call per section (well under a microsecond against steps of ~0.1 s). On
(``with collecting() as seconds:``, only ``bench/job.py`` does it), each section adds its wall time to
``seconds[name]`` and its call count to ``seconds[name + "#"]``. Sections may nest (the rasterizer's backward
runs inside the step's ``backward``); a reader subtracts the inner ones it wants to separate.

Wall time, not CPU time: the kernels run on two threads and what a user waits for is the wall.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import Any

_active: dict[str, float] | None = None


class _Timer:
    __slots__ = ("_into", "_name", "_t0")

    def __init__(self, into: dict[str, float], name: str) -> None:
        self._into, self._name, self._t0 = into, name, 0.0

    def __enter__(self) -> None:
        self._t0 = time.perf_counter()

    def __exit__(self, *exc: Any) -> None:
        into, name = self._into, self._name
        into[name] = into.get(name, 0.0) + time.perf_counter() - self._t0
        into[name + "#"] = into.get(name + "#", 0.0) + 1


_OFF = contextlib.nullcontext()


def section(name: str) -> contextlib.AbstractContextManager:
    """Time the enclosed block as ``name`` while a profile is collecting, else do nothing."""
    return _OFF if _active is None else _Timer(_active, name)


@contextlib.contextmanager
def collecting() -> Iterator[dict[str, float]]:
    """Collect sections (seconds by name, and call counts under ``name + "#"``) until the block ends."""
    global _active
    previous, _active = _active, {}
    try:
        yield _active
    finally:
        _active = previous
