"""The dashboard in a real browser (Debian's Chromium driven by Playwright; no browser is downloaded) against the
live stack (uvicorn + Celery worker + Redis): a wrong key's message, sign-in, an upload through the page with
options, progress watched to done, the job page (stages, log, report, gallery, water maps, downloads checked
against the artifact checksums, the 3D tab, the survey map), another owner's job reported as not found, and every
request the browser made free of the key and of any other host. ONE tiny job runs through the stack (module
fixture).

With DUALPHYS_DASHBOARD_SHOTS=<folder> the test also saves the screenshots docs/img/ holds."""

from __future__ import annotations

import hashlib
import io
import os
import re
import shutil
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
import survey_map as smap
from PIL import Image
from svc_helpers import KEYS, METRICS, REPO, upload, wait_for

from pipeline.job.layout import JobLayout

playwright_api = pytest.importorskip("playwright.sync_api", reason="the browser test needs playwright")

pytestmark = pytest.mark.slow

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# software WebGL2 (SwiftShader through ANGLE) for the 3D tab: no GPU on our machines or CI's
ARGS = ["--headless=new", "--no-sandbox", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run", "--disable-dev-shm-usage", "--use-gl=angle", "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
WRONG_KEY = "wrong-key-0123456789abcdef"
JOB_TIMEOUT_S = 720  # about a minute alone; CI shares the 2 cores with other work
SHOTS = os.environ.get("DUALPHYS_DASHBOARD_SHOTS")
VIEWER_JS = REPO / "service" / "web" / "static" / "viewer" / "viewer.js"


@dataclass
class Recorded:
    urls: list[str] = field(default_factory=list)
    api_auth: list[tuple[str, bool]] = field(default_factory=list)  # (path, had a Bearer header)

    def on_request(self, req) -> None:
        self.urls.append(req.url)
        path = urlsplit(req.url).path
        if path.startswith("/v1/"):
            self.api_auth.append((path, req.headers.get("authorization", "").startswith("Bearer ")))


@dataclass
class Flow:
    page: object
    rec: Recorded
    job_id: str
    progress: list[float]
    bob_job: str


def shot(page, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(SHOTS) / f"{name}.png"), full_page=False)


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    if not Path(CHROMIUM).exists():
        pytest.fail("the dashboard test needs Debian's chromium (apt-get install chromium; .ci/run does it)",
                    pytrace=False)
    with playwright_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def rec() -> Recorded:
    return Recorded()


@pytest.fixture(scope="module")
def context(browser, rec) -> Iterator[object]:
    ctx = browser.new_context(viewport={"width": 1280, "height": 860}, accept_downloads=True)
    ctx.on("request", rec.on_request)
    yield ctx
    ctx.close()


def wait_js(page, what: str, expr: str, arg=None, timeout: float = 30) -> None:
    """Poll a JS function in the page from Python: Playwright's wait_for_function evaluates its predicate with
    eval inside the page, which the dashboard's Content-Security-Policy (rightly) refuses."""
    wait_for(what, lambda: page.evaluate(expr, arg), timeout=timeout, interval=0.25)


def sign_in(page, key: str) -> None:
    page.fill("#signin-key", key)
    page.click("#signin-form button[type=submit]")


