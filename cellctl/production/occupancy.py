"""Is the pick area empty? Decided from the picture itself, not from what the part model matched.

A search that finds nothing says only that nothing looked like the model; the red-team's run
ended ``area_empty`` with 12 parts in plain view (issue 34). So a picture with no match is
called empty only when it shows no object either: in the recipe's search region (``search.roi``,
else the whole image), outside the arm's region (``cellctl.arm_view``), the picture's edges
(Canny, with thresholds set from the picture's own noise) are grouped into objects (edges within
a few pixels of each other), and an object counts when its larger side reaches
:data:`MIN_OBJECT_SHARE` of the taught part's smaller side (its teach ROI). An object there with no
match ends the run ``not_recognized`` (parts nothing matches: a different part, a part upside
down, a light changed), never ``area_empty``.

The test assumes what a pick area should be: a plain surface. A textured table, marks or a
fixture inside the search region read as objects; narrow ``search.roi`` to the area the parts lie
in (the frame of a ``not_recognized`` cycle is kept and shows the objects found).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

MIN_OBJECT_SHARE = 0.3
"""An object's larger side must reach this share of the taught part's smaller side (its teach ROI)."""
MIN_EDGE_LOW = 20.0
"""The lower Canny threshold at least this (grey levels of an 8-bit image), whatever the noise."""


@dataclass
class Occupancy:
    """What the picture shows in the search region, whatever the model matched."""

    objects: int
    min_extent_px: float
    boxes_px: list[list[int]] = field(default_factory=list)
    """Each object's bounding box ``[u, v, w, h]`` (image pixels; the largest first, at most 20)."""

    @property
    def occupied(self) -> bool:
        return self.objects > 0

    def as_dict(self) -> dict[str, Any]:
        return {"objects": self.objects, "min_extent_px": round(self.min_extent_px, 1), "boxes_px": self.boxes_px}


def occupancy(pixels: NDArray[Any], roi: Any, part_sides_px: list[float], arm_mask: NDArray[np.bool_] | None,
              known_px: list[tuple[float, float, float]] | None = None) -> Occupancy:
    """The objects in ``roi`` (``[u, v, w, h]`` or None: the whole image) outside ``arm_mask`` and outside the
    discs ``known_px`` (``(u, v, radius)``: what the picture's search did recognise — parts in a located
    place's slots, the fixture itself)."""
    img = pixels if pixels.ndim == 2 else cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    h_img, w_img = img.shape
    if roi is None:
        u0, v0, u1, v1 = 0, 0, w_img, h_img
    else:
        u, v, w, h = (float(x) for x in roi)
        u0, v0 = max(0, int(u)), max(0, int(v))
        u1, v1 = min(w_img, int(np.ceil(u + w))), min(h_img, int(np.ceil(v + h)))
    min_extent = MIN_OBJECT_SHARE * (min(part_sides_px) if part_sides_px else 50.0)
    if u1 - u0 < 3 or v1 - v0 < 3:
        return Occupancy(0, min_extent)
    crop = img[v0:v1, u0:u1]
    smooth = cv2.GaussianBlur(crop, (0, 0), 1.0)
    noise = 1.4826 * float(np.median(np.abs(crop.astype(np.float32) - smooth.astype(np.float32))))
    low = max(MIN_EDGE_LOW, 8.0 * noise)
    edges = cv2.Canny(smooth, low, 2.0 * low) > 0
    if arm_mask is not None:
        arm = cv2.dilate(arm_mask[v0:v1, u0:u1].astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        edges &= ~arm
    if known_px:
        seen = np.zeros(edges.shape, np.uint8)
        for u, v, r in known_px:
            cv2.circle(seen, (int(round(u - u0)), int(round(v - v0))), int(np.ceil(r)), 1, -1)
        edges &= seen == 0
    grouped = cv2.dilate(edges.astype(np.uint8), np.ones((5, 5), np.uint8))
    n, _, stats, _ = cv2.connectedComponentsWithStats(grouped, connectivity=8)
    boxes = []
    for i in range(1, n):
        x, y, w, h, _ = (int(s) for s in stats[i])
        if max(w, h) >= min_extent:
            boxes.append([x + u0, y + v0, w, h])
    boxes.sort(key=lambda b: -b[2] * b[3])
    return Occupancy(len(boxes), min_extent, boxes[:20])


def model_radius_px(model: Any) -> float:
    """Half the diagonal of a model's teach ROI (a recipe's ``models`` entry or a place's ``model``), pixels:
    the disc any turn of the taught part covers around its reference point."""
    roi = getattr(getattr(model, "teach", None), "roi", None)
    return 0.5 * float(np.hypot(roi[2], roi[3])) if roi is not None else 0.0


def part_sides_px(models: list[Any]) -> list[float]:
    """The smaller side of each model's teach ROI (a recipe's ``models`` entries), pixels."""
    out = []
    for m in models:
        teach = getattr(m, "teach", None)
        roi = getattr(teach, "roi", None)
        if roi is not None:
            out.append(float(min(roi[2], roi[3])))
    return out


def not_recognized_detail(occ: Occupancy, reason: str | None) -> str:
    """The cycle record's words for a picture with objects and no match."""
    boxes = ", ".join(str(b) for b in occ.boxes_px[:3])
    return (f"{occ.objects} object(s) in the search region and no match ({reason or 'nothing scored min_score'}): "
            f"parts the model does not recognise (another part, upside down, the light changed); boxes [u, v, w, h] "
            f"px: {boxes}; check the kept frame, then teach the part again or clear the area")
