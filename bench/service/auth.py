"""API tokens: random, shown once, stored as their SHA-256 only; roles viewer < operator < admin.

SHA-256 and not bcrypt/argon2: a token is 256 random bits from `secrets`, not a password a person chose, so there
is nothing to slow a guesser down for; a fast hash also lets every request look its token up by index.
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass

import anyio
from sqlalchemy import select

from bench.service.db import Database, Token
from bench.service.fresh import FreshCache

ROLES = ("viewer", "operator", "admin")
TOKEN_PREFIX = "dbt_"          # recognisable in a leaked log or a secret scanner
COOKIE = "drivebench_token"
CACHE_S = 2.0                  # a revoked token stops working within this


@dataclass(frozen=True)
class Principal:
    token_id: int
    name: str
    role: str

    def at_least(self, role: str) -> bool:
        return ROLES.index(self.role) >= ROLES.index(role)


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def new_token() -> str:
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def create_token(db: Database, name: str, role: str) -> tuple[int, str]:
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    token = new_token()
    with db.session() as s:
        row = Token(name=name, role=role, sha256=hash_token(token))
        s.add(row)
        s.flush()
        return row.id, token


class TokenCache:
    """Looks tokens up by hash; the API answers from memory for CACHE_S so that a busy API does not hit the database
    for every request: the fifty requests in flight when a token's answer expires share one read, and a token in
    use is read again in the background before then (bench.service.fresh). A revocation through this service
    forgets every answer at once."""

    def __init__(self, db: Database):
        self.db = db
        self._revocations = 0
        self._answers: FreshCache[Principal | None] = FreshCache(CACHE_S, 10_000)

    async def resolve(self, token: str) -> Principal | None:
        """For the event loop: from memory, or one read on a worker thread."""
        digest = hash_token(token)
        return await self._answers.get(digest, self._revocations,
                                       lambda: anyio.to_thread.run_sync(self._read, digest))

    def lookup(self, token: str | None) -> Principal | None:
        """For a worker thread (the login form): from the database."""
        return self._read(hash_token(token)) if token else None

    def _read(self, digest: str) -> Principal | None:
        with self.db.session() as s:
            row = s.execute(select(Token).where(Token.sha256 == digest, Token.revoked.is_(False))).scalar_one_or_none()
            return Principal(row.id, row.name, row.role) if row else None

    def forget(self) -> None:
        self._revocations += 1
        self._answers.show(self._revocations)


def bearer(header: str | None) -> str | None:
    if not header:
        return None
    scheme, _, value = header.partition(" ")
    return value.strip() if scheme.lower() == "bearer" and value.strip() else None
