"""The caller's ``X-Request-Id``: kept only when it is safe to echo and to log.

A request id is echoed in the response and written into every log line of the request, so what a
caller puts there must not carry a secret or break a log: it is kept when it is 1-64 characters of
letters, digits and ``._:-`` (a UUID, a PLC's sequence tag, ``order-4711:step-3``) and does not look
like a credential:

- a token of this service (its ``cct_`` prefix, or any token the table knows, by its hash),
- anything naming ``bearer`` or ``basic`` (an Authorization header pasted into the wrong header),
- a JSON web token (``eyJ...`` with two dots).

Anything else gets a fresh random id (32 hex digits) instead; the refused value itself is never
echoed, logged or counted.
"""

from __future__ import annotations

import re
import uuid

from starlette.types import Scope

MAX_REQUEST_ID_CHARS = 64
_SANE_ID = re.compile(rf"^[A-Za-z0-9._:-]{{1,{MAX_REQUEST_ID_CHARS}}}$")
_CREDENTIAL_WORDS = re.compile(r"bearer|basic", re.IGNORECASE)
_JWT = re.compile(r"^eyJ[A-Za-z0-9_-]*\.[A-Za-z0-9_-]*\.")
TOKEN_PREFIX = "cct_"
"""The prefix of the tokens ``cellctl token add`` makes (``cellctl.auth.new_token``)."""


def safe_request_id(value: str, known_token: object = None) -> str | None:
    """``value`` when it is a request id safe to echo and log, else None.

    ``known_token``: a callable ``str -> object`` answering non-None for a token the service knows
    (``TokenTable.lookup``); an id equal to such a token is refused whatever its form.
    """
    text = value.strip()
    if not _SANE_ID.match(text) or text.lower().startswith(TOKEN_PREFIX) or _CREDENTIAL_WORDS.search(text) \
            or _JWT.match(text):
        return None
    if callable(known_token) and len(text) >= 16 and known_token(text) is not None:
        return None
    return text


def incoming_request_id(scope: Scope) -> str | None:
    """The caller's request id if it is safe to log and echo, else None."""
    for name, value in scope.get("headers", ()):
        if name.lower() == b"x-request-id":
            tokens = getattr(getattr(scope.get("app"), "state", None), "tokens", None)
            return safe_request_id(bytes(value).decode("latin-1"), getattr(tokens, "lookup", None))
    return None


def new_request_id() -> str:
    return uuid.uuid4().hex
