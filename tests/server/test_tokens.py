"""Token generation, hashing and the role order (pure)."""

from __future__ import annotations

import hashlib

import pytest

from server.tokens import TOKEN_PREFIX, Role, generate_token, hash_token, is_well_formed


def test_tokens_are_random_well_formed_and_long() -> None:
    tokens = {generate_token() for _ in range(200)}
    assert len(tokens) == 200
    for t in tokens:
        assert t.startswith(TOKEN_PREFIX)
        assert len(t) == len(TOKEN_PREFIX) + 43  # 32 bytes, URL-safe base64 without padding
        assert is_well_formed(t)


@pytest.mark.parametrize(
    "text", ["", "sft_", "sft_abc", "xyz_" + "a" * 43, "sft_" + "a" * 42 + "!", "sft_" + "a" * 44]
)
def test_malformed_tokens(text: str) -> None:
    assert not is_well_formed(text)


def test_hash_is_sha256_hex() -> None:
    token = "sft_" + "A" * 43
    assert hash_token(token) == hashlib.sha256(token.encode()).hexdigest()
    assert hash_token(token) != hash_token(token[:-1] + "B")


def test_role_order() -> None:
    assert Role.ADMIN.admits(Role.OPERATOR) and Role.ADMIN.admits("viewer")
    assert Role.OPERATOR.admits(Role.VIEWER) and not Role.OPERATOR.admits(Role.ADMIN)
    assert Role.VIEWER.admits(Role.VIEWER) and not Role.VIEWER.admits(Role.OPERATOR)
    with pytest.raises(ValueError):
        Role.VIEWER.admits("root")
