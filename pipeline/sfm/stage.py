"""The SfM stage: ``job/images/`` -> ``job/scene/`` through the pycolmap recipe, cancellable."""

from __future__ import annotations

import threading
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobCancelled, JobOptions, StageContext
from pipeline.sfm.config import SfmConfig
from pipeline.sfm.recipe import run_sfm


def stage_sfm(job: Path, opts: JobOptions, ctx: StageContext) -> dict:
    """pycolmap runs in native code, so a watcher thread turns ``should_cancel`` into its CancellationToken;
    the running step then raises InterruptedError, which becomes JobCancelled."""
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    layout = JobLayout(job)
    token, done = pycolmap.CancellationToken(), threading.Event()

    def watch() -> None:
        while not done.wait(0.25):
            if ctx.should_cancel():
                token.cancel()
                return

    watcher = threading.Thread(target=watch, name="sfm-cancel-watch", daemon=True)
    watcher.start()
    try:
        return run_sfm(layout.images, layout.scene, SfmConfig(seed=opts.seed), cancellation_token=token).to_dict()
    except InterruptedError as e:
        raise JobCancelled(f"cancelled during sfm: {e}") from e
    finally:
        done.set()
        watcher.join()
