"""The client's pieces that need no server: the folder zipped while it streams, artifact selection, safe local
paths, the command line's refusals before any request (no key, nothing listening, a bad path), and waiting out a
server that briefly does not answer (a stdlib HTTP server playing a script: the live stack cannot be made to
answer 503 on cue)."""

from __future__ import annotations

import io
import json
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from svc_helpers import free_port

from cli.main import main
from pipeline.job.layout import JobLayout
from service.client.cli import KEY_ENV, SERVER_ENV
from service.client.download import local_path, select
from service.client.remote import Artifact, ClientError, ServiceClient
from service.client.watch import wait_job
from service.client.zipping import archive_content_type, folder_entries, zip_stream
from service.core.settings import Settings


def _tree(root: Path) -> dict[str, bytes]:
    files = {"a.jpg": b"\xff\xd8" + bytes(range(256)) * 40, "sub/b.png": b"\x89PNG" + b"x" * 3000,
             "notes.txt": b"depth 12 m\n" * 500, ".hidden.jpg": b"no", ".cache/c.jpg": b"no"}
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    return {k: v for k, v in files.items() if not k.startswith(".")}


def test_folder_zip_streams_in_pieces_and_reads_back_exactly(tmp_path) -> None:
    want = _tree(tmp_path)
    entries = folder_entries(tmp_path)
    assert [e.name for e in entries] == sorted(want)  # hidden files and folders are left out
    read: list[int] = []
    pieces = list(zip_stream(entries, read.append))
    assert len(pieces) >= 3 and sum(read) == sum(len(v) for v in want.values())
    with zipfile.ZipFile(io.BytesIO(b"".join(pieces))) as z:
        assert z.testzip() is None
        assert {n: z.read(n) for n in z.namelist()} == want
        kinds = {i.filename: i.compress_type for i in z.infolist()}
    assert kinds == {"a.jpg": zipfile.ZIP_STORED, "sub/b.png": zipfile.ZIP_STORED, "notes.txt": zipfile.ZIP_DEFLATED}


def test_archive_types_by_suffix() -> None:
    assert archive_content_type(Path("x.zip")) == "application/zip"
    assert archive_content_type(Path("x.tar.gz")) == "application/gzip"
    assert archive_content_type(Path("x.TAR")) == "application/x-tar"
    assert archive_content_type(Path("x.jpg")) is None


def test_select_by_glob_and_folder() -> None:
    arts = [Artifact(p, 1, "0", f"/u/{p}") for p in
            ("ingest.json", "output/reconstruction.ply", "output/restored/a.png", "output/renders/restored/a.png")]
    assert [a.path for a in select(arts, [])] == [a.path for a in arts]
    assert [a.path for a in select(arts, ["*.ply"])] == ["output/reconstruction.ply"]
    assert [a.path for a in select(arts, ["output/restored/"])] == ["output/restored/a.png"]
    assert [a.path for a in select(arts, ["output/restored/*"])] == ["output/restored/a.png"]
    assert [a.path for a in select(arts, ["restored"])] == ["output/restored/a.png", "output/renders/restored/a.png"]
    assert [a.path for a in select(arts, ["reconstruction.ply", "ingest.*"])] == ["ingest.json",
                                                                                   "output/reconstruction.ply"]
    assert select(arts, ["nothing*"]) == []


def test_select_survey_picks_its_result_and_products() -> None:
    """``--only survey``: the survey stage's survey.json and everything in output/survey/ (the GeoTIFFs and their
    previews), nothing else; a name without its extension picks each file of that name."""
    layout = JobLayout("job")
    survey = [layout.relative(p) for p in (layout.survey_result, layout.ortho, layout.ortho_water,
                                           layout.ortho_confidence, layout.dem, layout.ortho_preview,
                                           layout.ortho_water_preview, layout.hillshade_preview)]
    others = [layout.relative(p) for p in (layout.ply, layout.spz, layout.report_json, layout.ingest)]
    arts = [Artifact(p, 1, "0", f"/u/{p}") for p in (*others, *survey)]
    assert [a.path for a in select(arts, ["survey"])] == survey
    assert [a.path for a in select(arts, ["reconstruction"])] == [layout.relative(layout.ply),
                                                                   layout.relative(layout.spz)]
    assert [a.path for a in select(arts, ["*.tif"])] == survey[1:5]
    assert [a.path for a in select(arts, ["ortho"])] == [layout.relative(layout.ortho),
                                                         layout.relative(layout.ortho_preview)]


