"""Verdict of an N-point (jog-to-mark) calibration: can these marks support this map?

The same shape as the camera verdict (``calibration.verdict``): ``{"ok", "problems": [{"code",
"message"}], "advice": [...]}`` plus the figures the rules looked at. Each message says what to
do. The rules (thresholds stated so an operator can argue with them):

- ``too_few_marks``: fewer than ``EXTRA_MARKS`` marks beyond the model's minimum (similarity 2,
  affine 3, homography 4): without redundancy the leave-one-out test and the uncertainty mean
  little.
- ``loo_too_large``: the leave-one-out RMS of the chosen model (each mark predicted by the map
  fitted without it, mm) above ``MAX_LOO_RMS_MM``: a mark was recorded off its centre, the camera
  or the plate moved, or lens distortion is left in. The message names the worst marks.
- ``marks_not_spread``: the marks' convex hull in the image covers less than
  ``MIN_HULL_FRACTION`` of the image, or is thin (its narrowest extent under
  ``MIN_HULL_ASPECT`` of its widest): the map is then a guess across most of the view.
- ``map_extrapolates`` (advice, does not fail): the hull covers less than
  ``ADVISE_HULL_FRACTION`` of the image; outside it the map extrapolates.
- ``outlier_mark`` (advice): a mark whose leave-one-out error is over ``OUTLIER_FACTOR`` times
  the others' median (and over a third of the limit).
"""

from __future__ import annotations

from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import ArrayLike

from calibration.npoint.fit import MIN_POINTS, NPointResult, loo_errors_mm

EXTRA_MARKS: Final = 2
MAX_LOO_RMS_MM: Final = 0.25
MIN_HULL_FRACTION: Final = 0.02
MIN_HULL_ASPECT: Final = 0.2
ADVISE_HULL_FRACTION: Final = 0.25
OUTLIER_FACTOR: Final = 4.0


def _hull_figures(uv: np.ndarray, size: tuple[int, int]) -> tuple[float, float]:
    """(fraction of the image inside the marks' hull, narrowest / widest extent of the hull)."""
    pts = uv.astype(np.float32).reshape(-1, 1, 2)
    area = float(cv2.contourArea(cv2.convexHull(pts))) if len(uv) >= 3 else 0.0
    (_, _), (w, h), _ = cv2.minAreaRect(pts)
    aspect = float(min(w, h) / max(w, h)) if max(w, h) > 0 else 0.0
    return area / float(size[0] * size[1]), aspect


def assess_npoint(result: NPointResult, uv_px: ArrayLike, xy_mm: ArrayLike, image_size: tuple[int, int],
                  steps: list[int] | None = None) -> dict[str, Any]:
    """The ``verdict`` block of ``np.json`` for ``result`` fitted from these pairs (raw pixels, robot mm).

    ``steps`` names the marks in messages (default 1..N, the order given)."""
    uv_raw = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
    names = steps or list(range(1, len(uv_raw) + 1))
    model = result.model
    n = len(uv_raw)
    problems: list[dict[str, str]] = []
    advice: list[dict[str, str]] = []
    need = MIN_POINTS[model] + EXTRA_MARKS
    if n < need:
        problems.append({"code": "too_few_marks",
                         "message": f"only {n} marks for a {model} map; record at least {need} (9 spread over "
                                    "the working area is typical)"})
    uv = result.camera.undistort_points(uv_raw) if result.camera is not None else uv_raw
    loo = loo_errors_mm(model, uv, xy) if n > MIN_POINTS[model] else np.full(n, np.nan)
    loo_rms = float(np.sqrt(np.mean(loo ** 2))) if np.all(np.isfinite(loo)) else float("nan")
    order = [int(k) for k in np.argsort(-np.nan_to_num(loo, nan=-1.0))]
    if not np.isfinite(loo_rms) or loo_rms > MAX_LOO_RMS_MM:
        worst = ", ".join(f"mark {names[k]} ({loo[k]:.2f} mm)" for k in order[:3] if np.isfinite(loo[k]))
        shown = "not computable" if not np.isfinite(loo_rms) else f"{loo_rms:.3f} mm"
        problems.append({"code": "loo_too_large",
                         "message": f"leave-one-out RMS {shown} (limit {MAX_LOO_RMS_MM} mm)"
                                    + (f"; worst: {worst}" if worst else "")
                                    + ": re-record those marks with the tool centred on them; if all are large, "
                                      "check that the camera and the plate did not move and that lens "
                                      "distortion is removed (activate a camera calibration, undistort on)"})
    fraction, aspect = _hull_figures(uv_raw, image_size)
    if fraction < MIN_HULL_FRACTION or aspect < MIN_HULL_ASPECT:
        problems.append({"code": "marks_not_spread",
                         "message": f"the marks cover {fraction:.1%} of the image (hull narrowest/widest "
                                    f"{aspect:.2f}; limits {MIN_HULL_FRACTION:.0%}, {MIN_HULL_ASPECT}); spread "
                                    "them over the area where parts will lie, in both image directions"})
    elif fraction < ADVISE_HULL_FRACTION:
        advice.append({"code": "map_extrapolates",
                       "message": f"the marks cover {fraction:.1%} of the image: outside their hull the map "
                                  "extrapolates; use a larger plate or more marks there if parts lie outside"})
    if n >= 4 and np.all(np.isfinite(loo)):
        k = order[0]
        others = np.delete(loo, k)
        if loo[k] > OUTLIER_FACTOR * float(np.median(others)) and loo[k] > MAX_LOO_RMS_MM / 3:
            ratio = loo[k] / float(np.median(others))
            advice.append({"code": "outlier_mark",
                           "message": f"mark {names[k]} predicts {loo[k]:.3f} mm off, {ratio:.0f}x the others' "
                                      "median: re-record it"})
    return {"ok": not problems, "problems": problems, "advice": advice,
            "marks": n, "loo_rms_mm": loo_rms, "loo_limit_mm": MAX_LOO_RMS_MM,
            "loo_mm": [float(v) for v in loo], "hull_fraction": fraction, "hull_aspect": aspect}
