"""The dashboard's page and static files, in-process (no worker, no browser): served without a key, with a strict
Content-Security-Policy, the job options form built from the API's options, and nothing loaded from elsewhere
(survey vessels are offline). The browser test is test_dashboard.py."""

from __future__ import annotations

import re

import pytest

from pipeline.job.layout import JobLayout
from service.jobs.options import CLIENT_OPTIONS
from service.web.page import STATIC_DIR

PAGES = ["/", "/jobs", "/jobs/j-anything", "/surveys"]


@pytest.mark.parametrize("path", PAGES)
def test_pages_serve_the_shell_without_a_key(api, path):
    r = api.get(path)
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/html")
    csp = r.headers["content-security-policy"]
    assert "default-src 'self'" in csp and "frame-ancestors 'none'" in csp
    assert r.headers["referrer-policy"] == "no-referrer"
    assert '<script type="module" src="/static/app.js">' in r.text


def test_options_form_offers_every_client_option(api):
    html = api.get("/").text
    names = re.findall(r'name="([a-z_]+)"', html.split('<div class="options">')[1].split("</div>")[0])
    assert names == [*CLIENT_OPTIONS, "callback_url"]  # the webhook URL rides beside the options
    assert '<option value="fast" selected>fast</option>' in html


def test_static_files_are_served_and_local_only(api):
    files = sorted(p for p in STATIC_DIR.rglob("*") if p.is_file() and "viewer" not in p.parts)
    assert {p.name for p in files} >= {"app.js", "api.js", "job.js", "jobs.js", "surveys.js", "ui.js", "zip.js",
                                       "dashboard.css"}
    for p in files:
        r = api.get(f"/static/{p.relative_to(STATIC_DIR).as_posix()}")
        assert r.status_code == 200, p
        # no CDN, no remote font, no absolute URL of any kind
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}/", r.text, re.I), p
    assert api.get("/static/nope.js").status_code == 404


def test_the_api_still_wants_a_key(api):
    r = api.get("/v1/jobs")
    assert r.status_code == 401
    assert r.json()["error"]["code"] == "unauthorized"


def test_survey_map_spells_the_layouts_names():
    """surveymap.js names the survey stage's files in JavaScript; they are JobLayout's (pipeline/job/layout.py)."""
    js = (STATIC_DIR / "surveymap.js").read_text(encoding="utf-8")
    layout = JobLayout("job")
    assert f'const DIR = "{layout.relative(layout.survey)}/";' in js
    assert f'const RESULT = "{layout.relative(layout.survey_result)}";' in js
    assert f'const REPORT = "{layout.relative(layout.report_json)}";' in js
    for p in (layout.ortho, layout.ortho_water, layout.ortho_confidence, layout.dem, layout.ortho_preview,
              layout.ortho_water_preview, layout.hillshade_preview):
        assert f"`${{DIR}}{p.name}`" in js, p.name