@pytest.mark.parametrize("bad", ["../x", "/etc/passwd", "a/../../x", "a//b", "./a"])
def test_an_artifact_path_cannot_leave_the_folder(tmp_path, bad) -> None:
    with pytest.raises(ClientError) as e:
        local_path(tmp_path, bad)
    assert e.value.code == "bad_response"
    assert local_path(tmp_path, "output/x.png") == tmp_path / "output" / "x.png"


def test_client_variables_are_not_service_settings() -> None:
    """DUALPHYS_SERVER / DUALPHYS_KEY share the settings' prefix; a setting of that name would read them."""
    names = {SERVER_ENV, KEY_ENV}
    assert all(n.startswith("DUALPHYS_") for n in names)
    assert not {n.removeprefix("DUALPHYS_").lower() for n in names} & set(Settings.model_fields)


def test_no_key_and_nothing_listening_are_clear_messages(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.delenv(KEY_ENV, raising=False)
    monkeypatch.delenv(SERVER_ENV, raising=False)
    assert main(["jobs"]) == 1
    assert "no API key: pass --key or set DUALPHYS_KEY" in capsys.readouterr().err
    url = f"http://127.0.0.1:{free_port()}"
    monkeypatch.setenv(KEY_ENV, "secret-key-never-printed")
    assert main(["status", "j123", "--server", url]) == 1
    err = capsys.readouterr().err
    assert f"cannot connect to {url}: is the service running there?" in err and "secret-key" not in err
    assert main(["submit", str(tmp_path / "missing"), "--server", url]) == 1
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "photo.jpg").write_bytes(b"x")
    assert main(["submit", str(tmp_path / "photo.jpg"), "--server", url]) == 1
    assert "is not a folder or a .zip/.tar" in capsys.readouterr().err


class _Scripted(BaseHTTPRequestHandler):
    """Answers GET /v1/jobs/<id> with the next (status, body) of the server's script."""

    def do_GET(self) -> None:  # noqa: N802 (the stdlib's name)
        self.server.paths.append(self.path)
        status, body = self.server.script.pop(0)
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, *args) -> None:
        pass


@pytest.fixture()
def scripted():
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Scripted)
    server.script, server.paths = [], []
    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    yield server
    server.shutdown()
    server.server_close()


def test_wait_rides_out_a_server_that_is_briefly_unavailable(scripted) -> None:
    busy = {"error": {"code": "unavailable", "message": "restarting"}}
    job = {"id": "j1", "state": "running", "stage": "train", "progress": 40.0, "message": ""}
    scripted.script = [(200, job), (503, busy), (503, busy), (200, {**job, "state": "done", "progress": 100.0})]
    seen, slept = [], []
    with ServiceClient(f"http://127.0.0.1:{scripted.server_port}", "k" * 20) as c:
        final = wait_job(c, "j1", interval_s=0.01, on_update=seen.append, sleep=slept.append)
    assert final["state"] == "done" and [s["state"] for s in seen] == ["running", "done"]
    assert slept == [0.01, 0.02, 0.04]  # the poll interval, then doubling while the server did not answer
    assert scripted.paths == ["/v1/jobs/j1"] * 4


def test_wait_gives_up_on_a_real_refusal_at_once(scripted) -> None:
    scripted.script = [(404, {"error": {"code": "job_not_found", "message": "no job 'j1'"}})]
    with ServiceClient(f"http://127.0.0.1:{scripted.server_port}", "k" * 20) as c, pytest.raises(ClientError) as e:
        wait_job(c, "j1", interval_s=0.01, sleep=lambda s: None)
    assert (e.value.status, e.value.code) == (404, "job_not_found") and len(scripted.paths) == 1
