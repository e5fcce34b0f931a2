"""HTTP semantics, in-process (TestClient, real Redis, no worker): auth, ownership, error bodies, idempotency,
listing, cancel/retry/delete of queued jobs, surveys registration, OpenAPI."""

from __future__ import annotations

import pytest
from svc_helpers import auth, small_jpegs, small_video, zip_bytes


@pytest.fixture(scope="module")
def good_zip() -> bytes:
    return zip_bytes({f"dive/img_{i}.jpg": b for i, b in enumerate(small_jpegs(4))})


def create(api, owner: str, archive: bytes, **kw):
    files = {"archive": ("set.zip", archive, "application/zip")}
    return api.post("/v1/jobs", files=files, data={k: str(v) for k, v in kw.pop("data", {}).items()},
                    headers={**auth(owner), **kw.pop("headers", {})})


def assert_error(r, status: int, code: str) -> dict:
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) >= {"error"} and body["error"]["code"] == code and body["error"]["message"], body
    return body


def test_openapi_and_docs_are_served(api) -> None:
    spec = api.get("/openapi.json").json()
    assert {"/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/artifacts/{path}", "/v1/surveys",
            "/health", "/ready"} <= set(spec["paths"])
    assert "multipart/form-data" in spec["paths"]["/v1/jobs"]["post"]["requestBody"]["content"]
    assert "HTTPBearer" in spec["components"]["securitySchemes"]
    assert api.get("/docs").status_code == 200


def test_health_and_ready(api) -> None:
    assert api.get("/health").json() == {"status": "ok"}
    r = api.get("/ready")
    assert r.status_code == 200 and r.json()["redis"] is True and r.json()["data_dir_writable"] is True


@pytest.mark.parametrize("headers, params", [
    ({}, {}),
    ({"Authorization": "Bearer not-a-key-at-all-xxxxxxxx"}, {}),
    ({"Authorization": "Basic YWxpY2U6cHc="}, {}),
    ({}, {"api_key": "alice-key-0123456789abcdef"}),  # keys are never taken from the query string
])
def test_requests_without_a_valid_key_get_401(api, headers, params) -> None:
    for method, path in [("get", "/v1/jobs"), ("get", "/v1/jobs/jdoesnotexist0"), ("post", "/v1/jobs"),
                         ("get", "/v1/surveys")]:
        r = getattr(api, method)(path, headers=headers, params=params)
        assert_error(r, 401, "unauthorized")
        assert r.headers["www-authenticate"] == "Bearer"


def test_jobs_are_invisible_to_other_owners(api, good_zip) -> None:
    r = create(api, "alice", good_zip)
    assert r.status_code == 201, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert job["state"] == "queued" and job["ingest"]["images"] == 4 and job["stages"][0]["status"] == "done"
    jid = job["id"]
    for method, path in [("get", ""), ("get", "/log"), ("get", "/artifacts"), ("get", "/artifacts/ingest.json"),
                         ("get", "/bundle"), ("post", "/cancel"), ("post", "/retry"), ("delete", "")]:
        assert_error(getattr(api, method)(f"/v1/jobs/{jid}{path}", headers=auth("bob")), 404, "job_not_found")
    assert api.get("/v1/jobs", headers=auth("bob")).json()["total"] == 0
    assert api.get(f"/v1/jobs/{jid}", headers=auth("alice")).json()["id"] == jid
    assert api.get("/v1/jobs", headers=auth("alice")).json()["jobs"][0]["id"] == jid


def test_an_upload_of_one_video_becomes_a_job(api) -> None:
    """A zip holding only a video (and a broken one) is not refused: ingest takes its keyframes."""
    archive = zip_bytes({"dive/GX010042.MP4": small_video(), "dive/broken.mov": b"\x00" * 4096})
    r = create(api, "alice", archive)
    assert r.status_code == 201, r.text
    ing = r.json()["ingest"]
    assert 4 <= ing["images"] <= 8 and [s["file"] for s in ing["skipped"]] == ["dive/broken.mov"]
    assert [(v["file"], v["frames_decoded"], v["kept"]) for v in ing["videos"]][0] == \
        ("dive/GX010042.MP4", 40, ing["images"])
    assert ing["videos"][1]["file"] == "dive/broken.mov" and "not a readable video" in ing["videos"][1]["error"]


