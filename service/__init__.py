"""The HTTP service: FastAPI app (``service.app:create_app``), the composition root (``service.compose``),
settings, job store, uploads, surveys, and the embedded runner (``service.embedded.serve``). Imports nothing from
``worker``: the worker's Celery app is handed in. See docs/SERVICE.md."""
