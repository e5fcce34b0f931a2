"""Which callback URLs a job may carry: http(s), no credentials in the URL, a host on the deployment's allow list,
and an owner that has a signing secret. Checked at upload and again before every delivery (the settings may have
changed since), so the worker only ever connects to hosts the operator allowed."""

from __future__ import annotations

from urllib.parse import urlsplit

MAX_URL_LENGTH = 2048


class CallbackRefused(ValueError):
    """A callback URL the service will not call; ``code`` is the API's error code."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def check_callback_url(url: str, allowed_hosts: list[str], has_secret: bool) -> str:
    """``url`` unchanged if it may be called, else :class:`CallbackRefused`:

    - ``callbacks_disabled``: the deployment allows no host (``webhook_allowed_hosts`` empty);
    - ``invalid_callback``: not an absolute http(s) URL with a host, credentials in it, a bad port, too long;
    - ``callback_not_allowed``: its host is not one of ``allowed_hosts`` (exact, case-insensitive names; a
      ``.example.org`` entry allows every host under example.org);
    - ``callback_no_secret``: the owner has no signing secret (``webhook_secrets``), so nothing could be signed.
    """
    if not allowed_hosts:
        raise CallbackRefused("callbacks_disabled", "this server sends no webhooks (no callback host is allowed)")
    if len(url) > MAX_URL_LENGTH or any(c.isspace() or ord(c) < 0x20 for c in url):
        raise CallbackRefused("invalid_callback", f"callback_url must be one URL of at most {MAX_URL_LENGTH} "
                                                  "characters without spaces")
    try:
        parts = urlsplit(url)
        port = parts.port  # raises ValueError for a port that is not a number in 0-65535
    except ValueError as e:
        raise CallbackRefused("invalid_callback", f"callback_url does not parse: {e}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise CallbackRefused("invalid_callback", "callback_url must be an absolute http:// or https:// URL")
    if parts.username is not None or parts.password is not None:
        raise CallbackRefused("invalid_callback", "callback_url must not carry credentials (the body is signed)")
    if port == 0:
        raise CallbackRefused("invalid_callback", "callback_url has port 0")
    if not host_allowed(parts.hostname, allowed_hosts):
        raise CallbackRefused("callback_not_allowed", f"callback host {parts.hostname!r} is not allowed on this "
                                                      f"server (allowed: {', '.join(allowed_hosts)})")
    if not has_secret:
        raise CallbackRefused("callback_no_secret", "your key has no webhook signing secret on this server; ask "
                                                    "its operator for one")
    return url


def host_allowed(host: str, allowed_hosts: list[str]) -> bool:
    """``host`` (as urlsplit gives it: lower case, IPv6 without brackets) is on the list."""
    host = host.lower().rstrip(".")
    for entry in allowed_hosts:
        e = entry.lower().strip().strip("[]").rstrip(".")
        if e.startswith("."):
            if host.endswith(e) and len(host) > len(e):
                return True
        elif host == e:
            return True
    return False
