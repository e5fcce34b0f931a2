"""The client's one error type, in a module of its own so the commands can catch it without importing httpx
(``service.client.remote``, the only module that needs httpx, raises it)."""

from __future__ import annotations


class ClientError(Exception):
    """A request that did not succeed. ``status`` is the HTTP status (0: no answer); ``code`` the service's error
    code, or one of ``connection_failed``, ``timeout``, ``transport_error``, ``bad_response``."""

    def __init__(self, status: int, code: str, message: str):
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