@pytest.fixture(scope="module")
def flow(live, context, rec, scene_zip, tmp_path_factory) -> Flow:
    """Sign in, upload the scene through the page (iterations 60, preset fast), and watch its row to done."""
    page = context.new_page()
    page.goto(live.url + "/")
    page.wait_for_selector("#view-signin:not([hidden])")
    shot(page, "dashboard-signin")
    sign_in(page, KEYS["alice"])
    page.wait_for_selector("#view-jobs:not([hidden])")
    archive = tmp_path_factory.mktemp("dash") / "dive.zip"
    archive.write_bytes(scene_zip)
    page.set_input_files("#upload-archive", str(archive))
    page.click("#upload-form summary")
    page.fill("#upload-form [name=iterations]", "60")
    page.select_option("#upload-form [name=preset]", "fast")
    page.click("#upload-submit")
    msg = page.wait_for_selector("#upload-msg:text-matches('Job .* started')", timeout=120_000).inner_text()
    job_id = re.search(r"Job (\S+) started", msg).group(1)

    # bob's job, queued behind alice's and cancelled at once: it never runs, it only has to exist
    with live.client("bob") as bob:
        r = upload(bob, scene_zip, filename="bob.zip", iterations=5)
        assert r.status_code == 201, r.text
        bob_job = r.json()["id"]
        assert bob.post(f"/v1/jobs/{bob_job}/cancel").status_code == 202

    row = f"#jobs-body tr[data-job='{job_id}']"
    progress: list[float] = []

    def done() -> bool:
        state = page.get_attribute(row, "data-state")
        progress.append(float(page.eval_on_selector(f"{row} progress", "p => p.value")))
        if state == "running" and len(progress) == 8:
            shot(page, "dashboard-jobs")
        assert state not in ("failed", "cancelled"), f"job {state}"
        return state == "done"

    wait_for("the dashboard to show the job done", done, timeout=JOB_TIMEOUT_S, interval=1.0)
    METRICS["dashboard progress samples"] = f"{len(progress)} ({progress[0]:.1f} .. {progress[-1]:.1f})"
    return Flow(page, rec, job_id, progress, bob_job)


@pytest.mark.timeout(120)
def test_wrong_key_shows_a_clear_message_and_keeps_nothing(live, browser):
    ctx = browser.new_context()
    try:
        page = ctx.new_page()
        page.goto(live.url + "/")
        sign_in(page, WRONG_KEY)
        err = page.wait_for_selector("#signin-error:not([hidden])")
        assert "not accepted" in err.inner_text()
        assert page.is_visible("#view-signin") and not page.is_visible("#view-jobs")
        assert page.evaluate("Object.keys(sessionStorage).length") == 0
    finally:
        ctx.close()


@pytest.mark.timeout(120)
def test_picked_files_are_zipped_into_a_valid_archive(live, browser):
    """zip.js (picked images or a folder become one stored zip in the browser), read back by Python's zipfile."""
    ctx = browser.new_context()
    try:
        page = ctx.new_page()
        page.goto(live.url + "/")
        data = page.evaluate("""async () => {
            const { storeZip } = await import('/static/zip.js');
            const a = new File([new Uint8Array([0, 1, 2, 250, 255])], 'a.png');
            const b = new File(['h\u00e9llo '.repeat(5000)], 'b.jpg');
            const blob = await storeZip([{name: 'dive/a.png', file: a}, {name: 'dive/s\u00fcd/b.jpg', file: b}]);
            return Array.from(new Uint8Array(await blob.arrayBuffer()));
        }""")
    finally:
        ctx.close()
    z = zipfile.ZipFile(io.BytesIO(bytes(data)))
    assert z.testzip() is None  # every CRC-32 checks
    assert z.namelist() == ["dive/a.png", "dive/süd/b.jpg"]
    assert z.read("dive/a.png") == bytes([0, 1, 2, 250, 255])
    assert z.read("dive/süd/b.jpg") == ("héllo " * 5000).encode()
    assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())


@pytest.mark.timeout(JOB_TIMEOUT_S + 360)  # + the scene, generated once per cache
def test_progress_is_watched_to_done(flow):
    p = flow.progress
    assert p[-1] == 100
    assert all(b >= a for a, b in zip(p, p[1:])), f"progress went back: {p}"
    assert len(set(p)) >= 3, f"the bar moved too little to have been watched: {p}"


