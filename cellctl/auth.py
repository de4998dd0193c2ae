"""Bearer tokens and roles (viewer < operator < engineer). Tokens are stored as SHA-256 hashes.

Tokens are 32 random bytes (URL-safe base64), so a plain SHA-256 is a sufficient hash: there is
nothing to brute-force that a salt or a slow hash would protect.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass

from cellctl.config import ROLE_RANK, CellConfig, Role


@dataclass(frozen=True)
class Principal:
    """Who is calling: the token's name and role."""

    name: str
    role: Role

    def has(self, role: Role) -> bool:
        return ROLE_RANK[self.role] >= ROLE_RANK[role]


def new_token() -> str:
    return "cct_" + secrets.token_urlsafe(32)


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class TokenTable:
    """Looks tokens up by hash in constant time per entry."""

    def __init__(self, entries: list[tuple[str, Role, str]]) -> None:
        self._entries = entries

    @classmethod
    def from_config(cls, config: CellConfig, extra: list[tuple[str, Role, str]] | None = None) -> TokenTable:
        return cls([(t.name, t.role, t.sha256) for t in config.auth.tokens] + (extra or []))

    def __len__(self) -> int:
        return len(self._entries)

    def lookup(self, token: str) -> Principal | None:
        digest = hash_token(token)
        found: Principal | None = None
        for name, role, sha in self._entries:
            if hmac.compare_digest(digest, sha):
                found = Principal(name, role)
        return found
