"""Coverage and advice: can the calibration data support the camera model?

Each problem is a code and one message saying what to do. The rules (thresholds are stated so an
operator can argue with them):

- ``too_few_views``: fewer than ``MIN_GOOD_VIEWS`` views used.
- ``not_enough_tilt``: no view tilts the target more than ``MIN_TILT_DEG`` about an axis (the
  camera's x axis = the image's horizontal, or its y axis = the vertical). Without tilt the
  focal length and the target distance cannot be told apart (docs/field-notes.md).
- ``corners_not_covered``: an image corner region (the outer ``CORNER_FRACTION`` of width and
  height) holds no observed point; distortion there is extrapolated. The message names them.
- ``border_not_covered``: along an image side, the border strip (the outer ``BORDER_FRACTION`` of the
  width or height) holds observed points over less than ``BORDER_MIN_FRACTION`` of its length (cells
  of the coverage grid: in practice, none). Lens distortion grows fastest towards the border; with
  the ring empty it is extrapolated there, however well the centre fits (measured on held-out renders:
  ``bench/intrinsics_border.py``). The message names the sides and how much of each is covered.
- ``focal_poorly_determined``: 1-sigma of fx or fy above ``MAX_FOCAL_REL_SIGMA`` of its value.
- ``principal_point_poorly_determined``: 1-sigma of cx or cy above ``MAX_PP_REL_SIGMA`` of the
  image width/height.
- ``projection_uncertain``: the expected projection error over the covered region
  (``uncertainty.projection_rms_px``) above ``MAX_PROJECTION_RMS_PX``: the data do not pin the
  model's parameters down (too many parameters for the data, or too little data). The advice
  depends on the model: more and better-spread views always; fewer coefficients only where the
  model has some to spare and the lens is not wide-angle (``WIDE_ANGLE_FOV_DEG``).
- ``outlier_views``: views whose RMS is far above the rest (advice only; does not fail).
- ``cross_validation_disagrees`` (``cross_validation_problem``, added where the calibration was
  cross-validated): the cameras calibrated from disjoint halves (folds) of the views project the
  covered region more than ``MAX_CROSS_VALIDATION_PX`` apart *and* more than
  ``CROSS_VALIDATION_FACTOR`` times what their own uncertainties explain: the model does not
  describe the lens (or the board is not flat), whatever the RMS says.
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

MIN_GOOD_VIEWS: Final = 8
MIN_TILT_DEG: Final = 15.0
CORNER_FRACTION: Final = 0.2
BORDER_FRACTION: Final = 0.1
"""The border strip along each image side: cells whose centre lies in the outer 10% of the width/height."""
BORDER_MIN_FRACTION: Final = 0.05
"""A side's strip counts as covered when observed points lie over at least this share of its length (one
cell of the 16 x 12 grid along a side: the radial terms are pinned by the largest radius reached, the image
corners; the strip asks for each side's distortion to be sampled at least once)."""
MAX_FOCAL_REL_SIGMA: Final = 0.01
MAX_PP_REL_SIGMA: Final = 0.01
MAX_PROJECTION_RMS_PX: Final = 0.5
MAX_CROSS_VALIDATION_PX: Final = 0.5
CROSS_VALIDATION_FACTOR: Final = 3.0
WIDE_ANGLE_FOV_DEG: Final = 90.0
"""A lens seeing this much across (horizontal) is wide-angle: its distortion terms are needed."""


