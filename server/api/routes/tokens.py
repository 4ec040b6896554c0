"""``/tokens`` (admin): list, create and revoke REST access tokens.

A new token is in the answer to its ``POST`` only; the server keeps its SHA-256
(:mod:`server.tokens`). Revoking is immediate (every request looks its token up) and final; the
record stays listed with ``revoked_ns`` so its use can still be traced. A token created with
``expires_in_s`` is refused from ``expires_ns`` on, like a revoked one. Creating and revoking go
through the runtime's single store writer.
"""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, Body, Depends, Path, Response, status
from pydantic import BaseModel, Field

from server.api.deps import StoreDep, WriterDep, require_role
from server.api.errors import NotFound, error_responses
from server.storage.base import TokenRecord
from server.tokens import MAX_LIFETIME_S, Role, issue_token

__all__ = ["TokenCreate", "TokenCreated", "TokenPublic", "TokensPublic", "router"]

router = APIRouter(
    prefix="/tokens", tags=["tokens"], dependencies=[Depends(require_role(Role.ADMIN))]
)


class TokenCreate(BaseModel):
    """A token to create."""

    name: str = Field(
        min_length=1,
        max_length=100,
        pattern=r"^[^\x00-\x1f\x7f]+$",
        description="whom or what the token is for, e.g. `grafana` or `alice`",
    )
    role: Role = Field(description="viewer (read) < operator (vehicle configs) < admin (all)")
    expires_in_s: int | None = Field(
        default=None,
        strict=True,  # JSON true is not a lifetime of 1 s
        ge=1,
        le=MAX_LIFETIME_S,
        description="lifetime in seconds from now (at most ten years); null: never expires",
    )


class TokenPublic(BaseModel):
    """A token as stored (never the token itself). Times: int ns since the epoch, UTC."""

    id: int
    name: str
    role: Role
    created_ns: int
    last_used_ns: int | None = Field(description="last use, to within a minute; null: never")
    revoked_ns: int | None = Field(description="when it was revoked; null: not revoked")
    expires_ns: int | None = Field(default=None, description="when it expires; null: never")


class TokenCreated(TokenPublic):
    """The new token's record and the token, shown this once."""

    token: str = Field(description="send as `Authorization: Bearer <token>`; not kept anywhere")


class TokensPublic(BaseModel):
    """Every token, revoked ones included, by id."""

    data: list[TokenPublic]
    count: int


def _public(record: TokenRecord) -> TokenPublic:
    return TokenPublic(
        id=record.id,
        name=record.name,
        role=Role(record.role),
        created_ns=record.created_ns,
        last_used_ns=record.last_used_ns,
        revoked_ns=record.revoked_ns,
        expires_ns=record.expires_ns,
    )


@router.get(
    "",
    response_model=TokensPublic,
    responses=error_responses(401, 403),
    summary="List access tokens (admin)",
)
def list_tokens(store: StoreDep) -> TokensPublic:
    tokens = [_public(r) for r in store.list_tokens()]
    return TokensPublic(data=tokens, count=len(tokens))


@router.post(
    "",
    response_model=TokenCreated,
    status_code=status.HTTP_201_CREATED,
    responses=error_responses(400, 401, 403, 413, 422),
    summary="Create an access token (admin); the answer is the only place it appears",
)
def create_token(body: Annotated[TokenCreate, Body()], writer: WriterDep) -> TokenCreated:
    lifetime_ns = None if body.expires_in_s is None else body.expires_in_s * 1_000_000_000
    token, record = writer.call(
        lambda s: issue_token(s, body.name, body.role, time.time_ns(), lifetime_ns)
    )
    return TokenCreated(**_public(record).model_dump(), token=token)


@router.delete(
    "/{token_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses=error_responses(401, 403, 404),
    summary="Revoke an access token (admin); takes effect on the next request",
)
def revoke_token(token_id: Annotated[int, Path(ge=1, le=2**63 - 1)], writer: WriterDep) -> Response:
    if writer.call(lambda s: s.revoke_token(token_id, time.time_ns())) is None:
        raise NotFound(f"unknown token {token_id}")
    return Response(status_code=status.HTTP_204_NO_CONTENT)
