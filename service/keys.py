"""API keys: scopes, secrets and their hashes.

A key is ``csk_`` + 32 random bytes (URL-safe base64). Only its sha256 is stored;
comparisons of hashes are constant-time. A scope includes the ones before it:
``read`` < ``write`` < ``admin``.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from typing import Literal, get_args

Scope = Literal["read", "write", "admin"]
SCOPES: tuple[str, ...] = get_args(Scope)
"""From weakest to strongest: a scope allows everything the ones before it allow."""

KEY_PREFIX = "csk_"


def allows(granted: str, needed: str) -> bool:
    """Whether a key of scope `granted` may do what needs scope `needed`."""
    return SCOPES.index(granted) >= SCOPES.index(needed)


def new_key() -> str:
    """A fresh secret key (shown once to its creator, never stored)."""
    return KEY_PREFIX + secrets.token_urlsafe(32)


def new_key_id() -> str:
    """The public id of a key (names it in GET and DELETE)."""
    return secrets.token_hex(8)


def key_hash(key: str) -> str:
    """sha256 of the key, hex: what the store keeps."""
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).hexdigest()


def same_hash(a: str, b: str) -> bool:
    """Constant-time equality of two hashes."""
    return hmac.compare_digest(a.encode(), b.encode())
