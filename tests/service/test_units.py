"""Pure pieces of the service: progress weights, survey grouping, the streaming multipart receiver, settings,
error codes, log paging."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from service.jobs.manifest import overall_progress, stage_weights
from service.jobs.store import JobStore
from service.jobs.uploads import UploadError, receive_upload
from service.surveys.registry import resolve_under_roots
from service.surveys.sets import ImageFile, group_images, list_images, set_hash
from worker.runner import error_code


def test_progress_weights_cover_any_stage_list() -> None:
    for stages in [("ingest", "sfm", "train", "export"),
                   ("ingest", "sfm", "classify", "train", "evaluate", "export"), ("ingest", "brand_new", "export")]:
        w = stage_weights(stages)
        assert set(w) == set(stages) and abs(sum(w.values()) - 100) < 1e-9
        assert overall_progress(stages, set(), None, 0) == 0
        assert overall_progress(stages, set(stages), None, 0) == 100


@given(st.lists(st.tuples(st.integers(0, 3), st.floats(0, 1)), min_size=1, max_size=40))
def test_progress_is_monotonic_along_a_run(steps) -> None:
    """Stages in order, each fraction rising: the overall value never drops (the runner also keeps a max)."""
    stages = ("ingest", "sfm", "train", "export")
    seen, best = -1.0, {}
    for i, f in sorted(steps):
        best[i] = max(best.get(i, 0.0), f)
    for i in sorted(best):
        for f in sorted({0.0, best[i], 1.0}):
            p = overall_progress(stages, set(stages[:i]), stages[i], f)
            assert p >= seen
            seen = p


def _img(rel: str, mtime: float) -> ImageFile:
    return ImageFile(rel, 10, mtime, int(mtime * 1e9))


def test_grouping_rule_subfolders_and_time_gaps() -> None:
    t = 1_700_000_000.0
    files = [_img("dive1/a.jpg", t), _img("dive1/deeper/b.jpg", t + 9999), _img("dive2/c.jpg", t),
             _img("x1.jpg", t), _img("x2.jpg", t + 10), _img("x3.jpg", t + 20),  # one burst
             _img("y1.jpg", t + 1000), _img("y2.jpg", t + 1005)]  # > gap later: a second burst
    sets = group_images(files, gap_s=300)
    names = [s.name for s in sets]
    assert names[:2] == ["dive1", "dive2"]
    assert [f.rel for f in sets[0].files] == ["dive1/a.jpg", "dive1/deeper/b.jpg"]  # any depth, one set
    assert [[f.rel for f in s.files] for s in sets[2:]] == [["x1.jpg", "x2.jpg", "x3.jpg"], ["y1.jpg", "y2.jpg"]]
    assert sets[2].name == time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(t))


def test_set_hash_depends_on_names_and_content_only() -> None:
    a, b = _img("s/a.jpg", 1), _img("s/b.jpg", 2)
    d = {"s/a.jpg": (10, 1, "aa"), "s/b.jpg": (10, 2, "bb")}
    assert set_hash([a, b], d) == set_hash([b, a], d)
    assert set_hash([a, b], d) != set_hash([a, b], {**d, "s/b.jpg": (10, 2, "cc")})


def test_list_images_skips_links_hidden_and_non_images(tmp_path: Path) -> None:
    (tmp_path / "set").mkdir()
    (tmp_path / "set" / "a.JPG").write_bytes(b"x")
    (tmp_path / "set" / ".hidden.jpg").write_bytes(b"x")
    (tmp_path / "set" / "notes.txt").write_bytes(b"x")
    (tmp_path / ".cache").mkdir()
    (tmp_path / ".cache" / "b.jpg").write_bytes(b"x")
    os.symlink("/etc/hostname", tmp_path / "set" / "link.jpg")
    os.symlink(tmp_path / "set", tmp_path / "loop")
    assert [f.rel for f in list_images(tmp_path)] == ["set/a.JPG"]


def test_survey_paths_must_resolve_under_a_root(tmp_path: Path) -> None:
    from service.surveys.registry import SurveyError

    root = tmp_path / "root"
    (root / "ok").mkdir(parents=True)
    os.symlink(tmp_path, root / "escape")
    assert resolve_under_roots(str(root / "ok"), [root]) == (root / "ok").resolve()
    for bad, code in [(str(root / "escape"), "path_not_allowed"), (str(tmp_path), "path_not_allowed"),
                      (str(root / "ok" / ".." / ".."), "path_not_allowed"), (str(root / "nope"), "path_not_found")]:
        with pytest.raises(SurveyError) as e:
            resolve_under_roots(bad, [root])
        assert e.value.code == code


# ---------------------------------------------------------------- multipart receiver


def _multipart(fields: dict[str, str], file_bytes: bytes, boundary: str = "XyZ123boundary") -> bytes:
    parts = []
    for k, v in fields.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode())
    parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="archive"; filename="s.zip"\r\n'
                 f"Content-Type: application/zip\r\n\r\n".encode() + file_bytes + b"\r\n")
    return b"".join(parts) + f"--{boundary}--\r\n".encode()


def _receive(body: bytes, cuts: list[int], dest: Path, max_bytes: int = 1 << 20, ctype: str | None = None):
    async def chunks():
        prev = 0
        for c in sorted(set(cuts)) + [len(body)]:
            if c > prev:
                yield body[prev:c]
                prev = c

    ctype = ctype or "multipart/form-data; boundary=XyZ123boundary"
    return asyncio.run(receive_upload(chunks(), ctype, {}, dest, max_bytes))


@settings(max_examples=60, deadline=None)
@given(data=st.binary(min_size=0, max_size=3000), cuts=st.lists(st.integers(0, 3400), max_size=12))
def test_multipart_stream_is_split_anywhere(tmp_path_factory, data: bytes, cuts: list[int]) -> None:
    dest = tmp_path_factory.mktemp("mp") / "archive"
    body = _multipart({"preset": "fast", "iterations": "7"}, data)
    got = _receive(body, cuts, dest)
    assert dest.read_bytes() == data and got.bytes == len(data)
    assert got.fields == {"preset": "fast", "iterations": "7"} and got.filename == "s.zip"


def test_multipart_over_the_cap_is_refused_while_streaming(tmp_path: Path) -> None:
    body = _multipart({}, b"x" * 5000)
    with pytest.raises(UploadError) as e:
        _receive(body, list(range(0, len(body), 512)), tmp_path / "a", max_bytes=4000)
    assert (e.value.status, e.value.code) == (413, "upload_too_large")


@pytest.mark.parametrize("body, ctype, code", [
    (b"--XyZ123boundary\r\nContent-Disposition: form-data; name=\"preset\"\r\n\r\nfast\r\n--XyZ123boundary--\r\n",
     None, "missing_archive"),
    (b"garbage that is not multipart at all", None, "malformed_multipart"),
    (b"{}", "application/json", "unsupported_media_type"),
    (b"abc", "multipart/form-data", "malformed_multipart"),
])
def test_multipart_refusals(tmp_path: Path, body: bytes, ctype: str | None, code: str) -> None:
    with pytest.raises(UploadError) as e:
        _receive(body, [], tmp_path / "a", ctype=ctype)
    assert e.value.code == code


def test_two_archives_are_refused(tmp_path: Path) -> None:
    one = _multipart({}, b"abc")
    body = one.replace(b"--XyZ123boundary--\r\n", b"") + one[:]
    with pytest.raises(UploadError) as e:
        _receive(body, [], tmp_path / "a")
    assert e.value.code == "too_many_files"


# ---------------------------------------------------------------- misc


def test_settings_require_keys_and_data_dir(monkeypatch) -> None:
    from service.core.settings import load_settings

    for k in list(os.environ):
        if k.startswith("DUALPHYS_"):
            monkeypatch.delenv(k)
    with pytest.raises(ValidationError) as e:
        load_settings()
    assert {err["loc"][0] for err in e.value.errors()} == {"api_keys", "data_dir"}
    with pytest.raises(ValidationError):
        load_settings(api_keys={"short": "alice"}, data_dir="/tmp")
    monkeypatch.setenv("DUALPHYS_API_KEYS", '{"a-long-enough-api-key": "alice"}')
    monkeypatch.setenv("DUALPHYS_DATA_DIR", "/tmp/x")
    s = load_settings()
    assert s.owner_of("a-long-enough-api-key") == "alice" and s.owner_of("a-long-enough-api-kex") is None
    assert "a-long-enough-api-key" not in repr(s)


def test_error_codes_from_pipeline_exceptions() -> None:
    from pipeline.ingest.intake import IngestError
    from pipeline.sfm.recipe import TooFewRegisteredError

    assert error_code(IngestError("too_few_images", "x")) == "too_few_images"
    assert error_code(TooFewRegisteredError("x")) == "too_few_registered"
    assert error_code(RuntimeError("boom")) == "stage_failed"


def test_log_pages_end_on_whole_lines(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    (tmp_path / "jabcdefgh").mkdir()
    for i in range(50):
        store.append_log("jabcdefgh", f"line {i}")
    text, offset, pages = "", 0, 0
    while True:
        t, nxt, size = store.read_log("jabcdefgh", offset, 100)
        assert t == "" or t.endswith("\n")
        text, pages = text + t, pages + 1
        if nxt == offset:
            break
        offset = nxt
    assert offset == size and pages > 10 and text.count("\n") == 50
    with open(store.layout("jabcdefgh").log, "a") as f:
        f.write("partial line without end")
    assert store.read_log("jabcdefgh", offset, 100) == ("", offset, size + 24)


def test_worker_and_api_import_no_torch(tmp_path: Path) -> None:
    """Celery's prefork parent must never load torch (a forked child would hang in OpenMP); neither does the API."""
    import json
    import subprocess
    import sys

    code = ("import sys\n"
            "import worker.app, worker.tasks, worker.runner, service.app\n"
            "app = worker.app.app\n"
            "app.loader.import_default_modules()\n"
            "service.app.create_app()\n"
            "bad = [m for m in ('torch', 'pycolmap', 'numba', 'OpenImageIO') if m in sys.modules]\n"
            "assert not bad, bad\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DUALPHYS_")}
    env.update(DUALPHYS_API_KEYS=json.dumps({"a-long-enough-api-key": "alice"}), DUALPHYS_DATA_DIR=str(tmp_path))
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]


def test_client_options_are_the_pipelines_job_options():
    """The API's form fields are JobOptions' own (declared once): same names, defaults and help; the API adds
    only bounds and the choice of fields a client may set."""
    import dataclasses

    from pipeline.job.options import JobOptions
    from service.jobs.options import CLIENT_OPTIONS, JobOptionsIn

    spec = {f.name: f for f in dataclasses.fields(JobOptions)}
    assert set(JobOptionsIn.model_fields) == set(CLIENT_OPTIONS) <= set(spec)
    for name, f in JobOptionsIn.model_fields.items():
        assert f.default == spec[name].default and f.description == spec[name].metadata["help"]
    assert JobOptions(**JobOptionsIn().model_dump()) == JobOptions()
    with pytest.raises(ValueError, match="max_width"):
        JobOptionsIn(max_width=8)
