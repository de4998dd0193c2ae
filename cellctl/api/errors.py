"""Uniform error bodies: ``{"error": {"code": ..., "message": ...}}``; device outages answer 503.

A device that is unreachable answers 503 with ``{"available": false, "reason": ...}`` (INTERFACES
§5); bad input answers 4xx with a machine-readable code and a human message; never a 500 for
anything a caller or a device did.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from drivers.base import DeviceTimeout, DeviceUnavailable, DriverError, MotionRejected

log = logging.getLogger(__name__)


class ApiError(Exception):
    """An error with an HTTP status, a machine-readable code and a message for people."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message


def error_body(code: str, message: str) -> dict[str, dict[str, str]]:
    return {"error": {"code": code, "message": message}}


def unavailable_response(reason: str) -> JSONResponse:
    return JSONResponse(status_code=503, content={"available": False, "reason": reason,
                                                  **error_body("device_unavailable", reason)})


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse(status_code=exc.status, content=error_body(exc.code, exc.message))

    @app.exception_handler(DeviceUnavailable)
    async def _unavailable(_: Request, exc: DeviceUnavailable) -> JSONResponse:
        return unavailable_response(str(exc))

    @app.exception_handler(DeviceTimeout)
    async def _timeout(_: Request, exc: DeviceTimeout) -> JSONResponse:
        return unavailable_response(str(exc))

    @app.exception_handler(MotionRejected)
    async def _rejected(_: Request, exc: MotionRejected) -> JSONResponse:
        return JSONResponse(status_code=422, content=error_body("motion_rejected", str(exc)))

    @app.exception_handler(DriverError)
    async def _driver(_: Request, exc: DriverError) -> JSONResponse:
        return JSONResponse(status_code=502, content=error_body("device_error", str(exc)))

    @app.exception_handler(LookupError)
    async def _not_found(_: Request, exc: LookupError) -> JSONResponse:
        # The store's NotFound and our "no such ..." KeyErrors carry a message for people.
        msg = exc.args[0] if exc.args and isinstance(exc.args[0], str) else str(exc)
        return JSONResponse(status_code=404, content=error_body("not_found", msg))

    @app.exception_handler(ValueError)
    async def _invalid(_: Request, exc: ValueError) -> JSONResponse:
        # Our typed input errors subclass ValueError (store InvalidInput, calibration and pick errors).
        log.warning("refused: %s", exc, exc_info=True)
        return JSONResponse(status_code=422, content=error_body("invalid_input", str(exc)))

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err.get("loc", ()))
            parts.append(f"{loc}: {err.get('msg', 'invalid')}")
        return JSONResponse(status_code=422, content=error_body("invalid_request", "; ".join(parts)))

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = {401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed"}.get(
            exc.status_code, "http_error")
        return JSONResponse(status_code=exc.status_code, content=error_body(code, str(exc.detail)),
                            headers=getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception) -> JSONResponse:
        log.exception("unexpected error")
        return JSONResponse(status_code=500, content=error_body(
            "internal_error", f"{type(exc).__name__}: {exc} (this is a cellctl bug; please report it)"))
