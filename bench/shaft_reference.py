"""The shaft support turned by 120 deg (issue 37): is the 1 px between the matcher and its reference the
matcher's or the reference's?

``tests/data/pick_real/invariant-templatematching``: ``image_1.png`` shows two aluminium shaft-support
blocks on black cloth, one as taught, one turned by about 120 deg. Per instance this script prints the
pose (the ROI centre, px, and the turn, deg) by four measurements:

- the matcher (``shape.find``): the final pose (edge fit and patch fit merged) and the edge fit alone
  (the model without its patch);
- the reference of ``bench/pick_real.py``: a rotation-and-sub-pixel NCC sweep of the taught ROI
  (``bench.pick_reference.sweep``, 0.1 deg steps); the corpus's ``measured_estimate`` was made by the same
  kind of sweep (0.25 deg steps), so it is not a second opinion;
- each again with the source's drawn artefact (a 2-px cyan line across both parts, rows 160-161) painted
  out from the rows beside it;
- a third, independent measure: the silhouette's centroid (Otsu threshold, the part's component with its
  bore filled), against the teach silhouette's centroid carried by each pose.

Run: ``.venv/bin/python bench/shaft_reference.py`` (a few seconds).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.pick_cases import load_cases  # noqa: E402
from bench.pick_reference import sweep  # noqa: E402
from vision import shape  # noqa: E402
from vision.shape.model import ShapeModel  # noqa: E402


def centroid(im: np.ndarray, x: float, y: float) -> tuple[float, float, int]:
    """Centroid (x, y) and area (px) of the bright silhouette at (x, y), holes filled."""
    _, b = cv2.threshold(cv2.GaussianBlur(im, (0, 0), 1.0), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    b = cv2.morphologyEx(b, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8))
    _, lab, _, cen = cv2.connectedComponentsWithStats(b)
    k = int(lab[int(round(y)), int(round(x))])
    if k == 0:
        k = 1 + int(np.argmin(np.hypot(cen[1:, 0] - x, cen[1:, 1] - y)))
    cnts, _ = cv2.findContours((lab == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    full = np.zeros(im.shape, np.uint8)
    cv2.drawContours(full, cnts, -1, 1, -1)
    m = cv2.moments(full, True)
    return m["m10"] / m["m00"], m["m01"] / m["m00"], int(full.sum())


def main() -> None:
    case = next(c for c in load_cases() if c.id == "invariant_tm_shaft_supports")
    img = case.test_image(case.tests[0])
    teach = case.teach_image()
    u, v, w, h = case.roi
    cu, cv_ = u + w / 2.0, v + h / 2.0
    model = shape.teach(teach, case.roi)
    edge_only = ShapeModel(model.levels, model.params, model.roi, model.image_size, None)
    painted = img.copy()
    a, b = img[159, 160:449].astype(float), img[162, 160:449].astype(float)
    painted[160, 160:449] = np.round((2 * a + b) / 3).astype(np.uint8)
    painted[161, 160:449] = np.round((a + 2 * b) / 3).astype(np.uint8)
    tx, ty, ta = centroid(teach, cu, cv_)

    def carried(x: float, y: float, a_deg: float) -> tuple[float, float]:
        c, s = math.cos(math.radians(a_deg)), math.sin(math.radians(a_deg))
        return x + c * (tx - cu) + s * (ty - cv_), y - s * (tx - cu) + c * (ty - cv_)

    print(f"teach silhouette: centroid ({tx:.2f}, {ty:.2f}), area {ta} px\n")
    print("| image | fit | match (x, y, deg) | sweep (x, y, deg) | match - sweep px / deg | silhouette area px "
          "| match's centroid off px | sweep's centroid off px | sigma px / deg | patch NCC | fit chi2 |")
    print("| --- " * 11 + "|")
    for name, im in (("as published", img), ("line painted out", painted)):
        for fit, mdl in (("final", model), ("edges only", edge_only)):
            for m in shape.find(mdl, im).matches:
                ref = sweep(teach, case.roi, im, m.u_px, m.v_px, m.angle_deg)
                if ref is None:
                    continue
                sx, sy, sa = centroid(im, m.u_px, m.v_px)
                pm, pr = carried(m.u_px, m.v_px, m.angle_deg), carried(ref.u_px, ref.v_px, ref.angle_deg)
                print(f"| {name} | {fit} | ({m.u_px:.2f}, {m.v_px:.2f}, {m.angle_deg:.2f}) | ({ref.u_px:.2f}, "
                      f"{ref.v_px:.2f}, {ref.angle_deg:.2f}) | {math.hypot(m.u_px - ref.u_px, m.v_px - ref.v_px):.2f}"
                      f" / {m.angle_deg - ref.angle_deg:+.2f} | {sa} | {math.hypot(pm[0] - sx, pm[1] - sy):.2f} | "
                      f"{math.hypot(pr[0] - sx, pr[1] - sy):.2f} | {m.sigma_px:.3f} / {m.sigma_angle_deg:.3f} | "
                      f"{m.scores.get('patch_ncc', math.nan):.3f} | {m.scores.get('fit_chi2', math.nan):.2f} |")


if __name__ == "__main__":
    main()
