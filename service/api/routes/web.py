"""The dashboard: ``GET /`` and its client-side routes serve one HTML shell (no key needed: the page holds no
data; everything it shows comes from ``/v1`` with the key the user types in), ``/static`` its scripts and
styles. The page's Content-Security-Policy allows only this origin (no CDN, no remote fonts) plus ``blob:``/
``data:`` images (authenticated downloads are shown as blob URLs; the report inlines its plots)."""

from __future__ import annotations

from fastapi import APIRouter, FastAPI
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from service.web.page import STATIC_DIR, render_index

router = APIRouter(tags=["dashboard"], include_in_schema=False)

# 'wasm-unsafe-eval' and blob:/data: workers: the 3D viewer bundle (static/viewer/) compiles WebAssembly and starts
# workers from blob: and data: URLs; nothing else is loosened. The report is shown in a sandboxed srcdoc iframe
# without scripts.
CSP = ("default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; worker-src 'self' blob: data:; "
       "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; connect-src 'self' blob: data:; "
       "font-src 'self'; frame-src 'self' blob:; object-src 'none'; base-uri 'none'; form-action 'none'; "
       "frame-ancestors 'none'")
PAGE_HEADERS = {"Content-Security-Policy": CSP, "Referrer-Policy": "no-referrer",
                "X-Content-Type-Options": "nosniff", "Cache-Control": "no-cache"}


def _page() -> HTMLResponse:
    return HTMLResponse(render_index(), headers=PAGE_HEADERS)


@router.get("/", response_class=HTMLResponse)
def index() -> HTMLResponse:
    return _page()


@router.get("/jobs", response_class=HTMLResponse)
def jobs_page() -> HTMLResponse:
    return _page()


@router.get("/jobs/{job_id}", response_class=HTMLResponse)
def job_page(job_id: str) -> HTMLResponse:
    return _page()


@router.get("/surveys", response_class=HTMLResponse)
def surveys_page() -> HTMLResponse:
    return _page()


def mount_dashboard(app: FastAPI) -> None:
    """The page routes and ``/static`` (the package's ``service/web/static``)."""
    app.include_router(router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR, check_dir=True), name="static")