@pytest.mark.timeout(300)
def test_job_page_shows_stages_log_report_gallery_and_maps(live, flow):
    page = flow.page
    page.click(f"#jobs-body a[href='/jobs/{flow.job_id}']")
    page.wait_for_selector("#job-summary[data-state=done]")
    assert page.url == f"{live.url}/jobs/{flow.job_id}"
    with live.client("alice") as c:
        api_stages = c.get(f"/v1/jobs/{flow.job_id}").json()["stages"]
        artifacts = c.get(f"/v1/jobs/{flow.job_id}/artifacts").json()["artifacts"]
    rows = page.query_selector_all("#stages-body tr")
    assert [r.get_attribute("data-stage") for r in rows] == [s["name"] for s in api_stages]
    assert all(r.query_selector("td:nth-child(3)").inner_text().endswith("s") for r in rows)
    wait_js(page, "the log tail", "() => document.querySelector('#job-log').textContent.length > 100")
    shot(page, "dashboard-job")

    page.click(".tabs [data-tab=report]")
    report = page.frame_locator("#report-frame").locator("h1")
    assert "dualphys report" in report.inner_text(timeout=30_000)
    shot(page, "dashboard-report")

    page.click(".tabs [data-tab=gallery]")
    n_photos = sum(a["path"].startswith("output/restored/") for a in artifacts)
    n_views = sum(a["path"].startswith("output/renders/with_water/") for a in artifacts)
    assert n_photos >= 2 and n_views >= 2
    wait_js(page, "the gallery's photo pairs (as taken | restored previews) and the model's views",
            "n => [...document.querySelectorAll('#gallery figure.pair img, #photos figure.pair img')]"
            ".filter(i => i.complete && i.naturalWidth > 0).length >= n",
            arg=2 * min(n_photos, 24) + 2 * min(n_views, 24), timeout=60)
    sizes = page.eval_on_selector_all("#gallery figure.pair img", "imgs => imgs.map(i => [i.dataset.preview, "
                                      "i.naturalWidth, i.naturalHeight])")
    assert {k.split("/")[0] for k, _, _ in sizes} == {"original", "restored"}
    assert all(0 < max(w, h) <= 640 for _, w, h in sizes), sizes
    assert page.eval_on_selector_all("#gallery img", "imgs => imgs.every(i => i.src.startsWith('blob:'))")
    shot(page, "dashboard-gallery")
    stem = sizes[0][0].split("/")[1]
    with live.client("alice") as c:
        r = c.get(f"/v1/jobs/{flow.job_id}/previews/restored/{stem}")
        assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg" and r.content[:2] == b"\xff\xd8"
        r = c.get(f"/v1/jobs/{flow.job_id}/previews/restored/no-such-photo")
        assert (r.status_code, r.json()["error"]["code"]) == (404, "preview_not_found")
        assert c.get(f"/v1/jobs/{flow.job_id}/previews/thumbnail/{stem}").status_code == 422
    with live.client("bob") as c:  # another owner's job: exactly like a missing one
        r = c.get(f"/v1/jobs/{flow.job_id}/previews/original/{stem}")
        assert (r.status_code, r.json()["error"]["code"]) == (404, "job_not_found")

    page.click(".tabs [data-tab=maps]")
    wait_js(page, "the water maps",
            "() => [...document.querySelectorAll('#maps img')].filter(i => i.naturalWidth > 0).length >= 3")


@pytest.mark.timeout(120)
def test_downloads_match_the_artifact_checksums(live, flow):
    page = flow.page
    page.click(".tabs [data-tab=downloads]")
    with live.client("alice") as c:
        artifacts = {a["path"]: a for a in c.get(f"/v1/jobs/{flow.job_id}/artifacts").json()["artifacts"]}
    wait_js(page, "the file list", "n => document.querySelectorAll('#files-body tr').length === n", arg=len(artifacts))
    for path in ("output/report.json", "output/reconstruction.ply"):
        row = page.locator("#files-body tr", has_text=path).first
        with page.expect_download() as dl:
            row.locator("button").click()
        data = Path(dl.value.path()).read_bytes()
        assert hashlib.sha256(data).hexdigest() == artifacts[path]["sha256"], path
        assert dl.value.suggested_filename == path.rsplit("/", 1)[-1]


def _canvas(page) -> np.ndarray:
    """The 3D tab's canvas as the screen shows it, [H, W, 3] 0-255."""
    png = page.locator("#viewer canvas").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)


def _settled(page, changed_from: np.ndarray | None = None, timeout_s: float = 40.0) -> np.ndarray:
    """The canvas once it has drawn something (over 5 % of it off its clear colour), differs from ``changed_from``
    by over 1 grey level on average (after a camera move) and two frames in a row agree: the viewer sorts and
    uploads the splats in workers, so a frame can be empty or a step behind."""
    prev = _canvas(page)
    for _ in range(int(timeout_s / 0.5)):
        page.wait_for_timeout(500)
        img = _canvas(page)
        drawn = float((np.abs(img - np.median(img.reshape(-1, 3), axis=0)).max(axis=2) > 24).mean())
        changed = changed_from is None or float(np.abs(img - changed_from).mean()) > 1.0
        if drawn > 0.05 and changed and float(np.abs(img - prev).mean()) < 0.3:
            return img
        prev = img
    return prev