def tilts_deg(normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """(V, 2) tilt of each target about the camera's x and y axes (degrees) from its plane normal
    (the target z axis in the camera frame)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n * np.sign(n[:, 2:3] + 1e-300)
    return np.degrees(np.column_stack([np.arctan2(-n[:, 1], n[:, 2]), np.arctan2(n[:, 0], n[:, 2])]))


def uncovered_corners(coverage: NDArray[np.int64], fraction: float = CORNER_FRACTION) -> list[str]:
    """Names of image corners whose region holds no observed point."""
    ny, nx = coverage.shape
    cx = max(1, int(round(nx * fraction)))
    cy = max(1, int(round(ny * fraction)))
    regions = {"top-left": coverage[:cy, :cx], "top-right": coverage[:cy, -cx:],
               "bottom-left": coverage[-cy:, :cx], "bottom-right": coverage[-cy:, -cx:]}
    return [k for k, r in regions.items() if r.sum() == 0]


def border_coverage(coverage: NDArray[np.int64], fraction: float = BORDER_FRACTION) -> dict[str, float]:
    """For each image side (top, bottom, left, right), the share of its border strip's length (cells along
    the side) that holds an observed point; the strip is the cells whose centre lies in the outer
    ``fraction`` of the image."""
    ny, nx = coverage.shape
    kx = max(1, int(np.sum((np.arange(nx) + 0.5) / nx < fraction)))
    ky = max(1, int(np.sum((np.arange(ny) + 0.5) / ny < fraction)))
    c = np.asarray(coverage) > 0
    return {"top": float(c[:ky, :].any(axis=0).mean()), "bottom": float(c[-ky:, :].any(axis=0).mean()),
            "left": float(c[:, :kx].any(axis=1).mean()), "right": float(c[:, -kx:].any(axis=1).mean())}


def uncovered_border(coverage: NDArray[np.int64]) -> list[str]:
    """The image sides whose border strip is covered over less than ``BORDER_MIN_FRACTION`` of its length."""
    return [k for k, f in border_coverage(coverage).items() if f < BORDER_MIN_FRACTION]


def horizontal_fov_deg(size: tuple[int, int], fx: float) -> float:
    """Horizontal field of view (degrees) of a pinhole with focal length ``fx`` (px) over ``size``."""
    return float(np.degrees(2.0 * np.arctan2(size[0] / 2.0, fx))) if fx > 0 else float("nan")


def _projection_advice(model: str, size: tuple[int, int], values: dict[str, float]) -> str:
    """What to do about a poorly determined projection, checked against the model and the lens."""
    more_data = "add views (10-20), tilted 20-45 deg, that cover the image corners and edges"
    fov = horizontal_fov_deg(size, float(values.get("fx", 0.0)))
    if model == "division":
        return more_data + " (the division model has a single distortion coefficient: none to drop)"
    if np.isfinite(fov) and fov >= WIDE_ANGLE_FOV_DEG:
        return (more_data + f" (a wide-angle lens, {fov:.0f} deg across: it needs its distortion terms, so "
                "do not drop coefficients; the fisheye4 model (an angle polynomial) or the division model often "
                "describe such lenses better: let cross-validation choose the model (the automatic model choice))")
    if model == "opencv8":
        return more_data + ", or choose opencv5 (5 coefficients instead of 8)"
    if model == "opencv5":
        return more_data + ", or choose the division model (1 coefficient instead of 5)"
    return more_data


def assess(*, n_views: int, size: tuple[int, int], coverage: NDArray[np.int64], normals: NDArray[np.float64],
           sigmas: dict[str, float], values: dict[str, float], uncertainty: dict[str, Any],
           n_outlier_views: int = 0, model: str = "") -> dict[str, Any]:
    """The ``verdict`` block of ``cam.json``: ``{"ok": bool, "problems": [{"code", "message"}]}``.

    ``model`` (the lens model's name) makes the advice fit it: no "fewer coefficients" for the
    one-coefficient division model or for a wide-angle lens."""
    problems: list[dict[str, str]] = []
    advice: list[dict[str, str]] = []
    if n_views < MIN_GOOD_VIEWS:
        problems.append({"code": "too_few_views",
                         "message": f"only {n_views} views used; take at least {MIN_GOOD_VIEWS} (10-20 is "
                                    "better), with the target tilted and moved over the whole image"})
    t = tilts_deg(normals)
    max_x = float(np.max(np.abs(t[:, 0]))) if len(t) else 0.0
    max_y = float(np.max(np.abs(t[:, 1]))) if len(t) else 0.0
    axes = []
    if max_x < MIN_TILT_DEG:
        axes.append(f"the horizontal axis (image x; largest tilt {max_x:.0f} deg): tip the target's top "
                    "edge towards and away from the camera")
    if max_y < MIN_TILT_DEG:
        axes.append(f"the vertical axis (image y; largest tilt {max_y:.0f} deg): turn the target's left "
                    "edge towards and away from the camera")
    if axes:
        problems.append({"code": "not_enough_tilt",
                         "message": "not enough tilt about " + " and about ".join(axes)
                                    + f"; add views tilted {MIN_TILT_DEG:.0f}-45 deg"})
    missing = uncovered_corners(coverage)
    if missing:
        problems.append({"code": "corners_not_covered",
                         "message": f"no target points in the image corner(s) {', '.join(missing)} (outer "
                                    f"{CORNER_FRACTION:.0%} of the image); add views with the target there, "
                                    "or distortion there is a guess"})
    sides = uncovered_border(coverage)
    if sides:
        share = border_coverage(coverage)
        problems.append({"code": "border_not_covered",
                         "message": "the image border is not covered: target points lie along "
                                    + ", ".join(f"the {k} edge over {share[k]:.0%}" for k in sides)
                                    + f" of its outer {BORDER_FRACTION:.0%} strip (at least "
                                    f"{BORDER_MIN_FRACTION:.0%} needed); add views with the target reaching the "
                                    f"{', '.join(sides)} edge(s) of the image, where the lens distorts most "
                                    "(uncovered, the distortion there is extrapolated)"})
    for f in ("fx", "fy"):
        if f in sigmas and values.get(f):
            rel = sigmas[f] / abs(values[f])
            if not np.isfinite(rel) or rel > MAX_FOCAL_REL_SIGMA:
                problems.append({"code": "focal_poorly_determined",
                                 "message": f"{f} = {values[f]:.1f} px is uncertain by {sigmas[f]:.1f} px "
                                            f"({rel:.1%}, limit {MAX_FOCAL_REL_SIGMA:.0%}); add views with "
                                            "more tilt and at different distances"})
                break
    for c, n in (("cx", size[0]), ("cy", size[1])):
        if c in sigmas:
            rel = sigmas[c] / n
            if not np.isfinite(rel) or rel > MAX_PP_REL_SIGMA:
                problems.append({"code": "principal_point_poorly_determined",
                                 "message": f"{c} is uncertain by {sigmas[c]:.1f} px ({rel:.1%} of the "
                                            "image); add tilted views covering the whole image"})
                break
    proj = uncertainty.get("projection_rms_px")
    if proj is None or not np.isfinite(proj) or proj > MAX_PROJECTION_RMS_PX:
        shown = "unknown" if proj is None else f"{proj:.2f} px"
        problems.append({"code": "projection_uncertain",
                         "message": f"expected projection error over the covered region is {shown} "
                                    f"(limit {MAX_PROJECTION_RMS_PX} px): a parameter is poorly "
                                    f"determined; {_projection_advice(model, size, values)}"})
    if n_outlier_views:
        advice.append({"code": "outlier_views",
                       "message": f"{n_outlier_views} view(s) fit far worse than the rest (see "
                                  "views[].outlier); check them or recalibrate with outlier dropping"})
    return {"ok": not problems, "problems": problems, "advice": advice,
            "max_tilt_deg": {"about_x": round(max_x, 1), "about_y": round(max_y, 1)},
            "border_covered": {k: round(v, 3) for k, v in border_coverage(coverage).items()}}


def cross_validation_problem(cv: dict[str, Any]) -> dict[str, str] | None:
    """The ``cross_validation_disagrees`` problem for a cross-validation block
    (``calibration.intrinsics.cross_validate``), or None when the folds agree."""
    d = cv.get("projection_difference_rms_px")
    expected = cv.get("expected_from_uncertainty_px") or 0.0
    if d is None or not np.isfinite(d):
        return None
    if d <= MAX_CROSS_VALIDATION_PX or d <= CROSS_VALIDATION_FACTOR * expected:
        return None
    return {"code": "cross_validation_disagrees",
            "message": f"cameras calibrated from disjoint halves of the views differ by {d:.2f} px over the "
                       f"covered region (their uncertainties explain {expected:.2f} px; limit "
                       f"{MAX_CROSS_VALIDATION_PX} px): the model does not describe this lens or the target is not "
                       "flat; let cross-validation choose the lens model and the board warp (the automatic "
                       "choices), and add views over the whole image"}
