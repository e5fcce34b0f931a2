"""Terminal progress for a job's stages (``dualphys run``): one tqdm bar per stage when tqdm is installed, else a
short line on stderr at most every ``min_interval`` seconds. Used as ``StageContext.on_progress``."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from typing import Any, TextIO


class StageProgress:
    """``on_progress(stage, fraction, message)`` for :class:`pipeline.job.options.StageContext`."""

    def __init__(self, stages: Sequence[str], stream: TextIO | None = None, use_tqdm: bool | None = None,
                 min_interval: float = 5.0) -> None:
        self.stages = list(stages)
        self.stream = stream or sys.stderr
        self.min_interval = min_interval
        self._tqdm: Any = None
        if use_tqdm is not False:
            try:
                from tqdm import tqdm  # lazy: an optional package; without it progress is a plain line

                self._tqdm = tqdm
            except ImportError:
                if use_tqdm:
                    raise
        self._bar: Any = None
        self._stage = ""
        self._last = 0.0
        self._finished = False
        self.skipped: list[str] = []  # stages whose marker matched (nothing was run)

    @property
    def stage(self) -> str:
        """The stage last reported ("" before the first)."""
        return self._stage

    def _label(self, stage: str) -> str:
        i = self.stages.index(stage) + 1 if stage in self.stages else 0
        return f"[{i}/{len(self.stages)}] {stage}"

    def __call__(self, stage: str, fraction: float, message: str) -> None:
        if stage != self._stage:
            self.close()
            self._stage, self._last, self._finished = stage, 0.0, False
            if self._tqdm is not None:
                self._bar = self._tqdm(total=1000, desc=self._label(stage), file=self.stream, leave=True,
                                       bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed} {postfix}")
        if self._finished:  # the stage's own last report already closed it
            return
        done = fraction >= 1.0
        if done and message.startswith("skipped"):
            self.skipped.append(stage)
        self._finished = done
        if self._bar is not None:
            self._bar.n = int(round(1000 * min(max(fraction, 0.0), 1.0)))
            self._bar.set_postfix_str(message, refresh=False)
            self._bar.refresh()
            if done:
                self.close()
            return
        now = time.monotonic()
        if fraction <= 0.0 or done or now - self._last >= self.min_interval:
            self._last = now
            self.stream.write(f"{self._label(stage)}: {100 * fraction:5.1f}% {message}\n")
            self.stream.flush()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


__all__ = ["StageProgress"]
