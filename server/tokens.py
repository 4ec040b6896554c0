"""REST access tokens: roles, generation and hashing (pure, no I/O).

A token is ``sft_`` followed by 43 URL-safe base64 characters: 32 bytes (256 bits) from
:mod:`secrets`. It is shown once when created; the store keeps only its SHA-256
(:func:`hash_token`).

Why a plain SHA-256 and not a password KDF (bcrypt, scrypt, Argon2): a KDF's deliberate slowness
protects *low-entropy* secrets chosen by people against guessing after a database leak. A token
here is 256 random bits; guessing one from its hash is as hard as guessing the token itself, so
slowing each guess down buys nothing. A fast, unsalted hash in turn lets every request find its
token with one indexed lookup (``token_sha256`` is unique) and costs microseconds, not the tens of
milliseconds per request a KDF would add.

Roles are ordered: ``viewer`` (read) < ``operator`` (also change vehicle configs) < ``admin``
(also delete vehicles, manage tokens). A role admits everything a lower one does.
"""

from __future__ import annotations

import hashlib
import re
import secrets
from enum import StrEnum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.storage.base import Store, TokenRecord

__all__ = [
    "TOKEN_PREFIX",
    "Role",
    "generate_token",
    "hash_token",
    "is_well_formed",
    "issue_token",
]

TOKEN_PREFIX = "sft_"
_TOKEN_BYTES = 32
_TOKEN_RE = re.compile(r"sft_[A-Za-z0-9_\-]{43}")


class Role(StrEnum):
    """What a token may do; compare with :meth:`admits`."""

    VIEWER = "viewer"
    OPERATOR = "operator"
    ADMIN = "admin"

    @property
    def rank(self) -> int:
        return _RANK[self]

    def admits(self, needed: Role | str) -> bool:
        """True when a holder of this role may do what ``needed`` allows."""
        return self.rank >= Role(needed).rank


_RANK = {Role.VIEWER: 0, Role.OPERATOR: 1, Role.ADMIN: 2}


def generate_token() -> str:
    """A new token: ``sft_`` + 256 random bits, URL-safe base64 (no padding)."""
    return TOKEN_PREFIX + secrets.token_urlsafe(_TOKEN_BYTES)


def is_well_formed(token: str) -> bool:
    """True when ``token`` has the shape :func:`generate_token` produces (cheap check before
    any database lookup; says nothing about validity)."""
    return _TOKEN_RE.fullmatch(token) is not None


def hash_token(token: str) -> str:
    """Hex SHA-256 of the token's UTF-8 bytes: what the store keeps and looks up."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def issue_token(store: Store, name: str, role: Role | str, now_ns: int) -> tuple[str, TokenRecord]:
    """Create a token in ``store``: returns the token (show it once, it is not kept) and its
    record. ``name`` says whom or what it is for; ``role`` is checked here."""
    token = generate_token()
    record = store.create_token(name, Role(role).value, hash_token(token), now_ns)
    return token, record
