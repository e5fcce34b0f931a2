"""One scan of one survey: every new image set (:mod:`.sets`) becomes exactly one job.

- A set is submitted when it has at least ``min_images`` images, or a video (whose keyframes ingest takes), and
  its newest file (by modification time, not capture time) is at least ``settle_s`` old (the ROV has stopped
  writing to it). Smaller sets and sets still
  being written are listed on the survey as ``waiting`` with the reason.
- The job id is derived from (survey, set hash), and a job folder that exists is never created again, so re-scans,
  concurrent scanners and restarts of beat or workers never submit a set twice. A set that changes after
  submission (an image added, replaced or removed) has a new hash and becomes a new job.
- The set's images are copied into the job folder (``input/``) and checked against the hash while copying, so
  the job never depends on a folder that keeps changing. The folder is read through
  :class:`service.surveys.safe_fs.FolderTree` (no link followed, at any depth, at any moment).
"""

from __future__ import annotations

import hashlib
import logging
import os
import secrets
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from pipeline.job.layout import JobLayout
from service.jobs.manifest import Manifest
from service.jobs.ops import pipeline_stages

from .registry import SubmittedSet, Survey, SurveyError, SurveyRegistry, SurveyState, WaitingSet
from .safe_fs import FolderTree
from .sets import HASH_CHUNK, ImageSet, file_sha256, group_images, list_tree, set_hash, with_exif_times

log = logging.getLogger(__name__)


@dataclass
class ScanConfig:
    min_images: int
    settle_s: float
    gap_s: float


def set_job_id(sid: str, set_hash: str) -> str:
    return "s" + hashlib.sha256(f"{sid}\0{set_hash}".encode()).hexdigest()[:23]


def scan(registry: SurveyRegistry, survey: Survey, jobs, cfg: ScanConfig, now: float | None = None) -> list[str]:
    """One scan of one survey (the caller holds the survey's scan lock). Returns the job ids it submitted.

    A set already recorded in the survey's state is never submitted again, even when its job was deleted
    (a user who deletes a job does not want it back on the next scan)."""
    t0 = time.time()
    now = now if now is not None else t0
    state = registry.state(survey.id)
    root = Path(survey.path)
    submitted: list[str] = []
    try:
        allowed_root = registry.check_folder(survey)
        with FolderTree(allowed_root, root) as tree:
            submitted = _scan_tree(registry, survey, jobs, cfg, now, state, tree)
        state.last_error = state.last_error_code = None
    except SurveyError as e:  # the folder is not (any more) one this survey may read: nothing is submitted
        log.error("survey %s: not scanned: %s", survey.id, e)
        state.last_error, state.last_error_code = str(e), e.code
    except OSError as e:  # a link met on the way (ELOOP / ENOTDIR), a vanished folder, a read error
        log.error("survey %s: scan failed: %s", survey.id, e)
        state.last_error = f"scan failed: {e.strerror or e}"
        state.last_error_code = "scan_failed"
    state.scans += 1
    state.last_scan_at = time.time()
    state.last_scan_seconds = round(time.time() - t0, 3)
    registry.save_state(survey.id, state)
    if submitted:
        log.info("survey %s: submitted %s", survey.id, submitted)
    return submitted


