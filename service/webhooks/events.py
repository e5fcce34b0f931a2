"""The event a run's end produces, planned in the manifest in the same locked write that ends the run.

Every place that makes a job terminal (the worker's stage end, a cancel of a job with no stage running, a broker
failure at dispatch) calls :func:`plan_event` on the manifest it is about to write, under the job's manifest
mutex. A run ends once and a delivery is planned only if none exists for (run, state), so a redelivered stage
message, a retried stage or two API processes cannot plan two events for one run; the sender
(``service.webhooks.deliver``) then owns the attempts.
"""

from __future__ import annotations

import json
import secrets
import time

from service.jobs.manifest import TERMINAL_STATES, Manifest, WebhookDelivery


def event_name(state: str) -> str:
    return f"job.{state}"


def plan_event(m: Manifest) -> WebhookDelivery | None:
    """Append the delivery announcing the end of ``m``'s current run to ``m.webhooks`` and return it; None when
    the job has no callback, is not terminal, or this run's end already has its delivery."""
    if m.callback_url is None or m.state not in TERMINAL_STATES:
        return None
    if any(d.run_id == m.run_id and d.state == m.state for d in m.webhooks):
        return None
    now = time.time()
    delivery_id = "d" + secrets.token_hex(8)
    run = m.current_run
    body = {
        "event": event_name(m.state),
        "delivery_id": delivery_id,
        "job_id": m.id,
        "run_id": m.run_id,
        "state": m.state,
        "error": m.error.model_dump() if m.error is not None else None,
        "message": m.message,
        "finished_at": run.finished_at if run is not None and run.finished_at is not None else now,
        "survey_id": m.survey_id,
        "links": {  # relative to the API's base URL; every one needs the owner's key
            "job": f"/v1/jobs/{m.id}",
            "log": f"/v1/jobs/{m.id}/log",
            "artifacts": f"/v1/jobs/{m.id}/artifacts",
            "bundle": f"/v1/jobs/{m.id}/bundle",
        },
    }
    d = WebhookDelivery(id=delivery_id, event=body["event"], run_id=m.run_id, state=m.state, url=m.callback_url,
                        created_at=now, body=json.dumps(body, separators=(",", ":"), sort_keys=True))
    m.webhooks.append(d)
    return d
