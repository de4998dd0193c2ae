"""Bearer tokens and roles (viewer < operator < engineer). Tokens are stored as SHA-256 hashes.

Tokens are 32 random bytes (URL-safe base64), so a plain SHA-256 is a sufficient hash: there is
nothing to brute-force that a salt or a slow hash would protect.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import secrets
import threading
from dataclasses import dataclass
from pathlib import Path

from cellctl.config import ROLE_RANK, CellConfig, Role

log = logging.getLogger(__name__)


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
    """Looks tokens up by hash in constant time per entry.

    When built from a config read from a file, every lookup checks (one ``stat``) whether the file
    changed and then re-reads its ``auth.tokens``: ``cellctl token add/remove`` take effect in a
    running service without a restart. A changed file that does not validate keeps the previous
    tokens (logged); other sections of the file need a restart.
    """

    def __init__(self, entries: list[tuple[str, Role, str]], source: Path | None = None,
                 extra: list[tuple[str, Role, str]] | None = None) -> None:
        self._entries = entries
        self._source = source
        self._extra = list(extra or [])
        self._stamp = _stamp(source) if source is not None else None
        self._lock = threading.Lock()

    @classmethod
    def from_config(cls, config: CellConfig, extra: list[tuple[str, Role, str]] | None = None) -> TokenTable:
        return cls(_entries(config) + (extra or []), config.source, extra)

    def __len__(self) -> int:
        return len(self._entries)

    def names(self) -> list[tuple[str, Role]]:
        self._refresh()
        return [(name, role) for name, role, _ in self._entries]

    def lookup(self, token: str) -> Principal | None:
        self._refresh()
        digest = hash_token(token)
        found: Principal | None = None
        for name, role, sha in self._entries:
            if hmac.compare_digest(digest, sha):
                found = Principal(name, role)
        return found

    def _refresh(self) -> None:
        if self._source is None:
            return
        stamp = _stamp(self._source)
        if stamp == self._stamp:
            return
        with self._lock:
            if stamp == self._stamp:
                return
            from cellctl.config import ConfigError, load_config

            self._stamp = stamp
            try:
                config = load_config(self._source)
            except ConfigError as exc:
                log.error("%s changed but does not validate; keeping the previous tokens: %s", self._source, exc)
                return
            self._entries = _entries(config) + self._extra
            log.info("%s changed: %d token(s) configured now", self._source, len(config.auth.tokens))


def _entries(config: CellConfig) -> list[tuple[str, Role, str]]:
    return [(t.name, t.role, t.sha256) for t in config.auth.tokens]


def _stamp(path: Path) -> tuple[int, int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)
