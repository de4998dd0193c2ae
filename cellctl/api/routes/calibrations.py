"""Calibrations: add a file made elsewhere, list, get, activate, roll back, export (OpenCV / ROS / HALCON), report."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path as FilePath
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Path, Query
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from cellctl.api.body import EdgeRoute
from cellctl.api.deps import Engineer, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.calibration_file import CalibrationFileError
from cellctl.calibration_file import add_calibration as add_calibration_file
from cellctl.mapping import handeye_camera_conflicts
from cellctl.store import NotFound, NothingToRollBack
from cellctl.strict_types import Bool

log = logging.getLogger(__name__)
router = APIRouter(prefix="/calibrations", tags=["calibrations"], route_class=EdgeRoute)

Kind = Literal["camera", "handeye", "npoint", "conveyor"]
CalId = Annotated[int, Path(ge=1, le=2**62, description="calibration id")]


class CalibrationSummaryPublic(BaseModel):
    id: int
    cell_id: str
    kind: str
    camera_id: str
    robot_id: str | None
    version: int
    tool_version: str
    creator: str
    note: str
    created_s: float
    active: bool
    warning: str | None = None


class RollbackInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kind: Kind
    camera_id: str
    robot_id: str | None = None


class ActivateInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    force: Bool = Field(False, description="activate even though the calibration's verdict is not ok "
                                           "(logged in the audit log with the problems)")


def _get(services: ServicesDep, cal_id: int) -> Any:
    try:
        return services.store.get_calibration(cal_id)
    except NotFound:
        raise ApiError(404, "unknown_calibration", f"no calibration {cal_id} in cell {services.config.cell_id!r}; "
                                                   "GET /calibrations lists the stored ones") from None


@router.get("", response_model=list[CalibrationSummaryPublic])
def list_calibrations(services: ServicesDep, _: Viewer, kind: Kind | None = None, camera_id: str | None = None,
                      robot_id: str | None = None) -> list[dict[str, Any]]:
    return [s.to_dict() for s in services.store.list_calibrations(kind, camera_id, robot_id)]


@router.post("", status_code=201, responses={
    422: {"description": "invalid_calibration: a value of the file is wrong (the message names it); "
                         "not_a_calibration: the file is of another kind (the message names what it looks like and "
                         "what to give); unknown_device: no such camera_id/robot_id in the config"}},
    openapi_extra={"requestBody": {"required": True, "content": {"application/json": {"schema": {
        "type": "object", "description": "a calibration file as the CLI writes it: cam.json (calib intrinsics, "
                                         "calib import, calib dlt), he.json (calib handeye, --dof 4 too) or "
                                         "np.json (calib npoint)"}}}}})
def add_calibration(services: ServicesDep, who: Engineer,
                    data: Annotated[Any, Body(description="the calibration file's JSON, as written")],
                    kind: Annotated[Kind | None, Query(description="camera, handeye or npoint (default: "
                                                                   "recognised from the file's keys)")] = None,
                    camera_id: Annotated[str | None, Query(max_length=64, description="the camera it belongs to "
                                                           "(default: the config's calibration.camera)")] = None,
                    robot_id: Annotated[str | None, Query(max_length=64, description="hand-eye and n-point: the "
                                                          "robot (default: calibration.robot); not for a camera "
                                                          "calibration")] = None,
                    note: Annotated[str, Query(max_length=500, description="stored with the version")] = ""
                    ) -> dict[str, Any]:
    """Store a calibration made elsewhere as a new version (engineer); it is never activated here.

    The file is checked as the service would use it (kind, schema, finite numbers, sane sizes);
    the answer is the stored version's summary with the file's verdict (``verdict_ok``: null when
    the file has none) and ``activated: false``. Activate it with ``POST /calibrations/{id}/activate``.
    """
    try:
        return add_calibration_file(services.store, services.config, data, who.name, kind, camera_id, robot_id, note,
                   source="the body")
    except CalibrationFileError as exc:
        raise ApiError(422, exc.code, str(exc)) from None


@router.get("/{cal_id}")
def get_calibration(cal_id: CalId, services: ServicesDep, _: Viewer,
                    inputs: Annotated[bool, Query(description="include the stored inputs")] = False
                    ) -> dict[str, Any]:
    rec = _get(services, cal_id)
    out: dict[str, Any] = {**rec.summary().to_dict(), "result": rec.result}
    if inputs:
        out["inputs"] = rec.inputs
    return out


@router.post("/{cal_id}/activate", response_model=CalibrationSummaryPublic,
             responses={409: {"description": "verdict_not_ok: the calibration's verdict is not ok; the message "
                                             "names the problems; handeye_camera_mismatch: a camera calibration "
                                             "that differs from the one an active hand-eye without a camera of its "
                                             "own was solved with; send {\"force\": true} to activate anyway"}})
def activate(cal_id: CalId, services: ServicesDep, who: Engineer,
             body: Annotated[ActivateInput | None, Body()] = None) -> dict[str, Any]:
    """Make this calibration the active one of its camera (and robot).

    A calibration whose verdict is not ok is refused with 409 ``verdict_not_ok`` unless the body
    says ``{"force": true}``; a forced activation is written to the audit log with the problems.
    A camera calibration whose intrinsics differ from those an active hand-eye of the camera was
    solved with is activated with a ``warning`` that the hand-eye must be redone (the hand-eye keeps
    mapping through the camera it carries); when that hand-eye carries no camera of its own, its
    mapping would change, and the activation is refused the same way (409
    ``handeye_camera_mismatch``) unless forced.
    """
    rec = _get(services, cal_id)
    force = body is not None and body.force
    problems = verdict_problems(rec.result)
    if problems is not None:
        listed = "; ".join(f"{p['code']}: {p['message']}" if p["message"] else p["code"] for p in problems)
        if not force:
            raise ApiError(409, "verdict_not_ok",
                           f"calibration {cal_id}'s verdict is not ok ({listed or 'no problems listed'}); "
                           "fix the data and calibrate again, or send {\"force\": true} to activate it anyway")
        log.warning("calibration %d activated by %s although its verdict is not ok: %s", cal_id, who.name, listed)
        services.store.audit(who.name, "calibration.force_activate", f"calibration:{cal_id}",
                             {"problems": problems}, "forced: verdict not ok")
    conflicts = handeye_camera_conflicts(services, rec) if rec.kind == "camera" else []
    blocking = [c.message for c in conflicts if c.changes_mapping]
    if blocking:
        listed = "; ".join(blocking)
        if not force:
            raise ApiError(409, "handeye_camera_mismatch",
                           f"calibration {cal_id}'s intrinsics differ from those an active hand-eye was solved with "
                           f"({listed}); send {{\"force\": true}} to activate it anyway")
        services.store.audit(who.name, "calibration.force_activate", f"calibration:{cal_id}",
                             {"handeye_camera_mismatch": blocking}, "forced: differs from the hand-eye's camera")
    if conflicts:
        log.warning("camera calibration %d activated by %s although an active hand-eye was solved with other "
                    "intrinsics: %s", cal_id, who.name, "; ".join(c.message for c in conflicts))
    rec = services.store.activate(cal_id, who.name)
    summary: dict[str, Any] = rec.summary().to_dict()
    if conflicts:
        summary["warning"] = "the hand-eye must be redone: " + "; ".join(c.message for c in conflicts)
    return summary


def verdict_problems(result: dict[str, Any]) -> list[dict[str, str]] | None:
    """The verdict's problems when the verdict is not ok; ``None`` when it is ok or there is none."""
    verdict = result.get("verdict")
    if not isinstance(verdict, dict) or verdict.get("ok", False) is True:
        return None
    problems = verdict.get("problems") or []
    return [{"code": str(p.get("code", "")), "message": str(p.get("message", ""))}
            for p in problems if isinstance(p, dict)]


