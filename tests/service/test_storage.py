"""service.storage against the real object store (SeaweedFS, tests/service/object_server.py): what a pull or a
push moves, and the job store whose manifests and files live in the store."""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
import uuid

import pytest
from svc_helpers import free_port, make_settings

from service.compose import compose, job_store
from service.jobs.manifest import Manifest
from service.jobs.store import JobNotFound, JobStore, StoreUnavailable, new_job_id
from service.storage.jobs import SyncedJobStore
from service.storage.mirror import FolderMirror, travels
from service.storage.objects import ObjectStore
from worker.runner import ProgressReporter, when_redis_answers

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


class Gate:
    """A TCP forwarder on a free local port in front of the object server, to cut the store off mid-job and bring
    it back (``down``: the listener and every open connection closed, so clients see refused connections)."""

    def __init__(self, target: str):
        host, port = target.rsplit("//", 1)[1].split(":")
        self.target = (host, int(port))
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self._conns: list[socket.socket] = []
        self._listener: socket.socket | None = None

    def up(self) -> None:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", self.port))
        s.listen(16)
        self._listener = s
        threading.Thread(target=self._accept, args=(s,), daemon=True).start()

    def down(self) -> None:
        if self._listener is not None:
            with contextlib.suppress(OSError):
                self._listener.shutdown(socket.SHUT_RDWR)  # wakes the accept (a bare close leaves it listening)
            self._listener.close()
            self._listener = None
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
            c.close()
        self._conns.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return  # closed: down()
            server = socket.create_connection(self.target)
            self._conns += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(a: socket.socket, b: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := a.recv(65536):
                b.sendall(data)
        with contextlib.suppress(OSError):
            b.shutdown(socket.SHUT_WR)


def test_an_object_store_outage_is_waited_out_not_a_failed_stage(object_server, tmp_path, unit_prefix) -> None:
    """The store away mid-stage: a progress write is skipped (the stage goes on), the stage's end waits for the store
    and lands once it is back, a reader gets StoreUnavailable (the API's 503 object_store_unavailable)."""
    from object_server import ACCESS_KEY, SECRET_KEY

    gate = Gate(object_server.url)
    gate.up()
    prefix = f"outage-{uuid.uuid4().hex[:8]}"
    settings = make_settings(tmp_path / "data", f"{unit_prefix}-{prefix}", object_store_url=gate.url,
                             object_store_bucket=BUCKET, object_store_prefix=prefix,
                             object_store_access_key=ACCESS_KEY, object_store_secret_key=SECRET_KEY,
                             redis_outage_wait_s=60)
    rt = compose(settings, None)
    try:
        rt.store.ensure()
        jid = new_job_id()
        rt.store.job_dir(jid).mkdir(parents=True)
        m = _manifest(jid)
        m.state = "running"
        rt.store.write(m)
        reporter = ProgressReporter(rt, jid, m.run_id, ("ingest", "train"), {"ingest"}, floor=0.0)
        reporter._manifest_at = 0.0
        reporter("train", 0.5, "iteration 5/10")  # written through the store
        assert rt.store.read(jid).message == "iteration 5/10"

        gate.down()
        with pytest.raises(StoreUnavailable):
            rt.store.read(jid)
        reporter._manifest_at = 0.0
        reporter("train", 0.6, "iteration 6/10")  # skipped, not raised: the stage goes on
        assert reporter.store_away

        # the stage's end: waits (with backoff) while the store is away, lands once it is back
        def end() -> str:
            got = rt.store.read(jid)
            got.message = "train done"
            rt.store.write(got)
            return "recorded"

        threading.Timer(3.0, gate.up).start()
        t0 = time.monotonic()
        assert when_redis_answers(rt, "record the end", end) == "recorded"
        assert time.monotonic() - t0 >= 2.5  # it did wait for the store (the gate opened after 3 s)
        assert Manifest.model_validate_json(ObjectStore(object_server.url, BUCKET, prefix, ACCESS_KEY, SECRET_KEY)
                                            .get_bytes(f"jobs/{jid}/manifest.json")).message == "train done"
        reporter._manifest_at = 0.0
        reporter("train", 0.7, "iteration 7/10")
        assert not reporter.store_away and rt.store.read(jid).message == "iteration 7/10"
    finally:
        gate.down()
        ObjectStore(object_server.url, BUCKET, prefix, ACCESS_KEY, SECRET_KEY).delete_prefix("")
        rt.close()
