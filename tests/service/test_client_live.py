"""`dualphys submit / status / jobs / download / cancel` against the live stack (real uvicorn, Celery prefork
worker, Redis; conftest.py): one tiny job goes through it — the scene's folder, zipped while it uploads, with
--wait — and everything else reads that job or stops before a worker runs anything."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from svc_helpers import KEYS, METRICS, small_jpegs, zip_bytes

from cli.main import main
from service.client.cli import KEY_ENV, SERVER_ENV
from service.client.download import NET_CHUNK, download_artifact
from service.client.remote import ServiceClient

pytestmark = pytest.mark.slow


def run(*argv: str) -> tuple[int, str, str]:
    """The command in this process: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(argv))
    return rc, out.getvalue(), err.getvalue()


def last_json(text: str):
    return json.loads(text.strip().splitlines()[-1])


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def remote(live) -> list[str]:
    """--server and alice's --key."""
    return ["--server", live.url, "--key", KEYS["alice"]]


@pytest.fixture(scope="module")
def done_job(live, remote, scene_images) -> dict:
    """The module's one job: the generated scene's folder through `dualphys submit --wait`."""
    live.ensure_worker()
    folder = scene_images[0].parent
    t0 = time.monotonic()
    rc, out, err = run("submit", str(folder), "--wait", "--interval", "0.5", "--preset", "fast",
                       "--iterations", "60", *remote)
    seconds = time.monotonic() - t0
    METRICS["client submit --wait (12 views, 60 iterations)"] = f"{seconds:.1f} s"
    return {"rc": rc, "out": out, "err": err, "status": last_json(out), "folder": folder, "seconds": seconds}


@pytest.fixture(scope="module")
def alice(live) -> Iterator[ServiceClient]:
    with ServiceClient(live.url, KEYS["alice"]) as c:
        yield c


@pytest.mark.timeout(600)  # the scene is generated on first use (the session fixture): minutes on a busy machine
def test_submit_a_folder_and_wait_until_done(done_job, alice) -> None:
    assert done_job["rc"] == 0, done_job["err"]
    st = done_job["status"]
    assert st["state"] == "done" and st["progress"] == 100.0 and st["error"] is None
    job = alice.job(st["id"])
    assert job["source"]["filename"] == f"{done_job['folder'].name}.zip"
    assert job["ingest"]["images"] == len(list(done_job["folder"].glob("*.png"))) == 12
    assert job["options"]["iterations"] == 60 and job["options"]["preset"] == "fast"
    # not a terminal: one line per stage change instead of a bar
    assert f"{st['id']}: running train" in done_job["err"] and f"{st['id']}: done" in done_job["err"]


@pytest.mark.timeout(120)
def test_status_and_jobs(done_job, remote, live, monkeypatch) -> None:
    jid = done_job["status"]["id"]
    rc, out, _ = run("status", jid, *remote)
    assert rc == 0 and last_json(out)["state"] == "done"
    rc, out, _ = run("status", jid, "--full", *remote)
    assert rc == 0 and [s["name"] for s in last_json(out)["stages"]][0] == "ingest"
    rc, out, _ = run("status", jid, "--wait", *remote)  # already ended: returns at once, exit code of done
    assert rc == 0
    # server and key from the environment
    monkeypatch.setenv(SERVER_ENV, live.url)
    monkeypatch.setenv(KEY_ENV, KEYS["alice"])
    rc, out, _ = run("jobs", "--json")
    assert rc == 0 and jid in [j["id"] for j in last_json(out)]
    rc, out, _ = run("jobs", "--status", "done")
    assert rc == 0 and any(line.startswith(jid) and " done " in line for line in out.splitlines())


@pytest.mark.timeout(120)
def test_download_everything_verified_then_nothing_again(done_job, remote, alice, tmp_path) -> None:
    jid = done_job["status"]["id"]
    arts = alice.artifacts(jid)
    assert any(a.path == "output/reconstruction.ply" for a in arts) and any("restored/" in a.path for a in arts)
    t0 = time.monotonic()
    rc, out, err = run("download", jid, "--out", str(tmp_path), *remote)
    METRICS["client download (all artifacts)"] = f"{sum(a.size for a in arts)} bytes in {time.monotonic() - t0:.2f} s"
    assert rc == 0, err
    summary = last_json(out)
    assert summary["files"] == len(arts) and summary["fetched"] == summary["bytes"] == sum(a.size for a in arts)
    for a in arts:
        assert sha256(tmp_path / a.path) == a.sha256, a.path
    assert not list(tmp_path.rglob("*.part"))
    rc, out, _ = run("download", jid, "--out", str(tmp_path), *remote)
    again = last_json(out)
    assert rc == 0 and again["fetched"] == 0 and again["skipped"] == len(arts)
    # selected artifacts only, and the bundle
    rc, out, _ = run("download", jid, "--out", str(tmp_path / "sel"), "--only", "*.ply", "--only", "report.json",
                     *remote)
    assert rc == 0 and last_json(out)["files"] == 1 + sum(a.path.endswith("report.json") for a in arts)
    assert sha256(tmp_path / "sel" / "output" / "reconstruction.ply") == next(
        a.sha256 for a in arts if a.path == "output/reconstruction.ply")
    rc, out, _ = run("download", jid, "--out", str(tmp_path / "sel"), "--only", "no-such-*", *remote)
    assert rc == 1
    rc, out, _ = run("download", jid, "--bundle", "--out", str(tmp_path / "b"), *remote)
    with zipfile.ZipFile(tmp_path / "b" / f"{jid}.zip") as z:
        assert sorted(z.namelist()) == sorted(a.path for a in arts)


