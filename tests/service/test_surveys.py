"""Survey scanning called directly (no beat, no worker): one job per set, content identity, settle time,
deleted jobs stay deleted, lost scan state does not duplicate, a set copied into the job folder; loose images
grouped by EXIF capture time (files written with Exif tags by OpenImageIO), falling back to mtime."""

from __future__ import annotations

import os
import random
import time
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from svc_helpers import small_jpegs, small_video

from service.surveys.exif import read_exif_time
from service.surveys.registry import SurveyError, SurveyOptions, SurveyRegistry
from service.surveys.scan import ScanConfig, scan
from service.surveys.sets import ImageFile, with_exif_times


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
    copied = sorted(p.name for p in (rt.store.layout(first[0]).input / "dive-a").iterdir())
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


def test_a_folder_with_one_video_is_a_set(rt) -> None:
    """A video counts as enough for a set (its keyframes are the images); it is copied like a photo."""
    site = rt.settings.survey_roots[0] / "rov"
    (site / "transect-1").mkdir(parents=True)
    (site / "transect-1" / "cam.mp4").write_bytes(small_video())
    (site / "transect-1" / "notes.txt").write_text("not part of the set")
    _write(site / "transect-2", 2, seed=5)  # two photos and no video: waits
    reg = _registry(rt)
    survey = reg.register("alice", str(site), 1, None, SurveyOptions())
    jobs = scan(reg, survey, rt.jobs, ScanConfig(min_images=3, settle_s=0, gap_s=300))
    assert len(jobs) == 1
    m = rt.store.read(jobs[0])
    assert m.source["set"] == "transect-1" and m.source["images"] == 0 and m.source["videos"] == 1
    assert [p.name for p in (rt.store.layout(jobs[0]).input / "transect-1").iterdir()] == ["cam.mp4"]
    assert [w.name for w in reg.state(survey.id).waiting] == ["transect-2"]


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


# ---------------------------------------------------------------- capture time from EXIF


def _write_exif(path: Path, exif: dict[str, str], mtime: float, seed: int = 0) -> None:
    """A small image (format from the suffix) carrying ``exif`` (OpenImageIO names without the ``Exif:`` prefix,
    e.g. ``SubsecTimeOriginal``), with its mtime set; checks that the tags round-trip through OpenImageIO."""
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = oiio.ImageSpec(32, 24, 3, "uint8")
    for k, v in exif.items():
        spec.attribute(f"Exif:{k}", v)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), spec), oiio.geterror()
    assert out.write_image(np.random.default_rng(seed).integers(0, 256, (24, 32, 3), dtype=np.uint8))
    out.close()
    os.utime(path, (mtime, mtime))
    inp = oiio.ImageInput.open(str(path))
    try:
        assert {k: inp.spec().getattribute(f"Exif:{k}") for k in exif} == exif
    finally:
        inp.close()


def _stamp(t: float, tz: timezone = UTC) -> str:
    return datetime.fromtimestamp(t, tz).strftime("%Y:%m:%d %H:%M:%S")


def _set_name(t: float) -> str:
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(t))


def _job_sets(rt, owner: str) -> dict[str, list[str]]:
    """Set name -> the image names copied into its job."""
    out = {}
    for m in rt.jobs.list(owner):
        out[m.source["set"]] = sorted(p.name for p in rt.store.layout(m.id).input.iterdir())
    return out


def test_loose_images_grouped_by_exif_capture_time_and_settled_by_mtime(rt) -> None:
    site = rt.settings.survey_roots[0] / "exif"
    t = float(int(time.time()) - 100_000)
    plus2 = timezone(timedelta(hours=2))
    order = list(range(6))
    random.Random(0).shuffle(order)  # mtimes 1000 s apart in shuffled order: by mtime, six sets of one
    for i in range(6):
        burst, k = i % 2, i // 2  # img_0/2/4: first burst (local time +02:00, sub-seconds); img_1/3/5: second (UTC)
        taken = t + 1000 * burst + 2 * k
        exif = ({"DateTimeOriginal": _stamp(taken, plus2), "SubsecTimeOriginal": "250",
                 "OffsetTimeOriginal": "+02:00"} if burst == 0 else {"DateTimeOriginal": _stamp(taken)})
        _write_exif(site / f"img_{i}.jpg", exif, mtime=t + 50_000 + 1000 * order[i], seed=i)
    reg = _registry(rt)
    survey = reg.register("carol", str(site), 1, None, SurveyOptions())
    cfg = ScanConfig(min_images=3, settle_s=0, gap_s=300)
    assert len(scan(reg, survey, rt.jobs, cfg)) == 2
    assert _job_sets(rt, "carol") == {_set_name(t): ["img_0.jpg", "img_2.jpg", "img_4.jpg"],
                                      _set_name(t + 1000): ["img_1.jpg", "img_3.jpg", "img_5.jpg"]}
    cached = reg.state(survey.id).exif_times
    assert cached["img_0.jpg"][2] == t + 0.25 and cached["img_5.jpg"][2] == t + 1004

    for i in range(6, 9):  # a third burst taken long ago but copied just now: waits until its files settle
        _write_exif(site / f"img_{i}.jpg", {"DateTimeOriginal": _stamp(t + 5000 + i)}, mtime=time.time(), seed=i)
    assert scan(reg, survey, rt.jobs, ScanConfig(min_images=3, settle_s=3600, gap_s=300)) == []
    assert len(scan(reg, survey, rt.jobs, cfg)) == 1
    assert _job_sets(rt, "carol")[_set_name(t + 5006)] == ["img_6.jpg", "img_7.jpg", "img_8.jpg"]