@pytest.mark.timeout(180)
def test_3d_tab_shows_the_reconstruction_and_the_camera_moves(flow):
    """The 3D tab mounts the viewer on the job's own splat file and cameras (fetched with the key); its canvas is
    not blank and a drag turns the camera (the viewer's own tests compare what it draws with our rasterizer)."""
    page = flow.page
    page.click(".tabs [data-tab=viewer]")
    assert VIEWER_JS.exists(), "the viewer bundle is part of the package (web/viewer/README.md builds it)"
    page.wait_for_selector("#viewer canvas", timeout=60_000)
    first = _settled(page)
    assert float(first.std()) > 4.0, "the 3D view is blank"
    shot(page, "dashboard-viewer")
    box = page.locator("#viewer canvas").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + box["width"] / 5, y + box["height"] / 10, steps=10)
    page.mouse.up()
    moved = _settled(page, changed_from=first)
    diff = float(np.abs(moved - first).mean())
    METRICS["dashboard 3D: mean change after a drag (grey levels)"] = round(diff, 1)
    assert diff > 3.0, f"the picture hardly changed when the camera moved ({diff:.2f} grey levels)"


def _survey_of(live, job_id: str) -> tuple[dict, dict, str]:
    """The job's artifacts by path, its survey.json and its mode (report.json), from the API."""
    rel = JobLayout("job").relative
    with live.client("alice") as c:
        artifacts = {a["path"]: a for a in c.get(f"/v1/jobs/{job_id}/artifacts").json()["artifacts"]}
        result = rel(JobLayout("job").survey_result)
        assert result in artifacts, ("the job made no survey products (is the survey stage in the table, and the "
                                     f"ortho option on by default?): {len(artifacts)} artifacts")
        survey = c.get(artifacts[result]["url"]).json()
        mode = c.get(artifacts["output/report.json"]["url"]).json()["mode"]
    return artifacts, survey, mode


def _preview_size(live, artifact: dict) -> tuple[int, int]:
    with live.client("alice") as c:
        return Image.open(io.BytesIO(c.get(artifact["url"]).content)).size


def _check_survey_facts(page, survey: dict) -> None:
    """The numbers beside the map are survey.json's: each as stored (data-value) and as read (3 digits, units)."""
    shown = smap.facts(page)
    grid, terrain, frame = survey.get("grid") or {}, survey.get("terrain") or {}, survey.get("frame") or {}
    expected = {"gsd": grid.get("gsd"), "area": grid.get("area"), "rugosity": terrain.get("rugosity"),
                "height": (terrain.get("height") or {}).get("robust_range")}
    for key, value in expected.items():
        if value is None:
            assert key not in shown, (key, shown)
            continue
        raw, text = shown[key]
        assert float(raw) == pytest.approx(value, rel=1e-9), (key, raw, value)
        read = float(text.split()[0]) if key == "rugosity" else smap.shown_length(text)
        assert read == pytest.approx(value, rel=6e-3, abs=1e-12), (key, text, value)  # 3 significant digits
    for name in (frame.get("crs_name"), frame.get("crs")):
        if name:
            assert name in shown["crs"][1], (name, shown["crs"])


def _check_scale_bar(page, survey: dict, preview_width: int, scale: float) -> None:
    """The bar's length on screen matches the ground it claims: ground per preview pixel over the zoom."""
    per_pixel = smap.ground_per_pixel(survey, preview_width)
    bar = smap.scale_bar(page)
    if per_pixel is None:
        assert bar["hidden"], bar
        return
    assert not bar["hidden"] and 10 < bar["width"] <= 120, bar
    assert smap.shown_length(bar["label"]) / bar["width"] == pytest.approx(per_pixel / scale, rel=1e-3), bar


