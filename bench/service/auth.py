"""API tokens: random, shown once, stored as their SHA-256 only; roles viewer < operator < admin.

SHA-256 and not bcrypt/argon2: a token is 256 random bits from `secrets`, not a password a person chose, so there
is nothing to slow a guesser down for; a fast hash also lets every request look its token up by index.
"""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
from dataclasses import dataclass

from sqlalchemy import select

from bench.service.db import Database, Token

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
    """Looks tokens up by hash; answers from memory for CACHE_S so that a busy API does not hit the database
    for every request."""

    def __init__(self, db: Database):
        self.db = db
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[float, Principal | None]] = {}

    def cached(self, token: str) -> tuple[bool, Principal | None]:
        """(found, principal) from memory only: the event loop asks this first and goes to a thread only on a miss."""
        with self._lock:
            hit = self._cache.get(hash_token(token))
        if hit is not None and hit[0] > time.monotonic():
            return True, hit[1]
        return False, None

    def lookup(self, token: str | None) -> Principal | None:
        if not token:
            return None
        digest = hash_token(token)
        now = time.monotonic()
        with self._lock:
            hit = self._cache.get(digest)
        if hit is not None and hit[0] > now:
            return hit[1]
        with self.db.session() as s:
            row = s.execute(select(Token).where(Token.sha256 == digest, Token.revoked.is_(False))).scalar_one_or_none()
            principal = Principal(row.id, row.name, row.role) if row else None
        with self._lock:
            if len(self._cache) > 10_000:
                self._cache.clear()
            self._cache[digest] = (now + CACHE_S, principal)
        return principal

    def forget(self) -> None:
        with self._lock:
            self._cache.clear()


def bearer(header: str | None) -> str | None:
    if not header:
        return None
    scheme, _, value = header.partition(" ")
    return value.strip() if scheme.lower() == "bearer" and value.strip() else None