def test_missing_or_malformed_exif_time_falls_back_to_mtime(rt) -> None:
    site = rt.settings.survey_roots[0] / "mixed"
    t = float(int(time.time()) - 100_000)
    late = t + 10_000  # every file's mtime: grouping by mtime alone would make one set of six
    for i in range(3):
        _write_exif(site / f"exif_{i}.jpg", {"DateTimeOriginal": _stamp(t + i)}, mtime=late, seed=i)
    for i, data in enumerate(small_jpegs(2, seed=40)):  # no Exif block at all
        (site / f"plain_{i}.jpg").write_bytes(data)
        os.utime(site / f"plain_{i}.jpg", (late + 1 + i, late + 1 + i))
    _write_exif(site / "bad_date.jpg", {"DateTimeOriginal": "2026:13:45 10:00:00"}, mtime=late, seed=9)
    reg = _registry(rt)
    survey = reg.register("dave", str(site), 1, None, SurveyOptions())
    assert len(scan(reg, survey, rt.jobs, ScanConfig(min_images=3, settle_s=0, gap_s=300))) == 2
    assert _job_sets(rt, "dave") == {_set_name(t): ["exif_0.jpg", "exif_1.jpg", "exif_2.jpg"],
                                     _set_name(late): ["bad_date.jpg", "plain_0.jpg", "plain_1.jpg"]}
    cached = reg.state(survey.id).exif_times
    assert [cached[n][2] for n in ("plain_0.jpg", "plain_1.jpg", "bad_date.jpg")] == [None, None, None]


def _image_file(root: Path, rel: str) -> ImageFile:
    st = (root / rel).stat()
    return ImageFile(rel, st.st_size, st.st_mtime, st.st_mtime_ns)


def test_exif_time_is_read_once_per_file_version(tmp_path: Path) -> None:
    t = float(int(time.time()) - 100_000)
    _write_exif(tmp_path / "a.jpg", {"DateTimeOriginal": "2026:05:01 10:00:00"}, mtime=t)
    _write_exif(tmp_path / "gone.jpg", {"DateTimeOriginal": "2026:05:01 10:00:01"}, mtime=t)
    _write_exif(tmp_path / "dive" / "b.jpg", {"DateTimeOriginal": "2026:05:01 10:00:02"}, mtime=t)
    cache: dict[str, tuple[int, int, float | None]] = {}
    first = with_exif_times(tmp_path, [_image_file(tmp_path, r) for r in ("a.jpg", "gone.jpg", "dive/b.jpg")], cache)
    ten = datetime(2026, 5, 1, 10, tzinfo=UTC).timestamp()
    assert [f.exif_time for f in first] == [ten, ten + 1, None]  # sub-folder images are not read
    assert sorted(cache) == ["a.jpg", "gone.jpg"]

    a = tmp_path / "a.jpg"  # the same size and mtime_ns, another date inside: the cached time is kept
    st = a.stat()
    a.write_bytes(a.read_bytes().replace(b"2026:05:01 10:00:00", b"2026:05:01 11:00:00"))
    os.utime(a, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert read_exif_time(a) == ten + 3600
    (tmp_path / "gone.jpg").unlink()
    assert [f.exif_time for f in with_exif_times(tmp_path, [_image_file(tmp_path, "a.jpg")], cache)] == [ten]
    assert sorted(cache) == ["a.jpg"]
    os.utime(a, (t + 1, t + 1))  # a new mtime: read again
    assert [f.exif_time for f in with_exif_times(tmp_path, [_image_file(tmp_path, "a.jpg")], cache)] == [ten + 3600]


def test_read_exif_time_formats_and_damaged_headers(tmp_path: Path) -> None:
    ten = datetime(2026, 5, 1, 10, tzinfo=UTC).timestamp()
    for suffix in (".jpg", ".tif", ".png"):
        _write_exif(tmp_path / f"x{suffix}", {"DateTimeOriginal": "2026:05:01 12:00:00", "SubsecTimeOriginal": "5",
                                              "OffsetTimeOriginal": "+02:00"}, mtime=ten)
        assert read_exif_time(tmp_path / f"x{suffix}") == ten + 0.5, suffix
    for name, stamp in (("zero.jpg", "0000:00:00 00:00:00"), ("text.jpg", "not a date"),
                        ("early.jpg", "1969:12:31 23:59:59")):
        _write_exif(tmp_path / name, {"DateTimeOriginal": stamp}, mtime=ten)
        assert read_exif_time(tmp_path / name) is None, name
    (tmp_path / "plain.jpg").write_bytes(small_jpegs(1)[0])
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "x.jpg").read_bytes()[:40])  # ends inside the Exif block
    (tmp_path / "notes.jpg").write_text("not an image")
    assert [read_exif_time(tmp_path / n) for n in ("plain.jpg", "cut.jpg", "notes.jpg")] == [None, None, None]