def test_idempotency_key_returns_the_first_job(api, good_zip) -> None:
    h = {"Idempotency-Key": "upload-2026-11-22-a"}
    first = create(api, "alice", good_zip, headers=h)
    again = create(api, "alice", good_zip, headers=h)
    other_owner = create(api, "bob", good_zip, headers=h)
    assert (first.status_code, again.status_code, other_owner.status_code) == (201, 200, 201)
    assert again.json()["id"] == first.json()["id"] != other_owner.json()["id"]
    assert api.get("/v1/jobs", headers=auth("alice")).json()["total"] == 1
    # a refused upload does not use up its key
    bad = create(api, "alice", b"not an archive", headers={"Idempotency-Key": "k2"})
    assert_error(bad, 415, "not_an_archive")
    assert create(api, "alice", good_zip, headers={"Idempotency-Key": "k2"}).status_code == 201


def test_cancel_retry_delete_of_a_queued_job(api, good_zip) -> None:
    jid = create(api, "alice", good_zip).json()["id"]
    r = api.post(f"/v1/jobs/{jid}/cancel", headers=auth("alice"))
    assert r.status_code == 202 and r.json()["state"] == "cancelled"  # nobody ran it yet: cancelled at once
    assert api.post(f"/v1/jobs/{jid}/cancel", headers=auth("alice")).json()["state"] == "cancelled"
    r = api.post(f"/v1/jobs/{jid}/retry", headers=auth("alice"))
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["state"] == "queued" and [x["from_stage"] for x in job["runs"]] == ["sfm", "sfm"]
    assert [x["outcome"] for x in job["runs"]] == ["cancelled", None]
    assert_error(api.post(f"/v1/jobs/{jid}/retry", headers=auth("alice")), 409, "not_retryable")
    api.post(f"/v1/jobs/{jid}/cancel", headers=auth("alice"))
    assert api.delete(f"/v1/jobs/{jid}", headers=auth("alice")).status_code == 204
    assert_error(api.get(f"/v1/jobs/{jid}", headers=auth("alice")), 404, "job_not_found")
    assert not (api.settings.jobs_dir / jid).exists()


def test_list_filters_and_pages(api, good_zip) -> None:
    ids = [create(api, "alice", good_zip).json()["id"] for _ in range(3)]
    api.post(f"/v1/jobs/{ids[0]}/cancel", headers=auth("alice"))
    page = api.get("/v1/jobs", params={"limit": 2}, headers=auth("alice")).json()
    assert page["total"] == 3 and [j["id"] for j in page["jobs"]] == ids[:0:-1] and page["next_offset"] == 2
    rest = api.get("/v1/jobs", params={"limit": 2, "offset": 2}, headers=auth("alice")).json()
    assert [j["id"] for j in rest["jobs"]] == [ids[0]] and rest["next_offset"] is None
    cancelled = api.get("/v1/jobs", params={"status": "cancelled"}, headers=auth("alice")).json()
    assert [j["id"] for j in cancelled["jobs"]] == [ids[0]]
    assert_error(api.get("/v1/jobs", params={"limit": 0}, headers=auth("alice")), 422, "invalid_request")
    assert_error(api.get("/v1/jobs", params={"status": "bogus"}, headers=auth("alice")), 422, "invalid_request")


def test_log_has_the_upload_story_and_pages_by_offset(api, good_zip) -> None:
    files = {"img_0.jpg": small_jpegs(1)[0], **{f"ok/{i}.jpg": b for i, b in enumerate(small_jpegs(3, seed=9))},
             "broken.jpg": b"\xff\xd8\xff garbage"}
    r = create(api, "alice", zip_bytes(files))
    assert r.status_code == 201
    jid = r.json()["id"]
    assert [s["file"] for s in r.json()["ingest"]["skipped"]] == ["broken.jpg"]
    full = api.get(f"/v1/jobs/{jid}/log", headers=auth("alice")).json()
    assert "job created by alice" in full["text"] and full["next_offset"] == full["size"]
    tail = api.get(f"/v1/jobs/{jid}/log", params={"offset": full["next_offset"]}, headers=auth("alice")).json()
    assert tail["text"] == "" and tail["next_offset"] == full["next_offset"]


@pytest.mark.parametrize("data, message", [({"preset": "bogus"}, "preset"), ({"iterations": "0"}, "iterations"),
                                           ({"metric_scale": "-1"}, "metric_scale"), ({"colour": "red"}, "colour"),
                                           ({"telemetry": "/etc/passwd.csv"}, "telemetry"),
                                           ({"telemetry": "../up.csv"}, "telemetry"),
                                           ({"scale_bar": "a.jpg:1,2:3,4"}, "scale_bar"),
                                           ({"ortho_gsd": "0"}, "ortho_gsd")])