@pytest.mark.timeout(180)
def test_survey_map_pans_zooms_and_switches_water(live, flow):
    """The survey tab shows the job's own orthomosaic preview (fetched with the key): a drag pans it by the drag,
    the wheel zooms in around the cursor, without water / with water / elevation swap the picture and keep the
    view, reset fits it again; the scale bar, ground resolution, CRS, area, rugosity and height range are
    survey.json's, and a GeoTIFF downloads with its listed checksum. In mode 3dgs (no water modelled) only the
    with-water mosaic exists, and the page says why."""
    layout = JobLayout("job")
    rel = layout.relative
    artifacts, survey, mode = _survey_of(live, flow.job_id)
    water, shade, dewatered = rel(layout.ortho_water_preview), rel(layout.hillshade_preview), rel(layout.ortho_preview)
    assert water in artifacts and shade in artifacts
    assert (dewatered in artifacts) == (mode != "3dgs"), (mode, [a for a in artifacts if "survey" in a])
    first, other = (dewatered, water) if mode != "3dgs" else (water, shade)

    page = flow.page
    page.goto(f"{live.url}/jobs/{flow.job_id}")
    page.wait_for_selector("#job-summary[data-state=done]")
    page.click(".tabs [data-tab=survey]")  # waits for the tab to appear (the artifact list has the products)
    v0 = smap.wait_shows(page, first)
    size = _preview_size(live, artifacts[first])
    assert (v0["w"], v0["h"]) == size and 0 < max(size) <= 2048 and v0["src"].startswith("blob:")
    box = page.locator(smap.VIEWPORT).bounding_box()
    assert v0["scale"] * v0["w"] <= box["width"] + 0.5 and v0["scale"] * v0["h"] <= box["height"] + 0.5  # fitted
    _check_survey_facts(page, survey)
    _check_scale_bar(page, survey, v0["box"][0], v0["scale"])
    if mode == "3dgs":
        assert page.is_disabled("#survey-map input[name=smap-layer][value=dewatered]")
        assert "3dgs" in page.inner_text("#survey-map [data-why]")

    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx + 90, cy + 60, steps=6)
    page.mouse.up()
    v1 = smap.wait_view_change(page, "the drag to pan the map", v0, "transform")
    assert v1["scale"] == v0["scale"]
    assert (v1["x"] - v0["x"], v1["y"] - v0["y"]) == (pytest.approx(90, abs=1), pytest.approx(60, abs=1))

    px, py = cx + 40, cy - 30
    page.mouse.move(px, py)
    page.mouse.wheel(0, -360)
    v2 = smap.wait_view_change(page, "the wheel to zoom the map", v1, "scale")
    assert v2["scale"] > v1["scale"]
    under = [((px - box["x"] - v["x"]) / v["scale"], (py - box["y"] - v["y"]) / v["scale"]) for v in (v1, v2)]
    assert under[1] == (pytest.approx(under[0][0], abs=0.5), pytest.approx(under[0][1], abs=0.5))  # around the cursor
    _check_scale_bar(page, survey, v2["box"][0], v2["scale"])
    shot(page, "dashboard-survey-map")

    for path in (other, shade) if other != shade else (other,):
        before = smap.view(page)
        key = {water: "water", shade: "elevation"}[path]
        page.check(f"#survey-map input[name=smap-layer][value={key}]")
        after = smap.wait_shows(page, path)
        assert after["src"] != before["src"] and after["src"].startswith("blob:")
        assert (after["transform"], after["box"]) == (before["transform"], before["box"]), path  # the same view
    assert (smap.view(page)["w"], smap.view(page)["h"]) == _preview_size(live, artifacts[shade])

    page.click("#survey-map button[data-zoom='fit']")
    v3 = smap.wait_view_change(page, "reset to fit the map again", v2, "transform")
    assert [v3["scale"], v3["x"], v3["y"]] == pytest.approx([v0["scale"], v0["x"], v0["y"]])

    tif = rel(layout.dem)
    with page.expect_download() as dl:
        page.click(f"#survey-map button[data-path='{tif}']")
    assert hashlib.sha256(Path(dl.value.path()).read_bytes()).hexdigest() == artifacts[tif]["sha256"]
    assert dl.value.suggested_filename == layout.dem.name