@router.post("/rollback", response_model=CalibrationSummaryPublic)
def rollback(body: RollbackInput, services: ServicesDep, who: Engineer) -> dict[str, Any]:
    try:
        rec = services.store.rollback(body.kind, body.camera_id, body.robot_id, who.name)
    except NothingToRollBack as exc:
        raise ApiError(409, "nothing_to_roll_back", str(exc)) from None
    if rec is None:
        raise ApiError(409, "nothing_to_roll_back", "no earlier active version to return to")
    summary: dict[str, Any] = rec.summary().to_dict()
    return summary


@router.get("/{cal_id}/export", response_class=PlainTextResponse)
def export(cal_id: CalId, services: ServicesDep, _: Viewer,
           format: Literal["opencv", "ros", "halcon", "json"] = "opencv",
           pixel_pitch_um: Annotated[float | None, Query(gt=0, le=100, allow_inf_nan=False,
                                                         description="sensor cell width in micrometres "
                                                                     "(required for format=halcon, e.g. 3.45)")] = None
           ) -> PlainTextResponse:
    import json

    from calibration import io as cal_io
    from calibration.io import camera_from_json

    rec = _get(services, cal_id)
    if format == "json":
        return PlainTextResponse(json.dumps(rec.result, indent=2), media_type="application/json")
    if rec.kind != "camera":
        raise ApiError(422, "not_a_camera", f"calibration {cal_id} is a {rec.kind} calibration; only camera "
                                            "calibrations export to OpenCV/ROS/HALCON (use format=json)")
    camera = camera_from_json(rec.result, f"calibration {cal_id}")
    try:
        if format == "halcon":
            if pixel_pitch_um is None:
                raise ApiError(422, "pixel_pitch_required",
                               "HALCON camera parameters are in metres on the sensor: give the sensor cell width "
                               "as pixel_pitch_um (micrometres, from the camera's data sheet, e.g. "
                               "?format=halcon&pixel_pitch_um=3.45)")
            return PlainTextResponse(cal_io.halcon_cam_par(camera, pixel_pitch_um * 1e-6))
        with tempfile.TemporaryDirectory() as tmp:
            path = FilePath(tmp) / "camera.yaml"
            if format == "opencv":
                cal_io.write_opencv_yaml(camera, path)
            else:
                cal_io.write_ros_yaml(camera, path, name=rec.camera_id)
            return PlainTextResponse(path.read_text(), media_type="application/x-yaml")
    except cal_io.ExportError as exc:
        raise ApiError(422, "export_unsupported", str(exc)) from None