def test_surveys_file_entries_with_bad_options_are_skipped(tmp_path: Path) -> None:
    root = tmp_path / "roots"
    for name in ("ok", "too-long", "bad-mode"):
        (root / name).mkdir(parents=True)
    conf = tmp_path / "surveys.toml"
    entries = [(root / "ok", ""), (root / "too-long", "iterations = 500"), (root / "bad-mode", 'mode = "nerf"')]
    conf.write_text("".join(f'[[survey]]\npath = "{p}"\nowner = "a"\n[survey.options]\n{o}\n' for p, o in entries))
    reg = SurveyRegistry(tmp_path / "surveys", [root], conf, 1.0, max_iterations=100)
    assert [s.name for s in reg.from_config()] == ["ok"]
    with pytest.raises(SurveyError, match="iterations: at most 100") as e:
        reg.register("a", str(root / "too-long"), 60, None, SurveyOptions(iterations=500))
    assert e.value.code == "invalid_options" and reg.all() == reg.from_config()


def test_owner_roots_and_first_claims(tmp_path: Path) -> None:
    """Issue 13, item 1: shared roots are first come, first served per folder; an owner's own roots are closed to
    everyone else; the surveys file cannot hand another owner's folder over."""
    root = tmp_path / "roots"
    for name in ("alice-only/site", "shared/a", "shared/b", "shared/b/inner"):
        (root / name).mkdir(parents=True)
    conf = tmp_path / "surveys.toml"
    conf.write_text(f'[[survey]]\npath = "{root / "shared/b/inner"}"\nowner = "bob"\n')
    reg = SurveyRegistry(tmp_path / "surveys", [root / "shared", root / "alice-only"], conf, 1.0,
                         owner_roots={"alice": [root / "alice-only"]})
    with pytest.raises(SurveyError) as e:
        reg.register("bob", str(root / "alice-only/site"), 60, None, SurveyOptions())
    assert e.value.code == "path_not_allowed"
    assert reg.register("alice", str(root / "alice-only/site"), 60, None, SurveyOptions()).owner == "alice"
    a = reg.register("alice", str(root / "shared/a"), 60, None, SurveyOptions())
    conf.write_text(conf.read_text() + f'[[survey]]\npath = "{root / "shared/a"}"\nowner = "carol"\n')
    # carol's surveys-file entry, added after alice registered that folder, is left out; bob's entry stays
    assert sorted((s.owner, Path(s.path).name) for s in reg.all() if s.origin == "config") == [("bob", "inner")]
    for owner, folder in (("bob", "shared/a"), ("alice", "shared/b"), ("alice", "shared/b/inner")):
        with pytest.raises(SurveyError) as e:
            reg.register(owner, str(root / folder), 60, None, SurveyOptions())
        assert e.value.code == "path_taken", (owner, folder)
    # at scan time the folder is checked again: replaced by a link, it is refused before anything is read
    assert reg.check_folder(a) == (root / "shared").resolve()
    (root / "shared/a").rename(root / "shared/a-old")
    (root / "shared/a").symlink_to(tmp_path)
    with pytest.raises(SurveyError) as e:
        reg.check_folder(a)
    assert e.value.code == "path_changed"
