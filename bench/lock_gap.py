"""How late a renewal thread in the stage process wakes (issue 44, item 2): the job lock is renewed by a daemon
thread in the pool child while the stage runs, and numba kernels (no ``nogil``) and pycolmap calls may hold the
GIL. This runs a generated job's stages in this process (``pipeline.job.runner.run_stage``, as the worker's pool
child does) with a thread that asks to wake every ``--every`` seconds and records, per stage, how late each wake
came: the worst is the longest a run lock's renewal (or any heartbeat written from the stage process) can stall.

    python bench/lock_gap.py --out /tmp/dualphys-lock-gap --views 24 --size 320x240 --iterations 600

The deciding number (docs/DECISIONS.md, "Runner liveness from the worker's heartbeat"): a TTL renewed from this
process must exceed the worst gap with margin; a liveness signal from the worker's main process avoids it.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from pathlib import Path

from pipeline.config import SynthConfig
from pipeline.job.options import JobOptions, StageContext
from pipeline.job.runner import STAGES, run_stage
from pipeline.synth.procedural import generate_scene

log = logging.getLogger("bench.lock_gap")


class WakeProbe:
    """A daemon thread that sleeps ``every`` s at a time and keeps the worst lateness per label."""

    def __init__(self, every: float):
        self.every, self.label = every, "-"
        self.worst: dict[str, float] = {}
        self.wakes: dict[str, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while True:
            t0 = time.monotonic()
            if self._stop.wait(self.every):
                return
            late = time.monotonic() - t0 - self.every
            self.worst[self.label] = max(self.worst.get(self.label, 0.0), late)
            self.wakes[self.label] = self.wakes.get(self.label, 0) + 1

    def __enter__(self) -> WakeProbe:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--views", type=int, default=24)
    p.add_argument("--size", default="320x240")
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--every", type=float, default=0.1, help="the probe thread's wake interval (s)")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    w, h = (int(x) for x in args.size.split("x"))
    scene, job = args.out / "scene", args.out / "job"
    if not (scene / "images").is_dir():
        generate_scene(SynthConfig(views=args.views, width=w, height=h, preset="medium", seed=0), scene)
    opts = JobOptions(source=str(scene / "images"), preset="fast", iterations=args.iterations)
    job.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    with WakeProbe(args.every) as probe:
        for stage in STAGES:
            probe.label = stage
            t0 = time.monotonic()
            run_stage(job, stage, opts, StageContext())
            seconds[stage] = time.monotonic() - t0
    rows = {s: {"seconds": round(seconds[s], 1), "wakes": probe.wakes.get(s, 0),
                "worst_late_s": round(probe.worst.get(s, 0.0), 3)} for s in STAGES}
    for s, r in rows.items():
        log.info("%-9s %7.1f s  %5d wakes  worst late %.3f s", s, r["seconds"], r["wakes"], r["worst_late_s"])
    log.info("json: %s", json.dumps(rows))


if __name__ == "__main__":
    main()
