"""Calibration reports and printable targets.

Modules: ``html`` (``calibration_report``: the one HTML report of a camera, hand-eye or N-point
calibration, for the CLI and the service; ``report_json``), ``camera`` (the camera part's data,
rebuilt from ``cam.json`` and the detections) and ``camera_plots`` (its figures), ``handeye`` and
``npoint`` (those parts), ``plots`` (matplotlib figures as inline SVG, the good/bad colour
``Band``), ``page`` (the page, tables, rounding), ``write`` (``write_report``: the report file the
CLI writes after an intrinsics calibration), ``target_print`` (a target at true scale as SVG, PDF
or PNG). Everything public is exported here: ``from calibration.report import X``
is the interface.
"""

from calibration.report.camera import MAX_VECTORS
from calibration.report.html import ReportError, calibration_report, report_json
from calibration.report.plots import warm_up
from calibration.report.target_print import (
    FORMATS,
    MM_PER_INCH,
    TargetPrintError,
    page_origin_px,
    png_bytes,
    png_dpi,
    to_image,
    to_pdf,
    to_svg,
    write_target,
)
from calibration.report.write import write_report

__all__ = [
    "FORMATS", "MAX_VECTORS", "MM_PER_INCH", "ReportError", "TargetPrintError", "calibration_report",
    "page_origin_px", "png_bytes", "png_dpi", "report_json", "to_image", "to_pdf", "to_svg", "warm_up",
    "write_report", "write_target",
]
