"""The HTTP service: FastAPI app (``service.app:create_app``), settings, job store, uploads, surveys, and the
embedded runner (``service.embedded.serve``). See docs/SERVICE.md."""
