"""The Celery worker (``celery -A worker.app``): one task per pipeline stage, survey scans for beat.
See docs/SERVICE.md."""