def test_invalid_options_are_refused_before_any_work(api, good_zip, data, message) -> None:
    body = assert_error(create(api, "alice", good_zip, data=data), 422, "invalid_options")
    assert message in body["error"]["message"]
    assert not any(api.settings.jobs_dir.iterdir())


def test_survey_options_reach_the_job(api, good_zip) -> None:
    r = create(api, "alice", good_zip, data={"ortho": "false", "ortho_gsd": "0.005", "telemetry": "frames.csv",
                                             "scale_bar": "IMG_1.JPG:10,20:110,20:0.5"})
    assert r.status_code == 201, r.text
    o = r.json()["options"]
    assert (o["ortho"], o["ortho_gsd"], o["telemetry"], o["scale_bar"]) == (False, 0.005, "frames.csv",
                                                                            "IMG_1.JPG:10,20:110,20:0.5")


def test_raw_body_upload_with_query_options(api, good_zip) -> None:
    r = api.post("/v1/jobs", content=good_zip, params={"preset": "balanced", "filename": "dive.zip"},
                 headers={**auth("alice"), "Content-Type": "application/zip"})
    assert r.status_code == 201, r.text
    assert r.json()["options"]["preset"] == "balanced" and r.json()["source"]["filename"] == "dive.zip"


def test_unknown_routes_and_methods_are_json_errors(api) -> None:
    assert_error(api.get("/v1/nothing-here", headers=auth("alice")), 404, "not_found")
    assert_error(api.put("/v1/jobs", headers=auth("alice")), 405, "method_not_allowed")


def test_surveys_registration(api) -> None:
    root = api.settings.survey_roots[0]
    (root / "reef").mkdir()
    h = auth("alice")
    r = api.post("/v1/surveys", json={"path": str(root / "reef"), "interval_s": 60}, headers=h)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert r.json()["origin"] == "api" and r.json()["sets"] == []
    assert_error(api.post("/v1/surveys", json={"path": str(root / "reef"), "interval_s": 60}, headers=h),
                 409, "survey_exists")
    assert_error(api.post("/v1/surveys", json={"path": "/etc", "interval_s": 60}, headers=h), 403, "path_not_allowed")
    assert_error(api.post("/v1/surveys", json={"path": str(root / "reef" / ".." / ".."), "interval_s": 60},
                          headers=h), 403, "path_not_allowed")
    assert_error(api.post("/v1/surveys", json={"path": str(root / "none"), "interval_s": 60}, headers=h),
                 422, "path_not_found")
    assert_error(api.post("/v1/surveys", json={"path": str(root / "reef"), "interval_s": 0.5}, headers=h),
                 422, "interval_too_short")
    assert [s["id"] for s in api.get("/v1/surveys", headers=h).json()["surveys"]] == [sid]
    assert api.get("/v1/surveys", headers=auth("bob")).json()["surveys"] == []
    assert_error(api.get(f"/v1/surveys/{sid}", headers=auth("bob")), 404, "survey_not_found")
    assert api.post(f"/v1/surveys/{sid}/scan", headers=h).status_code == 202
    assert api.delete(f"/v1/surveys/{sid}", headers=h).status_code == 204
    assert_error(api.get(f"/v1/surveys/{sid}", headers=h), 404, "survey_not_found")


@pytest.mark.parametrize("options, status, code, message", [
    ({"mode": "nerf"}, 422, "invalid_request", "unknown mode 'nerf'"),
    ({"preset": "bogus"}, 422, "invalid_request", "unknown preset 'bogus'"),
    ({"seed": -1}, 422, "invalid_request", "seed"),
    ({"iterations": 10**9}, 422, "invalid_options", "iterations: at most 100000"),
])
def test_survey_options_are_checked_when_registered(api, options, status, code, message) -> None:
    root = api.settings.survey_roots[0]
    (root / "reef").mkdir()
    body = assert_error(api.post("/v1/surveys", json={"path": str(root / "reef"), "interval_s": 60,
                                                      "options": options}, headers=auth("alice")), status, code)
    assert message in body["error"]["message"]
    assert api.get("/v1/surveys", headers=auth("alice")).json()["surveys"] == []


