"""service.storage against the real object store (SeaweedFS, tests/service/object_server.py): what a pull or a
push moves, and the job store whose manifests and files live in the store."""

from __future__ import annotations

import os
import uuid

import pytest
from svc_helpers import make_settings

from service.compose import job_store
from service.jobs.manifest import Manifest
from service.jobs.store import JobNotFound, JobStore, new_job_id
from service.storage.jobs import SyncedJobStore
from service.storage.mirror import FolderMirror, travels
from service.storage.objects import ObjectStore

BUCKET = "dualphys-unit"


@pytest.fixture()
def objects(object_server):
    from object_server import ACCESS_KEY, SECRET_KEY

    store = ObjectStore(object_server.url, BUCKET, f"unit-{uuid.uuid4().hex[:8]}", ACCESS_KEY, SECRET_KEY)
    store.ensure_bucket()
    yield store
    store.delete_prefix("")


def test_what_travels() -> None:
    assert travels("train/latest.pt") and travels(".stages/train.json") and travels("output/renders/a/b.png")
    assert not travels("train/latest.pt.tmp")  # the trainer's checkpoint while it is written
    assert not travels(".stages/.train.json.abc")  # an atomic write's temp file
    assert not travels(".sync.json") and not travels(".artifacts.json") and not travels(".previews/original/a.jpg")


def test_push_and_pull_move_only_what_changed(objects, tmp_path) -> None:
    a = FolderMirror(objects, "jobs/x/", tmp_path / "a")
    b = FolderMirror(objects, "jobs/x/", tmp_path / "b")
    (tmp_path / "a" / "train").mkdir(parents=True)
    (tmp_path / "a" / "train" / "latest.pt").write_bytes(b"1" * 1000)
    (tmp_path / "a" / "log.txt").write_text("one\n")
    (tmp_path / "a" / "train" / "latest.pt.tmp").write_bytes(b"half")
    assert a.push() == (2, 0)
    assert a.push() == (0, 0)  # nothing changed
    assert b.pull() == (2, 0) and (tmp_path / "b" / "train" / "latest.pt").read_bytes() == b"1" * 1000
    assert not (tmp_path / "b" / "train" / "latest.pt.tmp").exists()
    assert b.pull() == (0, 0)
    # b changes one file and removes the other: a push sends one and deletes one; a's pull follows
    with open(tmp_path / "b" / "log.txt", "a") as f:
        f.write("two\n")
    (tmp_path / "b" / "train" / "latest.pt").unlink()
    assert b.push() == (1, 1)
    assert set(objects.list("jobs/x/")) == {"jobs/x/log.txt"}
    assert a.pull() == (1, 1)
    assert (tmp_path / "a" / "log.txt").read_text() == "one\ntwo\n"
    assert not (tmp_path / "a" / "train" / "latest.pt").exists()
    # a file touched here since the last sync is fetched again even if the store did not change
    (tmp_path / "a" / "log.txt").write_text("local edit\n")
    os.utime(tmp_path / "a" / "log.txt", ns=(1, 1))
    assert a.pull() == (1, 0) and (tmp_path / "a" / "log.txt").read_text() == "one\ntwo\n"
    # a pull of a prefix the store does not have makes no folder
    assert FolderMirror(objects, "jobs/none/", tmp_path / "c").pull() == (0, 0) and not (tmp_path / "c").exists()


def _manifest(job_id: str) -> Manifest:
    return Manifest(id=job_id, owner="alice", created_at=1.0, updated_at=1.0, run_id="r1", options={}, source={})


