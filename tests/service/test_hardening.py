"""Issue 13 (service hardening) through the real API: uvicorn + a Celery worker + Redis (the ``live`` stack of
conftest.py; its survey sets need ``DUALPHYS_SURVEY_MIN_IMAGES=4`` images). The hostile-upload cases of the
issue (encrypted zips, ``./`` tars, over-long names, the ``file`` field) are in test_live.py's suite."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import pytest
from svc_helpers import job_log, job_status, small_jpegs, upload, wait_for, wait_job, zip_bytes

from pipeline.job.layout import JobLayout

pytestmark = pytest.mark.slow


def _write_set(folder: Path, n: int, seed: int, start: int = 0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, data in enumerate(small_jpegs(n, seed=seed)):
        (folder / f"frame_{start + i:03d}.jpg").write_bytes(data)


def _scan_and_wait(client, sid: str) -> dict:
    before = client.get(f"/v1/surveys/{sid}").json()["scans"]
    assert client.post(f"/v1/surveys/{sid}/scan").status_code == 202
    wait_for(f"a scan of {sid}", lambda: client.get(f"/v1/surveys/{sid}").json()["scans"] > before, timeout=60)
    return client.get(f"/v1/surveys/{sid}").json()


def _cancel_survey_jobs(client, sid: str) -> None:
    for j in client.get("/v1/jobs", params={"survey": sid, "limit": 200}).json()["jobs"]:
        if j["state"] in ("queued", "running"):
            client.post(f"/v1/jobs/{j['id']}/cancel")


def _files_under(root: Path) -> set[str]:
    return {p.name for p in root.rglob("*") if p.is_file()}


# ---------------------------------------------------------------- item 1: one owner per survey folder


@pytest.mark.timeout(120)
def test_a_survey_folder_has_one_owner(live) -> None:
    alice, bob = live.client("alice"), live.client("bob")
    site = live.survey_root / "owned-site"
    _write_set(site / "dive-01", 4, seed=500)
    r = alice.post("/v1/surveys", json={"path": str(site), "interval_s": 3600})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    # the same folder, a folder inside it, a folder around it (the root itself), by another key: refused
    for path in (site, site / "dive-01", live.survey_root, Path(str(site) + "/../owned-site")):
        r = bob.post("/v1/surveys", json={"path": str(path), "interval_s": 3600})
        assert r.status_code == 409 and r.json()["error"]["code"] == "path_taken", (path, r.text)
    # through a link that resolves to it: refused as well
    link = live.survey_root / "owned-site-link"
    link.symlink_to(site)
    r = bob.post("/v1/surveys", json={"path": str(link), "interval_s": 3600})
    assert r.status_code == 409 and r.json()["error"]["code"] == "path_taken"
    # alice's scan makes alice's job; bob sees no survey and no job of that folder
    got = _scan_and_wait(alice, sid)
    assert [s["name"] for s in got["sets"]] == ["dive-01"], got
    assert bob.get("/v1/surveys").json()["surveys"] == [] or all(
        s["path"] != str(site) for s in bob.get("/v1/surveys").json()["surveys"])
    bob_jobs = bob.get("/v1/jobs", params={"limit": 200}).json()["jobs"]
    assert not [j for j in bob_jobs if j["survey_id"] == sid]
    assert bob.get(f"/v1/surveys/{sid}").status_code == 404
    # alice may register another folder of her own next to it; the same folder twice is survey_exists
    assert alice.post("/v1/surveys", json={"path": str(site), "interval_s": 3600}).json()["error"]["code"] \
        == "survey_exists"
    _cancel_survey_jobs(alice, sid)
    assert alice.delete(f"/v1/surveys/{sid}").status_code == 204
    link.unlink()


# ---------------------------------------------------------------- item 2: the path is re-checked at every scan


@pytest.mark.timeout(120)
def test_survey_folder_swapped_for_a_link_after_registration_is_not_followed(live, tmp_path: Path) -> None:
    alice = live.client("alice")
    site = live.survey_root / "swapped-site"
    site.mkdir()
    r = alice.post("/v1/surveys", json={"path": str(site), "interval_s": 3600})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    outside = tmp_path / "outside"  # under no survey root
    _write_set(outside / "dive", 4, seed=600)
    _write_set(outside, 4, seed=610, start=10)
    marker = {f"frame_{i:03d}.jpg" for i in range(4)}
    site.rmdir()
    site.symlink_to(outside, target_is_directory=True)
    jobs_before = set(os.listdir(live.data_dir / "jobs"))
    try:
        got = _scan_and_wait(alice, sid)
        assert got["sets"] == [], got  # nothing from outside became a job
        assert alice.get("/v1/jobs", params={"survey": sid}).json()["total"] == 0
        assert got["last_error_code"] == "path_changed" and "link" in got["last_error"], got
        new_jobs = set(os.listdir(live.data_dir / "jobs")) - jobs_before
        assert not any(JobLayout(live.data_dir / "jobs" / j).input.exists() for j in new_jobs if
                       JobLayout(live.data_dir / "jobs" / j).manifest.exists()
                       and job_status(alice, j)["survey_id"] == sid)
        # the folder becomes a folder again, with a sub-folder that is a link to the outside: never entered
        site.unlink()
        site.mkdir()
        (site / "dive-link").symlink_to(outside / "dive", target_is_directory=True)
        _write_set(site / "real-dive", 4, seed=620)
        got = _scan_and_wait(alice, sid)
        assert got["last_error"] is None and [s["name"] for s in got["sets"]] == ["real-dive"], got
        (job,) = alice.get("/v1/jobs", params={"survey": sid}).json()["jobs"]
        copied = JobLayout(live.data_dir / "jobs" / job["id"]).input
        assert sorted(_files_under(copied)) == sorted(marker)
        assert all(p.resolve().is_relative_to((live.data_dir / "jobs" / job["id"]).resolve())
                   for p in copied.rglob("*"))
    finally:
        _cancel_survey_jobs(alice, sid)
        if site.is_symlink():
            site.unlink()


# ---------------------------------------------------------------- item 3: no server paths in status or log


@pytest.mark.timeout(180)
def test_stage_errors_and_the_job_log_carry_no_server_paths(live) -> None:
    live.ensure_worker()
    c = live.client("alice")
    r = upload(c, zip_bytes({f"dive/{i}.jpg": b for i, b in enumerate(small_jpegs(4, seed=700))}))
    assert r.status_code == 201, r.text
    jid = r.json()["id"]
    final = wait_job(c, jid, {"failed", "done", "cancelled"}, timeout=150)
    assert final["state"] == "failed" and final["error"]["stage"] == "sfm", final  # random noise: no model
    assert final["error"]["message"] and str(live.root) not in final["error"]["message"], final["error"]
    assert "images" in final["error"]["message"]  # named relative to the job
    log = job_log(c, jid)
    assert "sfm" in log and str(live.root) not in log and "Traceback" not in log, log[-2000:]
    ingest_json = c.get(f"/v1/jobs/{jid}/artifacts/ingest.json").json()
    assert ingest_json["source"] == "input/archive"


# ---------------------------------------------------------------- item 10: survey jobs tell the truth


@pytest.mark.timeout(240)
def test_survey_jobs_show_ingest_distinct_names_and_small_sets_wait(live) -> None:
    live.ensure_worker()
    alice = live.client("alice")
    site = live.survey_root / "growing-site"
    _write_set(site / "dive-01", 4, seed=800)
    _write_set(site / "dive-02", 3, seed=810)  # below DUALPHYS_SURVEY_MIN_IMAGES=4
    sid = alice.post("/v1/surveys", json={"path": str(site), "interval_s": 3600}).json()["id"]
    try:
        got = _scan_and_wait(alice, sid)
        assert [s["name"] for s in got["sets"]] == ["dive-01"]
        assert [(w["name"], w["images"]) for w in got["waiting"]] == [("dive-02", 3)]
        assert got["waiting"][0]["reason"].startswith("too_few_images")
        (first,) = alice.get("/v1/jobs", params={"survey": sid}).json()["jobs"]

        def ingested():
            s = job_status(alice, first["id"])
            done = next(x for x in s["stages"] if x["name"] == "ingest")["status"] == "done"
            return s if done and s["state"] != "queued" else None

        s = wait_for("the survey job's ingest", ingested, timeout=120)
        assert s["ingest"] is not None and s["ingest"]["images"] == 4, s
        # the folder grows: the grown set is a new job with a name of its own
        _write_set(site / "dive-01", 1, seed=820, start=4)
        time.sleep(0.05)
        got = _scan_and_wait(alice, sid)
        assert sorted(x["name"] for x in got["sets"]) == ["dive-01", "dive-01 (2)"], got
        names = sorted(j["source"]["set"] for j in alice.get("/v1/jobs", params={"survey": sid}).json()["jobs"])
        assert names == ["dive-01", "dive-01 (2)"]
    finally:
        _cancel_survey_jobs(alice, sid)
        shutil.rmtree(site, ignore_errors=True)


# ---------------------------------------------------------------- item 8: idempotency keys


@pytest.mark.timeout(120)
def test_idempotency_key_checks_the_request_and_survives_redis_losing_it(live, redis_client) -> None:
    c = live.client("alice")
    archive = zip_bytes({f"{i}.jpg": b for i, b in enumerate(small_jpegs(4, seed=900))})
    other = zip_bytes({f"{i}.jpg": b for i, b in enumerate(small_jpegs(4, seed=910))})
    key = {"Idempotency-Key": f"nightly-{time.time_ns()}"}
    first = upload(c, archive, headers=key, preset="fast")
    assert first.status_code == 201, first.text
    jid = first.json()["id"]
    c.post(f"/v1/jobs/{jid}/cancel")
    total = c.get("/v1/jobs", params={"limit": 1}).json()["total"]
    again = upload(c, archive, headers=key, preset="fast")
    assert again.status_code == 200 and again.json()["id"] == jid
    for r in (upload(c, other, headers=key, preset="fast"), upload(c, archive, headers=key, preset="balanced")):
        assert r.status_code == 422 and r.json()["error"]["code"] == "idempotency_key_reused", r.text
        assert jid in r.json()["error"]["message"]
    # Redis loses its data (here: the key's entry): the record kept with the jobs on disk still answers
    lost = [k for k in redis_client.scan_iter(match=f"{live.prefix}:idem:*")]
    assert lost
    redis_client.delete(*lost)
    after = upload(c, archive, headers=key, preset="fast")
    assert after.status_code == 200 and after.json()["id"] == jid, after.text
    assert c.get("/v1/jobs", params={"limit": 1}).json()["total"] == total
    assert not [p for p in (live.data_dir / "jobs").iterdir() if not JobLayout(p).manifest.exists()
                and p.name.startswith("j")]  # the repeats' bodies were not kept
