"""The signature of a webhook body: ``sha256=<hex HMAC-SHA256(owner's secret, raw body)>``.

Receivers recompute it over the bytes they received (before any JSON parsing) and compare in constant time;
docs/SERVICE.md ("Webhooks") has the recipe.
"""

from __future__ import annotations

import hashlib
import hmac

SIGNATURE_HEADER = "X-Dualphys-Signature"
PREFIX = "sha256="


def sign(secret: str, body: bytes) -> str:
    """The header value for ``body``: ``sha256=`` + 64 hex digits."""
    return PREFIX + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


def verify(secret: str, body: bytes, header: str | None) -> bool:
    """True when ``header`` is the signature of ``body`` under ``secret`` (constant-time comparison)."""
    if not header or not header.startswith(PREFIX):
        return False
    return hmac.compare_digest(sign(secret, body).encode(), header.strip().encode())