@pytest.mark.timeout(60)
def test_another_owners_job_is_not_found(live, flow):
    page = flow.page
    page.click("nav a[data-nav=jobs]")
    page.wait_for_selector(f"#jobs-body tr[data-job='{flow.job_id}']")
    assert page.query_selector(f"#jobs-body tr[data-job='{flow.bob_job}']") is None
    page.fill("#open-job-id", flow.bob_job)
    page.click("#open-job button")
    page.wait_for_selector("#job-error:not([hidden])")
    assert page.inner_text("#job-title") == "Job not found"
    assert "another API key" in page.inner_text("#job-error")
    assert not page.is_visible("#job-body")
    page.goto(f"{live.url}/jobs/{flow.bob_job}")  # typed into the address bar: same answer
    page.wait_for_selector("#job-error:not([hidden])")
    assert page.inner_text("#job-title") == "Job not found"


@pytest.mark.timeout(60)
def test_delete_from_the_job_page(live, flow):
    """Delete (after the browser's confirm) removes the job: gone from the list, 404 from the API."""
    page = flow.page
    page.goto(f"{live.url}/jobs/{flow.job_id}")
    page.wait_for_selector("#job-summary[data-state=done]")
    page.once("dialog", lambda d: d.accept())
    page.click("#job-delete")
    page.wait_for_selector("#view-jobs:not([hidden])")
    wait_js(page, "the job to leave the list", "id => !document.querySelector(`#jobs-body tr[data-job='${id}']`)",
            arg=flow.job_id)
    with live.client("alice") as c:
        r = c.get(f"/v1/jobs/{flow.job_id}")
    assert r.status_code == 404 and r.json()["error"]["code"] == "job_not_found"


@pytest.mark.timeout(60)
def test_key_never_in_a_url_and_nothing_leaves_the_service(live, flow, rec):
    assert rec.urls, "no request recorded"
    for key in (*KEYS.values(), WRONG_KEY):
        leaked = [u for u in rec.urls if key in u]
        assert not leaked, f"the key appears in {leaked[:3]}"
    hosts = {urlsplit(u).netloc for u in rec.urls if urlsplit(u).scheme in ("http", "https")}
    assert hosts == {urlsplit(live.url).netloc}, hosts
    assert rec.api_auth and all(ok for _, ok in rec.api_auth), [p for p, ok in rec.api_auth if not ok][:5]
    METRICS["dashboard requests recorded"] = str(len(rec.urls))


@pytest.mark.timeout(60)
def test_sign_out_forgets_the_key(live, flow):
    page = flow.page
    page.click("#signout")
    page.wait_for_selector("#view-signin:not([hidden])")
    assert page.evaluate("Object.keys(sessionStorage).length") == 0
    page.reload()
    page.wait_for_selector("#view-signin:not([hidden])")


@pytest.mark.timeout(120)
def test_surveys_page_registers_scans_and_shows_waiting_sets(live, browser, flow, scene_images):
    """A survey folder with one set of 2 images (below the live stack's minimum of 4): registered through the page,
    scanned with "Scan now" (the worker runs the scan), and shown waiting with its reason. No job is started."""
    folder = live.survey_root / "dash-survey"
    (folder / "dive-01").mkdir(parents=True)
    for p in scene_images[:2]:
        (folder / "dive-01" / p.name).write_bytes(p.read_bytes())
    ctx = browser.new_context()
    try:
        page = ctx.new_page()
        page.goto(live.url + "/surveys")
        sign_in(page, KEYS["alice"])
        page.wait_for_selector("#view-surveys:not([hidden])")
        page.fill("#survey-form [name=path]", str(folder))
        page.fill("#survey-form [name=name]", "dash-survey")
        page.fill("#survey-form [name=interval_s]", "3600")
        page.click("#survey-form button[type=submit]")
        page.wait_for_selector("#survey-msg:text('Registered dash-survey')")
        card = page.locator("[data-survey]", has_text="dash-survey")
        card.locator("button", has_text="Scan now").click()
        card.locator("li", has_text="too_few_images").wait_for(timeout=60_000)
        assert "dive-01: 2 images" in card.locator("li").first.inner_text()
        shot(page, "dashboard-surveys")
        page.fill("#survey-form [name=path]", "/etc")
        page.click("#survey-form button[type=submit]")
        page.wait_for_selector("#survey-msg:text-matches('Refused: .*path_not_allowed')")
    finally:
        ctx.close()