def _scan_tree(registry: SurveyRegistry, survey: Survey, jobs, cfg: ScanConfig, now: float, state: SurveyState,
               tree: FolderTree) -> list[str]:
    root = Path(survey.path)
    submitted: list[str] = []
    files = with_exif_times(root, list_tree(tree), state.exif_times, tree)
    present = {f.rel for f in files}
    state.digests = {k: v for k, v in state.digests.items() if k in present}
    state.waiting = []
    for image_set in group_images(files, cfg.gap_s):
        n = len(image_set.files)
        if n < cfg.min_images and not image_set.videos:
            state.waiting.append(WaitingSet(name=image_set.name, images=n, reason=(
                f"too_few_images: {n} image(s); a set needs at least {cfg.min_images} to be reconstructed "
                f"(it is submitted once it has them)")))
            continue
        if now - image_set.newest < cfg.settle_s:
            state.waiting.append(WaitingSet(name=image_set.name, images=n, reason=(
                f"settling: the newest image is {now - image_set.newest:.0f} s old; sets are submitted "
                f"{cfg.settle_s:.0f} s after their last change")))
            continue
        for f in image_set.files:
            known = state.digests.get(f.rel)
            if known is None or known[0] != f.size or known[1] != f.mtime_ns:
                state.digests[f.rel] = (f.size, f.mtime_ns, file_sha256(root / f.rel, tree.open(f.rel)))
        h = set_hash(image_set.files, state.digests)
        job_id = set_job_id(survey.id, h)
        if h in state.sets:
            _requeue_if_never_sent(jobs, job_id)
            continue
        name = unique_set_name(image_set.name, state.sets)
        try:
            if submit_set(jobs, survey, ImageSet(name, image_set.files), h, job_id, state.digests, tree):
                submitted.append(job_id)
        except SurveyError as e:
            log.warning("survey %s: set %s not submitted: %s", survey.id, image_set.name, e)
            continue
        state.sets[h] = SubmittedSet(name=name, images=n, job_id=job_id, submitted_at=time.time())
        registry.save_state(survey.id, state)  # recorded at once: a crash later in the scan loses nothing
    return submitted


def unique_set_name(name: str, sets: dict[str, SubmittedSet]) -> str:
    """``name``, or ``name (2)``, ``name (3)`` ... when earlier sets (e.g. the same sub-folder before it grew)
    already carry it: every job of a survey has its own display name."""
    taken = {s.name for s in sets.values()}
    if name not in taken:
        return name
    k = 2
    while f"{name} ({k})" in taken:
        k += 1
    return f"{name} ({k})"


def _requeue_if_never_sent(jobs, job_id: str) -> None:
    """A job whose creator died between writing its manifest and queueing its first stage gets queued now."""
    store = jobs.store
    if not store.exists(job_id):
        return
    m: Manifest = store.read(job_id)
    if m.state == "queued" and not m.dispatched and time.time() - m.created_at > 30:
        log.warning("survey job %s was never queued; queueing it now", job_id)
        jobs.dispatch(job_id, m.run_id, m.next_stage(pipeline_stages()))


def submit_set(jobs, survey: Survey, image_set: ImageSet, h: str, job_id: str,
               digests: dict[str, tuple[int, int, str]], tree: FolderTree | None = None) -> bool:
    """Create the job of one set unless it exists; True when this call created it.

    Copy into a staging folder, verify every file's hash while copying, rename the folder into place (atomic),
    then write the manifest and queue the first stage. A crash at any point leaves either nothing, a folder
    without manifest (removed and redone by the next scan) or a queued job whose first stage was never sent
    (sent by the next scan).
    """
    store = jobs.store
    final = store.job_dir(job_id)
    if store.exists(job_id):  # the state file was lost, the job was not: adopt it
        _requeue_if_never_sent(jobs, job_id)
        return False
    if final.exists():  # a scanner died between the rename and the manifest
        shutil.rmtree(final)
    staging = store.root / f".staging-{job_id}-{secrets.token_hex(3)}"
    root = Path(survey.path)
    try:
        for f in image_set.files:
            dst = JobLayout(staging).input / f.rel  # the staging folder becomes the job folder
            dst.parent.mkdir(parents=True, exist_ok=True)
            src = tree.open(f.rel) if tree is not None else open(root / f.rel, "rb")
            if _copy_hashed(src, dst) != digests[f.rel][2]:
                raise SurveyError("set_changed", f"{f.rel} changed while it was copied; the next scan retries")
        os.rename(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    opts = {**survey.options.model_dump(), "source": str(JobLayout(final).input)}
    source = {"kind": "survey", "survey_id": survey.id, "set": image_set.name, "set_hash": h,
              "images": len(image_set.files) - image_set.videos, "videos": image_set.videos}
    jobs.create(job_id, survey.owner, opts, source, survey_id=survey.id, callback_url=survey.callback_url)
    return True


def _copy_hashed(src: BinaryIO, dst: Path) -> str:
    h = hashlib.sha256()
    with src as fi, open(dst, "xb") as fo:
        while chunk := fi.read(HASH_CHUNK):
            h.update(chunk)
            fo.write(chunk)
        st = os.fstat(fi.fileno())
    os.utime(dst, ns=(st.st_atime_ns, st.st_mtime_ns))
    return h.hexdigest()
