"""One router per resource: jobs, artifacts, surveys, health."""