def test_the_synced_store_keeps_manifests_and_files_in_the_object_store(objects, tmp_path) -> None:
    api, worker = SyncedJobStore(tmp_path / "api" / "jobs", objects), SyncedJobStore(tmp_path / "w" / "jobs", objects)
    api.ensure()
    jid = new_job_id()
    api.job_dir(jid).mkdir()
    (api.layout(jid).images).mkdir()
    (api.layout(jid).images / "a.png").write_bytes(b"png")
    api.layout(jid).marker("ingest").parent.mkdir()
    api.layout(jid).marker("ingest").write_text("{}")
    api.write(_manifest(jid))  # pushes the folder, then the manifest
    assert worker.exists(jid) and worker.read(jid).owner == "alice"
    assert not worker.job_dir(jid).exists()  # reading the manifest fetches no file
    (api.layout(jid).input).mkdir()
    api.layout(jid).upload.write_bytes(b"zip")
    api.write(api.read(jid))
    worker.pull(jid, "sfm")  # the upload only travels to ingest
    assert not worker.layout(jid).input.exists()
    worker.pull(jid, "ingest")
    assert worker.layout(jid).upload.read_bytes() == b"zip"
    assert (worker.layout(jid).images / "a.png").read_bytes() == b"png"
    assert worker.layout(jid).marker("ingest").is_file()
    # the worker's checkpoint and results reach the store with its next manifest write; the API mirrors what it
    # serves and never the checkpoint
    worker.layout(jid).train.mkdir()
    worker.layout(jid).checkpoint.write_bytes(b"ckpt")
    worker.layout(jid).train_result.write_text('{"iterations": 3}')
    m = worker.read(jid)
    m.message = "train done"
    worker.write(m)
    assert api.read(jid).message == "train done"
    assert api.mirror(jid) == api.job_dir(jid)
    assert api.layout(jid).train_result.read_text() == '{"iterations": 3}' and not api.layout(jid).checkpoint.exists()
    # the log: every appender starts from the store's copy
    api.append_log(jid, "from the API")
    worker.append_log(jid, "from a worker")
    text, _, _ = api.read_log(jid, 0, 1 << 20)
    assert [line.split(" ", 1)[1] for line in text.splitlines()] == ["from the API", "from a worker"]
    assert [x.id for x in worker.list()] == [jid]
    api.remove(jid)
    assert objects.list(f"jobs/{jid}/") == {} and not api.job_dir(jid).exists()
    with pytest.raises(JobNotFound):
        worker.read(jid)
    assert worker.list() == []


def test_without_an_object_store_the_data_folder_is_the_store(tmp_path, unit_prefix) -> None:
    store = job_store(make_settings(tmp_path, unit_prefix))
    assert type(store) is JobStore and store.reachable() is None
    # Compose hands ``${DUALPHYS_OBJECT_STORE_URL:-}`` over as an empty string: the same as unset
    empty = make_settings(tmp_path, unit_prefix, object_store_url="", object_store_access_key="")
    assert empty.object_store_url is None and empty.object_store_access_key is None
    assert type(job_store(empty)) is JobStore
    assert type(job_store(make_settings(tmp_path, unit_prefix, object_store_url="http://127.0.0.1:1"))) \
        is SyncedJobStore


def test_ready_reports_the_object_store(object_server, tmp_path, unit_prefix) -> None:
    from fastapi.testclient import TestClient
    from object_server import ACCESS_KEY, SECRET_KEY

    from service.app import create_app

    store = dict(object_store_bucket=BUCKET, object_store_access_key=ACCESS_KEY, object_store_secret_key=SECRET_KEY)
    up = make_settings(tmp_path / "up", unit_prefix, object_store_url=object_server.url, **store)
    with TestClient(create_app(up)) as c:
        r = c.get("/ready")
        assert r.status_code == 200 and r.json()["object_store"] is True, r.json()
    from svc_helpers import free_port

    down = make_settings(tmp_path / "down", unit_prefix, object_store_url=f"http://127.0.0.1:{free_port()}", **store)
    with TestClient(create_app(down)) as c:  # starts without its store
        r = c.get("/ready")
        assert r.status_code == 503 and r.json()["object_store"] is False
        assert r.json()["error"]["code"] == "not_ready" and "object store" in r.json()["error"]["message"]
    with TestClient(create_app(make_settings(tmp_path / "none", unit_prefix))) as c:
        assert c.get("/ready").json()["object_store"] is None
