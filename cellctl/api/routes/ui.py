"""The operator web page: ``/`` is ``index.html``, ``/ui/<file>`` its static files; no token needed.

The page itself holds no data: everything it shows comes from the token-protected API, called
with the token the operator logs in with. Only plain file names inside ``cellctl/static`` are
served (no sub-directories, no dot files), so a crafted path cannot leave that directory.
"""

from __future__ import annotations

import re
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

from cellctl.api.errors import ApiError

router = APIRouter(tags=["ui"], include_in_schema=False)

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml", ".png": "image/png"}
# The page must never be served stale after an upgrade, and must not load anything from elsewhere.
_HEADERS = {"Cache-Control": "no-cache",
            "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; "
                                       "script-src 'self'; frame-src 'self' blob:; object-src 'none'",
            "X-Content-Type-Options": "nosniff"}


def _file(name: str) -> FileResponse:
    path = STATIC_DIR / name
    if not _NAME.match(name) or ".." in name or path.suffix not in _TYPES or not path.is_file():
        raise ApiError(404, "not_found", f"no page file {name!r}")
    return FileResponse(path, media_type=_TYPES[path.suffix], headers=_HEADERS)


@router.get("/")
def index() -> FileResponse:
    return _file("index.html")


@router.get("/ui/{name}")
def static_file(name: str) -> FileResponse:
    return _file(name)
