"""Uniform error bodies: ``{"error": {"code": ..., "message": ...}}``; device outages answer 503.

A device that is unreachable answers 503 with ``{"available": false, "reason": ...}`` (INTERFACES
§5); bad input answers 4xx with a machine-readable code and a human message; never a 500 for
anything a caller or a device did. Only the project's own error types map to a 4xx: the libraries'
roots (``CalibrationError``, ``VisionError``, ``DriverError``) and cellctl's (``CellctlError``):
``OWN_ERRORS``; anything else (a builtin ``KeyError``, a numpy ``ValueError``) is a bug: 500
with the request id, logged with its traceback.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from calibration import CalibrationError
from cellctl.errors import CellctlError
from cellctl.errors_format import format_validation_errors
from cellctl.logging_setup import request_id_var
from cellctl.store.errors import StoreUnavailable
from drivers.base import DeviceTimeout, DeviceUnavailable, DriverError, MotionRejected, RobotBusy, RobotStopped
from drivers.errors import DriverInputError
from vision.errors import VisionError

log = logging.getLogger(__name__)


class ApiError(CellctlError):
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

    @app.exception_handler(StoreUnavailable)
    async def _store(_: Request, exc: StoreUnavailable) -> JSONResponse:
        # A damaged or unreachable store is the plant's outage, not our bug: 503 saying what to do.
        log.error("store unavailable: %s", exc)
        return JSONResponse(status_code=503, content={"available": False, "reason": str(exc),
                                                      **error_body("store_unavailable", str(exc))})

    @app.exception_handler(MotionRejected)
    async def _rejected(_: Request, exc: MotionRejected) -> JSONResponse:
        return JSONResponse(status_code=422, content=error_body("motion_rejected", _with_notes(exc)))

    @app.exception_handler(DriverError)
    async def _driver(_: Request, exc: DriverError) -> JSONResponse:
        return JSONResponse(status_code=502, content=error_body("device_error", str(exc)))

    @app.exception_handler(DriverInputError)
    async def _driver_input(_: Request, exc: DriverInputError) -> JSONResponse:
        # the virtual cell's input errors (a recording, a scene, a render, a reach), not device faults
        log.warning("refused: %s", exc)
        return JSONResponse(status_code=422, content=error_body("invalid_input", _with_notes(exc)))

    @app.exception_handler(RobotBusy)
    async def _busy(_: Request, exc: RobotBusy) -> JSONResponse:
        return JSONResponse(status_code=409, content=error_body("robot_busy", str(exc)))

    @app.exception_handler(RobotStopped)
    async def _stopped(_: Request, exc: RobotStopped) -> JSONResponse:
        return JSONResponse(status_code=409, content=error_body("robot_stopped", str(exc)))

    @app.exception_handler(LookupError)
    async def _not_found(request: Request, exc: LookupError) -> JSONResponse:
        if not is_own_error(exc):
            return internal_error(request, exc)  # a KeyError in our code is a bug, not the caller's 404
        msg = exc.args[0] if exc.args and isinstance(exc.args[0], str) else str(exc)
        return JSONResponse(status_code=404, content=error_body("not_found", msg))

    @app.exception_handler(ValueError)
    async def _invalid(request: Request, exc: ValueError) -> JSONResponse:
        if not is_own_error(exc):
            return internal_error(request, exc)  # a numpy or stdlib ValueError is our bug
        log.warning("refused: %s", exc)
        return JSONResponse(status_code=422, content=error_body("invalid_input", _with_notes(exc)))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        # An unknown key's message lists the keys accepted there (read from the route's body model).
        body_field = getattr(request.scope.get("route"), "body_field", None)
        model = getattr(getattr(body_field, "field_info", None), "annotation", None)
        message = (_json_syntax_message(exc) or _not_json_message(request, exc)
                   or format_validation_errors(exc.errors(), with_input=False, model=model, model_loc=1))
        return JSONResponse(status_code=422, content=error_body("invalid_request", message))

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = {401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed"}.get(
            exc.status_code, "http_error")
        return JSONResponse(status_code=exc.status_code, content=error_body(code, str(exc.detail)),
                            headers=getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        return internal_error(request, exc)


def _json_syntax_message(exc: RequestValidationError) -> str | None:
    """A body that is not valid JSON: where (line and column, 1-based) and what the parser expected."""
    err = next((e for e in exc.errors() if e.get("type") == "json_invalid"), None)
    if err is None:
        return None
    loc = tuple(err.get("loc", ()))
    pos = loc[1] if len(loc) > 1 and isinstance(loc[1], int) else None
    doc = exc.body.decode("utf-8", "replace") if isinstance(exc.body, bytes) else exc.body
    what = (err.get("ctx") or {}).get("error", "invalid JSON")
    if pos is None or not isinstance(doc, str):
        return f"body: not valid JSON ({what})"
    line = doc.count("\n", 0, pos) + 1
    column = pos - (doc.rfind("\n", 0, pos) + 1) + 1
    near = doc[max(0, pos - 20):pos + 20].replace("\n", " ")
    return f"body: not valid JSON at line {line}, column {column}: {what} (near {near!r})"


def _not_json_message(request: Request, exc: RequestValidationError) -> str | None:
    """A body sent without ``Content-Type: application/json``: it was not read as JSON; say so."""
    content_type = request.headers.get("content-type", "")
    if "json" in content_type.lower():
        return None
    if not any(tuple(e.get("loc", ())) == ("body",) and isinstance(e.get("input"), bytes | str)
               for e in exc.errors()):
        return None
    sent = f"Content-Type: {content_type}" if content_type else "no Content-Type header"
    return (f"body: not read as JSON ({sent}); send the header Content-Type: application/json "
            "(curl: -H 'Content-Type: application/json')")


OWN_ERRORS: tuple[type[Exception], ...] = (CalibrationError, VisionError, DriverError, CellctlError)
"""The roots of the project's own typed errors (one per package): their messages are written for
people, so they may be a 4xx. Every error class of a package derives from its root
(``tests/test_error_roots.py``)."""


def is_own_error(exc: BaseException) -> bool:
    """True for the project's own typed errors (by type, never by the module that defines it)."""
    return isinstance(exc, OWN_ERRORS)


def _with_notes(exc: BaseException) -> str:
    notes = getattr(exc, "__notes__", None) or []
    return " ".join([str(exc), *notes])


def internal_error(request: Request, exc: BaseException) -> JSONResponse:
    """A bug: 500 with the request id, the traceback in the log (never dressed as a 4xx)."""
    rid = request_id_var.get() or request.headers.get("x-request-id") or "-"
    log.error("unexpected error (request %s)", rid, exc_info=(type(exc), exc, exc.__traceback__))
    return JSONResponse(status_code=500, content=error_body(
        "internal_error", f"{type(exc).__name__}: {exc} (a cellctl bug; report it with request id {rid})"),
        headers={"X-Request-Id": rid} if rid != "-" else None)
