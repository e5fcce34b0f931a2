"""The HTTP service (FastAPI). Built in the service issue; see DESIGN.md "Service and worker"."""
