"""Issue 44 items 4-5: workers on many hosts with no shared disk, through a real object store.

The API and three Celery workers each have their own data folder; the only things they share are Redis and the
object store (SeaweedFS, tests/service/object_server.py). The workers play the survey team's hosts: a CPU box
(queue ``cpu``: every stage but training) and two training boxes (queue ``gpu``, ``train_queue=gpu``; the
device stays ``cpu`` here). One training box is killed (kill -9 of its process group) after a checkpoint
reached the store; the other resumes it from there. The results download from the API and equal a one-host run.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import time
import zipfile

import pytest
from svc_helpers import METRICS, job_log, upload, wait_for, wait_job

from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions
from pipeline.job.runner import run_job
from service.jobs.artifacts import list_artifacts

pytestmark = pytest.mark.slow

ITERATIONS = 400  # the fast preset checkpoints every 80: a checkpoint reaches the store well before the end
BUCKET = "dualphys-test"  # the ``hosts`` fixture's (tests/service/conftest.py)
TIMINGS = {"seconds", "render_ms", "elapsed_s", "timings"}  # wall-clock fields: never equal between two runs


def untimed(obj):
    if isinstance(obj, dict):
        return {k: untimed(v) for k, v in obj.items() if k not in TIMINGS}
    if isinstance(obj, list):
        return [untimed(v) for v in obj]
    return obj


def ran_here(stack, host: str, job_id: str) -> list[str]:
    """The stages the host's worker started for the job (its own log, not the job's)."""
    text = stack.procs[host].log_path.read_text(errors="replace")
    return re.findall(rf"job {job_id}: stage (\w+) started", text)


def stored(object_server, prefix: str, job_id: str) -> dict[str, int]:
    s3 = object_server.client()
    keys = {}
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=f"{prefix}/jobs/{job_id}/"):
        keys.update({o["Key"].split(f"/jobs/{job_id}/", 1)[1]: o["Size"] for o in page.get("Contents", [])})
    return keys


def stored_checkpoint_iteration(object_server, prefix: str, job_id: str) -> int | None:
    import torch

    s3 = object_server.client()
    try:
        body = s3.get_object(Bucket=BUCKET, Key=f"{prefix}/jobs/{job_id}/train/latest.pt")["Body"].read()
    except s3.exceptions.NoSuchKey:
        return None
    return int(torch.load(io.BytesIO(body), map_location="cpu", weights_only=True)["iteration"])


@pytest.mark.timeout(600)
def test_stages_on_three_hosts_with_a_kill_resume_from_the_object_store(hosts, object_server, scene_zip,
                                                                        tmp_path) -> None:
    stack, c = hosts, hosts.client("alice")
    t0 = time.monotonic()
    r = upload(c, scene_zip, iterations=ITERATIONS, preset="fast")
    assert r.status_code == 201, r.text
    jid = r.json()["id"]

    # training starts on one of the two training boxes; wait for one of its checkpoints to reach the store
    trainer = wait_for("a training host", lambda: next((h for h in ("train-a", "train-b")
                                                        if ran_here(stack, h, jid)), None), timeout=240)
    other = "train-b" if trainer == "train-a" else "train-a"
    ckpt = wait_for("a checkpoint in the object store",
                    lambda: stored_checkpoint_iteration(object_server, stack.prefix, jid), timeout=240, interval=0.2)
    assert 0 < ckpt < ITERATIONS
    assert wait_job(c, jid, {"running", "done", "failed"}, timeout=5)["state"] == "running"
    stack.procs[trainer].kill9()
    killed_at = time.monotonic() - t0

    final = wait_job(c, jid, {"done", "failed", "cancelled"}, timeout=400)
    assert final["state"] == "done", final
    seconds = time.monotonic() - t0
    stages = {s["name"]: s for s in final["stages"]}
    assert final["completed_runs"] == 1 and [r["outcome"] for r in final["runs"]] == ["done"]
    assert [(a["attempt"], a["outcome"]) for a in stages["train"]["history"]] == [(1, "worker_lost"), (2, "done")]
    assert all(s["status"] == "done" for s in final["stages"])

    # where each stage ran: ingest in the API, training on both training boxes (killed, then resumed), the
    # rest on the CPU box; every host has only its own folder
    cpu_stages = [s for s in stages if s not in ("ingest", "train")]
    assert sorted(ran_here(stack, "cpu-box", jid)) == sorted(cpu_stages)
    assert ran_here(stack, trainer, jid) == ["train"] and ran_here(stack, other, jid) == ["train"]
    api_job = JobLayout(stack.data_dir / "jobs" / jid)
    trainer_job = JobLayout(stack.root / f"{trainer}-data" / "jobs" / jid)
    other_job = JobLayout(stack.root / f"{other}-data" / "jobs" / jid)
    cpu_job = JobLayout(stack.root / "cpu-box-data" / "jobs" / jid)
    assert not api_job.checkpoint.exists() and not api_job.scene.exists()  # the API never held the stages' files
    assert trainer_job.checkpoint.is_file() and not trainer_job.ply.exists()  # the killed box never exported
    assert other_job.checkpoint.is_file() and not other_job.ply.exists()
    assert cpu_job.ply.is_file()
    # the resumed box started from the checkpoint that was in the store when the first one died
    log = job_log(c, jid)
    resumed = [int(x) for x in re.findall(r"resumed from \S+ at iteration (\d+)", log)]
    assert len(resumed) == 1 and ckpt <= resumed[0] < ITERATIONS, log[-3000:]
    # the store holds the job: manifest, log, markers, the checkpoint, the results
    keys = stored(object_server, stack.prefix, jid)
    assert {"manifest.json", "log.txt", "input/archive", "train/latest.pt", "output/reconstruction.ply"} <= set(keys)
    assert {f".stages/{s}.json" for s in stages} <= set(keys)

    # downloads from the API (its mirror of the store): the PLY, the report, the bundle
    arts = c.get(f"/v1/jobs/{jid}/artifacts").json()["artifacts"]
    by_path = {a["path"]: a for a in arts}
    ply = c.get(by_path["output/reconstruction.ply"]["url"])
    assert ply.status_code == 200 and hashlib.sha256(ply.content).hexdigest() == \
        by_path["output/reconstruction.ply"]["sha256"]
    assert len(ply.content) == keys["output/reconstruction.ply"]
    part = c.get(by_path["output/reconstruction.ply"]["url"], headers={"Range": "bytes=10-109"})
    assert part.status_code == 206 and part.content == ply.content[10:110]
    report = c.get(by_path["output/report.json"]["url"]).json()
    assert report["metrics"]["test"]["psnr"] > 10
    bundle = c.get(f"/v1/jobs/{jid}/bundle")
    with zipfile.ZipFile(io.BytesIO(bundle.content)) as z:
        assert sorted(z.namelist()) == sorted(by_path) and z.read("output/reconstruction.ply") == ply.content

    # the same job on one host, straight through (no kill): the same results
    ref = tmp_path / "one-host"
    (tmp_path / "set.zip").write_bytes(scene_zip)
    options = {**final["options"], "source": str(tmp_path / "set.zip")}
    t1 = time.monotonic()
    run_job(ref, JobOptions.from_json(options))
    ref_seconds = time.monotonic() - t1
    ref_arts = {a.path: a for a in list_artifacts(ref)}
    assert sorted(ref_arts) == sorted(by_path)
    ref_report = json.loads(JobLayout(ref).report_json.read_text())
    assert untimed(ref_report["metrics"]) == untimed(report["metrics"])
    assert ref_report["model"]["n_gaussians"] == report["model"]["n_gaussians"]
    evaluate = object_server.client().get_object(Bucket=BUCKET, Key=f"{stack.prefix}/jobs/{jid}/evaluate.json")
    assert untimed(json.loads(evaluate["Body"].read())) == untimed(json.loads(JobLayout(ref).evaluate.read_text()))
    same_ply = ref_arts["output/reconstruction.ply"].sha256 == by_path["output/reconstruction.ply"]["sha256"]
    METRICS["many hosts (12 views, 400 iterations, API + 3 workers, kill -9 mid-training)"] = (
        f"killed at {killed_at:.0f} s after upload (checkpoint {ckpt} in the store), resumed at {resumed[0]}, "
        f"done in {seconds:.0f} s; one-host straight run {ref_seconds:.0f} s; PLY bit-identical: {same_ply}; "
        f"stage seconds {[(s['name'], s['seconds']) for s in final['stages']]}")
    assert same_ply