@pytest.mark.timeout(120)
def test_an_interrupted_download_resumes_with_a_range(done_job, remote, alice, tmp_path) -> None:
    jid = done_job["status"]["id"]
    big = max(alice.artifacts(jid), key=lambda a: a.size)  # the largest (the tiny job's PLY is ~50 kB)
    assert big.size > 2 * NET_CHUNK, big.size  # room to stop after the first piece

    class Stop(Exception):
        pass

    def stop_after_first_piece(n: int) -> None:
        raise Stop

    # 1. a transfer broken off midway leaves <path>.part with what arrived
    with pytest.raises(Stop):
        download_artifact(alice, big, tmp_path, on_bytes=stop_after_first_piece)
    part = tmp_path / f"{big.path}.part"
    kept = part.stat().st_size
    assert kept == NET_CHUNK and not (tmp_path / big.path).exists()
    # 2. the command run again asks for the rest (Range: bytes=<kept>-) and gets only that (206)
    rc, out, err = run("download", jid, "--out", str(tmp_path), "--only", big.path, *remote)
    assert rc == 0, err
    summary = last_json(out)
    assert summary["resumed"] == [big.path] and summary["fetched"] == big.size - kept
    assert sha256(tmp_path / big.path) == big.sha256 and not part.exists()
    METRICS["client resumed download"] = f"{big.path}: {kept} bytes kept, {summary['fetched']} fetched of {big.size}"
    # 3. a .part that is not a prefix of the file (another version): the resume fails its checksum, the whole
    # file is fetched once more and verifies
    (tmp_path / big.path).unlink()
    part.write_bytes(b"\0" * 1000)
    res = download_artifact(alice, big, tmp_path)
    assert res.verified and res.fetched == (big.size - 1000) + big.size and res.resumed_from == 0
    assert sha256(tmp_path / big.path) == big.sha256


@pytest.mark.timeout(120)
def test_wrong_key_unknown_job_and_another_owners_job(done_job, live) -> None:
    jid = done_job["status"]["id"]
    wrong = "wrong-key-0123456789abcdef"
    rc, out, err = run("jobs", "--server", live.url, "--key", wrong)
    assert rc == 1 and out == ""
    assert "the server refused the API key (unauthorized: unknown API key); check --key or DUALPHYS_KEY" in err
    assert wrong not in err
    rc, _, err = run("submit", str(done_job["folder"]), "--server", live.url, "--key", wrong)  # before uploading
    assert rc == 1 and "the server refused the API key" in err
    rc, _, err = run("status", "j-no-such-job", "--server", live.url, "--key", KEYS["alice"])
    assert rc == 1 and f"no job j-no-such-job on {live.url} for this key (job_not_found)" in err
    for cmd in (["status", jid], ["download", jid], ["cancel", jid]):  # bob cannot see alice's job
        rc, _, err = run(*cmd, "--server", live.url, "--key", KEYS["bob"])
        assert rc == 1 and f"no job {jid}" in err, (cmd, err)


@pytest.mark.timeout(180)
def test_cancel(done_job, remote, alice, tmp_path) -> None:
    """A finished job cannot be cancelled (409, exit 1); an archive sent as is, cancelled at once, ends
    cancelled (exit 4 with --wait). The worker is busy with nothing else, so the cancel is usually immediate;
    three tiny images make SfM fail fast if a stage starts first."""
    rc, _, err = run("cancel", done_job["status"]["id"], *remote)
    assert rc == 1 and "(job_finished, HTTP 409)" in err
    archive = tmp_path / "three.zip"
    archive.write_bytes(zip_bytes({f"{i}.jpg": b for i, b in enumerate(small_jpegs(3))}))
    rc, out, err = run("submit", str(archive), *remote)
    assert rc == 0, err
    jid = last_json(out)["id"]
    assert alice.job(jid)["source"]["filename"] == "three.zip"
    rc, out, err = run("cancel", jid, "--wait", "--interval", "0.2", *remote)
    final = last_json(out)
    assert final["state"] in ("cancelled", "failed")  # failed only when SfM refused the set before the cancel
    assert rc == {"cancelled": 4, "failed": 3}[final["state"]]
    assert f"job {jid} {final['state']}" in err
