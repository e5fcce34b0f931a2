"""The Celery worker: one task per pipeline stage. Built in the service issue."""
