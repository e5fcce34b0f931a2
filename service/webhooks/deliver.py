"""One attempt at a webhook delivery: the body of the ``dualphys.deliver_webhook`` task, kept out of Celery so it
can be tested directly (tests/service/test_webhooks.py).

The manifest is the truth about a delivery: its attempt count decides the next backoff and when to give up, so a
redelivered task message carries on where the last attempt left off instead of starting over. An attempt holds a
short Redis claim (``Coordinator.webhook_claim``): a duplicated message never sends at the same time, and a
message for a delivery that is no longer pending is dropped. No redirect is followed (it could lead off the
allowed hosts); any 2xx is success, anything else (or no answer within ``webhook_timeout_s``) a failed attempt.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import httpx

from service.core.settings import Settings
from service.jobs.manifest import Manifest, WebhookDelivery
from service.jobs.store import JobNotFound

from .callback import CallbackRefused, check_callback_url
from .signing import SIGNATURE_HEADER, sign

log = logging.getLogger(__name__)

USER_AGENT = "dualphys-webhook/1"


@dataclass(frozen=True)
class AttemptOutcome:
    status: str  # delivered | retry | given_up | dropped
    retry_after: float | None = None
    detail: str = ""


def backoff_s(settings: Settings, attempts_made: int) -> float:
    """Wait after the ``attempts_made``-th failed attempt: base, 2x base, 4x base, ... capped."""
    return min(settings.webhook_backoff_max_s, settings.webhook_backoff_s * 2 ** max(0, attempts_made - 1))


def headers_for(d: WebhookDelivery, secret: str, attempt: int) -> dict[str, str]:
    body = d.body.encode()
    return {
        "Content-Type": "application/json",
        "User-Agent": USER_AGENT,
        SIGNATURE_HEADER: sign(secret, body),
        "X-Dualphys-Event": d.event,
        "X-Dualphys-Delivery": d.id,
        "X-Dualphys-Attempt": str(attempt),
        "X-Dualphys-Timestamp": str(int(time.time())),
    }


def _read_pending(rt, job_id: str, delivery_id: str):
    """(manifest, its pending delivery record), or (why not, None) when the job is gone or the delivery is no
    longer pending (delivered or given up)."""
    try:
        m = rt.store.read(job_id)
    except JobNotFound:
        return "job deleted", None
    rec = _pending(m, delivery_id)
    return (m, rec) if rec is not None else ("delivery not pending (delivered or given up)", None)


def deliver(rt, job_id: str, delivery_id: str, client: httpx.Client | None = None) -> AttemptOutcome:
    """Make the next attempt of delivery ``delivery_id`` of job ``job_id`` and record it.

    ``rt`` is the composed components (``service.compose.Components``): settings, store, coordinator."""
    settings: Settings = rt.settings
    with rt.coord.webhook_claim(delivery_id, settings.webhook_timeout_s * 2 + 30) as got:
        if not got:
            return AttemptOutcome("dropped", detail="another attempt of this delivery is under way")
        first, d = _read_pending(rt, job_id, delivery_id)
        if d is None:
            return AttemptOutcome("dropped", detail=f"{first} (before the attempt)")
        attempt = d.attempts + 1
        code, error, final = _attempt(settings, first.owner, d, attempt, client)
        with rt.coord.manifest_mutex(job_id):  # read again: the manifest may have changed during the attempt
            m, rec = _read_pending(rt, job_id, delivery_id)
            if rec is None:
                return AttemptOutcome("dropped", detail=f"{m} (after the attempt)")
            now = time.time()
            rec.attempts, rec.last_attempt_at, rec.last_status_code, rec.last_error = attempt, now, code, error
            if error is None:
                rec.status, rec.finished_at = "delivered", now
                out = AttemptOutcome("delivered", detail=f"HTTP {code}")
            elif final or attempt >= settings.webhook_max_attempts:
                rec.status, rec.finished_at = "given_up", now
                out = AttemptOutcome("given_up", detail=error)
            else:
                out = AttemptOutcome("retry", retry_after=backoff_s(settings, attempt), detail=error)
            rt.store.write(m)
    log.info("job %s webhook %s (%s) attempt %d: %s %s", job_id, delivery_id, d.event, attempt, out.status,
             out.detail)
    return out


def _pending(m: Manifest, delivery_id: str) -> WebhookDelivery | None:
    return next((d for d in m.webhooks if d.id == delivery_id and d.status == "pending"), None)


def _attempt(settings: Settings, owner: str, d: WebhookDelivery, attempt: int,
             client: httpx.Client | None) -> tuple[int | None, str | None, bool]:
    """(the receiver's HTTP status or None, None on success else why, final). ``final``: refused here and never
    retried, because the settings no longer allow the URL or the owner has no secret any more."""
    secret = settings.webhook_secret(owner)
    try:
        check_callback_url(d.url, settings.webhook_allowed_hosts, secret is not None)
    except CallbackRefused as e:
        return None, f"{e.code}: {e}", True
    assert secret is not None
    own = client is None
    http = client or httpx.Client(timeout=settings.webhook_timeout_s, follow_redirects=False, trust_env=False)
    try:
        r = http.post(d.url, content=d.body.encode(), headers=headers_for(d, secret, attempt))
    except httpx.HTTPError as e:
        return None, f"{type(e).__name__}: {e}"[:300], False
    finally:
        if own:
            http.close()
    if 200 <= r.status_code < 300:
        return r.status_code, None, False
    return r.status_code, f"HTTP {r.status_code}", False
