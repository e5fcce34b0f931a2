"""A job as the service keeps it: ``manifest`` (the truth about a job), ``store`` (job folders on disk), ``ops``
(create and dispatch, cancel, retry, delete, the status view), ``intake`` (a job from an upload: ``uploads``
streams the body, ``idempotency`` records repeat keys, ``options`` checks what a client may set), ``artifacts``
and ``previews`` (what a job hands out) and ``redact`` (no server path reaches a client)."""
