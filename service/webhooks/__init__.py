"""Webhooks: a job may carry a callback URL; when a run of it ends (done / failed / cancelled) the service POSTs
one signed JSON event there, from a Celery task on the light ``surveys`` queue, with retries and backoff.

- ``callback``: the URL check at upload (allowed hosts, an owner secret) -> 422 ``callback_*``;
- ``signing``: ``X-Dualphys-Signature: sha256=<hex HMAC-SHA256 of the raw body>`` and its verification;
- ``events``: the delivery record planned in the manifest, under its mutex, in the same write that ends the run
  (so one event per run and terminal state, whoever ends it and however often a message is redelivered);
- ``deliver``: one attempt of a delivery (the task's body), recorded in the manifest.
"""
