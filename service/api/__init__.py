"""The HTTP layer: routers, dependencies, request and response schemas, error handling."""
