"""Survey scanning called directly (no beat, no worker): one job per set, content identity, settle time,
deleted jobs stay deleted, lost scan state does not duplicate, a set copied into the job folder."""

from __future__ import annotations

import os
import time
from pathlib import Path

from svc_helpers import small_jpegs

from service.surveys import ScanConfig, SurveyOptions, SurveyRegistry, scan


def _registry(rt) -> SurveyRegistry:
    s = rt.settings
    return SurveyRegistry(s.surveys_dir, s.survey_roots, s.surveys_file, s.survey_min_interval_s)


def _write(folder: Path, n: int, seed: int, mtime: float | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, data in enumerate(small_jpegs(n, seed=seed)):
        p = folder / f"img_{seed}_{i}.jpg"
        p.write_bytes(data)
        if mtime is not None:
            os.utime(p, (mtime + i, mtime + i))


def test_each_set_becomes_exactly_one_job(rt) -> None:
    root = rt.settings.survey_roots[0]
    site = root / "site"
    _write(site / "dive-a", 3, seed=1)
    reg = _registry(rt)
    survey = reg.register("alice", str(site), 1, None, SurveyOptions(iterations=10))
    cfg = ScanConfig(min_images=3, settle_s=0, gap_s=300)

    first = scan(reg, survey, rt.jobs, cfg)
    assert len(first) == 1
    m = rt.store.read(first[0])
    assert m.owner == "alice" and m.survey_id == survey.id and m.options["iterations"] == 10
    assert m.source["set"] == "dive-a" and m.state == "queued"
    copied = sorted(p.name for p in (rt.store.job_dir(first[0]) / "input" / "dive-a").iterdir())
    assert copied == sorted(p.name for p in (site / "dive-a").iterdir())
    assert rt.jobs.dispatcher.sent == [(first[0], "ingest", m.run_id)]

    assert scan(reg, survey, rt.jobs, cfg) == []  # nothing new
    (reg._folder(survey.id) / "state.json").unlink()  # the scan state is lost: the job is adopted, not redone
    assert scan(reg, survey, rt.jobs, cfg) == []
    assert len(rt.jobs.list("alice")) == 1

    rt.jobs.cancel(first[0], "alice")
    rt.jobs.delete(first[0], "alice")
    assert scan(reg, survey, rt.jobs, cfg) == []  # a deleted job is not resubmitted

    _write(site / "dive-b", 2, seed=2)  # too small: waits
    assert scan(reg, survey, rt.jobs, cfg) == []
    _write(site / "dive-b", 1, seed=3)  # now three images
    second = scan(reg, survey, rt.jobs, cfg)
    assert len(second) == 1 and rt.store.read(second[0]).source["images"] == 3
    assert reg.state(survey.id).scans == 4 and len(reg.state(survey.id).sets) == 2  # 4 since the state was lost


def test_loose_images_split_by_time_gaps_and_wait_to_settle(rt) -> None:
    root = rt.settings.survey_roots[0]
    site = root / "loose"
    t = time.time() - 10_000
    _write(site, 3, seed=10, mtime=t)
    _write(site, 3, seed=20, mtime=t + 1000)  # a second burst after a gap longer than gap_s
    reg = _registry(rt)
    survey = reg.register("bob", str(site), 1, "loose", SurveyOptions())
    assert len(scan(reg, survey, rt.jobs, ScanConfig(min_images=3, settle_s=0, gap_s=300))) == 2
    _write(site, 3, seed=30)  # just written: younger than settle_s
    assert scan(reg, survey, rt.jobs, ScanConfig(min_images=3, settle_s=3600, gap_s=300)) == []
    assert len(rt.jobs.list("bob")) == 2


def test_same_content_under_another_survey_is_another_job(rt) -> None:
    root = rt.settings.survey_roots[0]
    _write(root / "one" / "d", 3, seed=5)
    _write(root / "two" / "d", 3, seed=5)
    reg = _registry(rt)
    cfg = ScanConfig(min_images=3, settle_s=0, gap_s=300)
    a = scan(reg, reg.register("alice", str(root / "one"), 1, None, SurveyOptions()), rt.jobs, cfg)
    b = scan(reg, reg.register("alice", str(root / "two"), 1, None, SurveyOptions()), rt.jobs, cfg)
    assert len(a) == len(b) == 1 and a != b
