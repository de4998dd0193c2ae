"""The operator web page (``/`` is ``index.html``, ``/ui/<file>`` its static files) and the API
docs (``/docs`` Swagger UI, ``/redoc`` ReDoc, their assets under ``/docs/assets/``); no token needed.

The docs' JavaScript and CSS come from the ``fastapi-offline`` package (PyPI), served by the
service itself: nothing is loaded from a CDN, so the docs work on a plant network.

The page itself holds no data: everything it shows comes from the token-protected API, called
with the token the operator logs in with. Only plain file names inside ``cellctl/static`` are
served (no sub-directories, no dot files), so a crafted path cannot leave that directory.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse, Response

from cellctl.api.errors import ApiError

router = APIRouter(tags=["ui"], include_in_schema=False)

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml", ".png": "image/png"}
# The page must never be served stale after an upgrade, and must not load anything from elsewhere
# (inline styles: the calibration report it shows in a srcdoc frame carries its own <style>).
_HEADERS = {"Cache-Control": "no-cache",
            "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; "
                                       "style-src 'self' 'unsafe-inline'; "
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


def _docs_assets_dir() -> Path:
    import fastapi_offline

    return Path(fastapi_offline.__file__).resolve().parent / "static"


DOCS_ASSETS = {"swagger-ui-bundle.js": "text/javascript; charset=utf-8",
               "swagger-ui.css": "text/css; charset=utf-8",
               "redoc.standalone.js": "text/javascript; charset=utf-8",
               "favicon.png": "image/png"}


@router.get("/docs")
def swagger_ui(request: Request) -> HTMLResponse:
    root = request.scope.get("root_path", "")
    return get_swagger_ui_html(
        openapi_url=f"{root}/openapi.json", title="cellctl - API docs",
        swagger_js_url=f"{root}/docs/assets/swagger-ui-bundle.js",
        swagger_css_url=f"{root}/docs/assets/swagger-ui.css",
        swagger_favicon_url=f"{root}/docs/assets/favicon.png",
        oauth2_redirect_url=f"{root}/docs/oauth2-redirect",
        # No validator badge: it would send the spec to an outside service.
        swagger_ui_parameters={"validatorUrl": None})


@router.get("/docs/oauth2-redirect")
def swagger_ui_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


@router.get("/redoc")
def redoc(request: Request) -> HTMLResponse:
    root = request.scope.get("root_path", "")
    return get_redoc_html(openapi_url=f"{root}/openapi.json", title="cellctl - API reference",
                          redoc_js_url=f"{root}/docs/assets/redoc.standalone.js",
                          redoc_favicon_url=f"{root}/docs/assets/favicon.png", with_google_fonts=False)


# ReDoc's sidebar shows its vendor's logo from a CDN; the local favicon stands in for it.
_REWRITES = {"redoc.standalone.js": (b"https://cdn.redoc.ly/redoc/logo-mini.svg", b"/docs/assets/favicon.png")}


@functools.lru_cache(maxsize=len(DOCS_ASSETS))
def _asset_bytes(name: str) -> bytes:
    data = (_docs_assets_dir() / name).read_bytes()
    if name in _REWRITES:
        data = data.replace(*_REWRITES[name])
    return data


@router.get("/docs/assets/{name}")
def docs_asset(name: str) -> Response:
    if name not in DOCS_ASSETS:
        raise ApiError(404, "not_found", f"no docs asset {name!r}")
    return Response(_asset_bytes(name), media_type=DOCS_ASSETS[name],
                    headers={"Cache-Control": "max-age=86400", "X-Content-Type-Options": "nosniff"})
