"""Typed calls to the dualphys API over httpx: the Bearer key on every request, the service's JSON errors
(``{"error": {"code", "message"}}``) and transport failures turned into :class:`ClientError`."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import httpx

from service.client.errors import ClientError

log = logging.getLogger(__name__)

SUBMIT_ANSWER_S = 1800.0
"""How long a submit waits for its answer once the body is sent: the API unpacks and decodes every image before it
answers (docs/SERVICE.md, "Creating a job"), minutes for a large survey set."""


@dataclass(frozen=True)
class Artifact:
    path: str
    size: int
    sha256: str
    url: str


def error_from_response(r: httpx.Response) -> ClientError:
    """The service's error body as a ClientError (a proxy's HTML page or an empty body still gives one)."""
    try:
        err = r.json()["error"]
        return ClientError(r.status_code, str(err["code"]), str(err["message"]))
    except (ValueError, KeyError, TypeError):
        text = r.text.strip().splitlines()[0][:200] if r.text.strip() else r.reason_phrase
        return ClientError(r.status_code, f"http_{r.status_code}", text)


class ServiceClient:
    """One server, one API key. ``timeout`` bounds connecting and each read/write (not a whole transfer)."""

    def __init__(self, server: str, key: str, timeout: float = 60.0, transport: httpx.BaseTransport | None = None):
        self.server = server.rstrip("/")
        self.timeout = timeout
        self._http = httpx.Client(base_url=self.server, headers={"Authorization": f"Bearer {key}"},
                                  timeout=httpx.Timeout(timeout, connect=min(timeout, 10.0)), transport=transport)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> ServiceClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ plumbing

    @contextmanager
    def _transport_errors(self) -> Iterator[None]:
        try:
            yield
        except httpx.ConnectError as e:
            raise ClientError(0, "connection_failed", f"cannot connect to {self.server} ({e})") from None
        except httpx.TimeoutException as e:
            raise ClientError(0, "timeout", f"{self.server} did not answer in time ({type(e).__name__})") from None
        except httpx.TransportError as e:
            raise ClientError(0, "transport_error", f"talking to {self.server} failed: {e}") from None

    def request(self, method: str, url: str, **kw: Any) -> httpx.Response:
        with self._transport_errors():
            r = self._http.request(method, url, **kw)
        if r.status_code >= 400:
            raise error_from_response(r)
        return r

    def json(self, method: str, url: str, **kw: Any) -> Any:
        r = self.request(method, url, **kw)
        try:
            return r.json()
        except ValueError:
            raise ClientError(r.status_code, "bad_response", f"{method} {url} did not answer JSON") from None

    @contextmanager
    def stream(self, url: str, headers: dict[str, str] | None = None) -> Iterator[httpx.Response]:
        """A GET whose body is read by the caller (``iter_bytes``); error answers are raised, read in full."""
        with self._transport_errors(), self._http.stream("GET", url, headers=headers or {}) as r:
            if r.status_code >= 400:
                r.read()
                raise error_from_response(r)
            yield r

    # ------------------------------------------------------------ the API

    def submit(self, body: Iterable[bytes], *, filename: str, content_type: str = "application/zip",
               length: int | None = None, options: dict[str, Any] | None = None,
               idempotency_key: str | None = None) -> dict:
        """POST /v1/jobs with the archive as the raw body and the options as query parameters. With ``length``
        the body goes with a Content-Length (the server can refuse an oversized one before reading); without,
        chunked. ``body`` is read once, as the request is sent."""
        params = {k: str(v) for k, v in (options or {}).items() if v is not None}
        params["filename"] = filename
        headers = {"Content-Type": content_type}
        if length is not None:
            headers["Content-Length"] = str(length)  # httpx then sends no Transfer-Encoding: chunked
        if idempotency_key:
            headers["Idempotency-Key"] = idempotency_key
        timeout = httpx.Timeout(self.timeout, connect=min(self.timeout, 10.0), read=max(self.timeout, SUBMIT_ANSWER_S))
        return self.json("POST", "/v1/jobs", params=params, content=body, headers=headers, timeout=timeout)

    def check(self) -> None:
        """One cheap authenticated request: a wrong key or an unreachable server is reported before an upload
        starts (a server that refuses a streamed body mid-way may reset the connection instead of answering)."""
        self.json("GET", "/v1/jobs", params={"limit": 1})

    def job(self, job_id: str) -> dict:
        return self.json("GET", f"/v1/jobs/{job_id}")

    def jobs(self, status: str | None = None, limit: int | None = None) -> list[dict]:
        """Your jobs, newest first: every page (or the first ``limit``)."""
        out: list[dict] = []
        offset: int | None = 0
        while offset is not None and (limit is None or len(out) < limit):
            page_size = 200 if limit is None else min(200, limit - len(out))
            params: dict[str, Any] = {"offset": offset, "limit": page_size}
            if status:
                params["status"] = status
            page = self.json("GET", "/v1/jobs", params=params)
            out += page["jobs"]
            offset = page.get("next_offset")
        return out

    def cancel(self, job_id: str) -> dict:
        return self.json("POST", f"/v1/jobs/{job_id}/cancel")

    def artifacts(self, job_id: str) -> list[Artifact]:
        data = self.json("GET", f"/v1/jobs/{job_id}/artifacts")
        return [Artifact(path=a["path"], size=int(a["size"]), sha256=a["sha256"], url=a["url"])
                for a in data["artifacts"]]
