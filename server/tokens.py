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
    "MAX_LIFETIME_S",
    "TOKEN_PREFIX",
    "Role",
    "generate_token",
    "hash_token",
    "is_well_formed",
    "issue_token",
    "parse_lifetime_ns",
]

TOKEN_PREFIX = "sft_"
_TOKEN_BYTES = 32
_TOKEN_RE = re.compile(r"sft_[A-Za-z0-9_\-]{43}")
_LIFETIME_RE = re.compile(r"([1-9][0-9]{0,9})([smhdw])")
_UNIT_S = {"s": 1, "m": 60, "h": 3_600, "d": 86_400, "w": 604_800}
_NS_PER_S = 1_000_000_000

#: Longest lifetime a token may be given: ten years of 366 days, in seconds.
MAX_LIFETIME_S = 10 * 366 * 86_400


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


def parse_lifetime_ns(text: str) -> int:
    """A token lifetime such as ``90s``, ``30m``, ``12h``, ``7d`` or ``2w`` in integer ns.

    Raises ValueError for any other shape and for more than :data:`MAX_LIFETIME_S`.
    """
    match = _LIFETIME_RE.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"{text!r} is not a lifetime like 90s, 30m, 12h, 7d or 2w")
    seconds = int(match.group(1)) * _UNIT_S[match.group(2)]
    if seconds > MAX_LIFETIME_S:
        raise ValueError(f"{text!r} is longer than ten years")
    return seconds * _NS_PER_S


def issue_token(
    store: Store, name: str, role: Role | str, now_ns: int, expires_in_ns: int | None = None
) -> tuple[str, TokenRecord]:
    """Create a token in ``store``: returns the token (show it once, it is not kept) and its
    record. ``name`` says whom or what it is for; ``role`` is checked here; ``expires_in_ns``
    (> 0, or None: never) sets the expiry to ``now_ns + expires_in_ns``."""
    if expires_in_ns is not None and not 0 < expires_in_ns <= MAX_LIFETIME_S * _NS_PER_S:
        raise ValueError(f"a token's lifetime must be in (0, 10 years], not {expires_in_ns} ns")
    expires_ns = None if expires_in_ns is None else now_ns + expires_in_ns
    token = generate_token()
    record = store.create_token(name, Role(role).value, hash_token(token), now_ns, expires_ns)
    return token, record