def test_artifacts_listing_range_and_bundle(api, good_zip) -> None:
    import hashlib
    import io
    import zipfile

    jid = create(api, "alice", good_zip).json()["id"]
    arts = api.get(f"/v1/jobs/{jid}/artifacts", headers=auth("alice")).json()["artifacts"]
    assert [a["path"] for a in arts] == ["ingest.json"]  # only what a finished stage wrote
    url = arts[0]["url"]
    full = api.get(url, headers=auth("alice"))
    assert full.status_code == 200 and hashlib.sha256(full.content).hexdigest() == arts[0]["sha256"]
    part = api.get(url, headers={**auth("alice"), "Range": "bytes=2-11"})
    assert part.status_code == 206 and part.content == full.content[2:12]
    assert_error(api.get(url, headers={**auth("alice"), "Range": "bytes=99999-"}), 416, "range_not_satisfiable")
    assert_error(api.get(url, headers={**auth("alice"), "Range": "lines=1-2"}), 400, "bad_range")
    for sneaky in ("../manifest.json", "manifest.json", "input/archive", "images/dive__img_0.jpg", "%2e%2e/x"):
        r = api.get(f"/v1/jobs/{jid}/artifacts/{sneaky}", headers=auth("alice"))  # ".." may be resolved by the
        assert r.status_code == 404 and r.json()["error"]["code"] in ("artifact_not_found", "not_found")  # client
    bundle = api.get(f"/v1/jobs/{jid}/bundle", headers=auth("alice"))
    with zipfile.ZipFile(io.BytesIO(bundle.content)) as z:
        assert z.namelist() == ["ingest.json"] and z.read("ingest.json") == full.content


def test_without_redis_the_api_says_so_and_writes_nothing(tmp_path, good_zip) -> None:
    from fastapi.testclient import TestClient
    from svc_helpers import make_settings

    from service.app import create_app

    settings = make_settings(tmp_path, "dptest-noredis", redis_url="redis://127.0.0.1:1/0")
    with TestClient(create_app(settings)) as client:
        r = client.get("/ready")
        assert_error(r, 503, "not_ready")
        assert r.json()["redis"] is False
        assert client.get("/health").status_code == 200
        r = create(client, "alice", good_zip)
        assert r.status_code == 503 and r.json()["error"]["code"] in ("redis_unavailable", "broker_unavailable")
        assert not any(settings.jobs_dir.iterdir())


@pytest.mark.parametrize("limits, code", [({"min_images": 5}, "too_few_images"),
                                          ({"archive_max_entries": 3}, "too_many_entries")])
def test_the_deployments_upload_limits_reach_the_ingest_stage(tmp_path, unit_prefix, good_zip, limits, code) -> None:
    """The API runs the ingest stage with this deployment's ``min_images`` and archive limits (4 images here)."""
    from fastapi.testclient import TestClient
    from svc_helpers import make_settings

    from service.app import create_app

    (tmp_path / "surveys-root").mkdir()
    settings = make_settings(tmp_path, unit_prefix, **limits)
    with TestClient(create_app(settings)) as client:
        assert_error(create(client, "alice", good_zip), 413 if code == "too_many_entries" else 422, code)
        assert not any(settings.jobs_dir.iterdir())


def test_ready_requires_a_live_worker_on_every_needed_queue_when_asked(tmp_path, unit_prefix) -> None:
    """``require_workers`` (on under `dualphys serve`): a queue jobs need without a live worker makes /ready 503
    (issue 44: never a dead worker behind a healthy /ready); without the setting it stays 200 with a warning."""
    from fastapi.testclient import TestClient
    from svc_helpers import make_settings

    from service.app import create_app

    prefix = f"{unit_prefix}-ready-{tmp_path.name[-6:]}"
    for require in (False, True):
        settings = make_settings(tmp_path, prefix, require_workers=require)
        with TestClient(create_app(settings)) as client:
            r = client.get("/ready")
            assert r.status_code == (503 if require else 200), r.text
            assert r.json()["workers_ok"] is False and "no worker consumes the 'cpu' queue" in r.json()["warnings"]
            if require:
                assert_error(r, 503, "not_ready")
                assert "no worker consumes the 'cpu' queue" in r.json()["error"]["message"]
            coord = client.app.state.services.coord
            coord.announce_worker("w1@test", ["cpu", "surveys"], 1, ttl_s=30)
            try:
                r = client.get("/ready")
                assert r.status_code == 200 and r.json()["workers_ok"] is True, r.text
            finally:
                coord.forget_worker("w1@test")