@router.get("/{cal_id}/report", response_class=HTMLResponse,
            responses={200: {"content": {"text/html": {}, "application/json": {}}}})
def report(cal_id: CalId, services: ServicesDep, _: Viewer,
           format: Annotated[Literal["html", "json"], Query(description="html: the report page (inline SVG "
                                                                         "plots, no external files); json: its "
                                                                         "figures")] = "html") -> Response:
    """The calibration's report: the same page ``cellctl calib intrinsics --report`` writes.

    Built from what the store keeps for the calibration (its result and inputs, both immutable),
    so it is the same every time it is asked for; the page is kept in memory once built.
    """
    from calibration.report import ReportError, calibration_report, report_json

    rec = _get(services, cal_id)
    try:
        if format == "json":
            return JSONResponse(report_json(rec.kind, rec.result, rec.inputs))
        cached = services.reports.get((rec.id, rec.sha256))
        if cached is None:
            title = (f"{rec.kind} calibration {cal_id} (v{rec.version}) of {rec.camera_id}"
                     f"{' / ' + rec.robot_id if rec.robot_id else ''}")
            cached = calibration_report(rec.kind, rec.result, rec.inputs, title)
            services.reports.put((rec.id, rec.sha256), cached)
    except ReportError as exc:
        raise ApiError(409, "no_report", f"calibration {cal_id}: {exc}") from None
    return HTMLResponse(cached)

