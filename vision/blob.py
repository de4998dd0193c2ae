"""Blob route (the seed's ``threshold -> select_shape -> area_center``): fast, for simple scenes.

Teach: threshold the ROI (a fixed grey value or Otsu's), keep the largest region that does not
touch the ROI border, and remember its area, elongation and compactness, its orientation (major
axis from the second moments, the direction along it from the sign of the third moment) and
where the ROI centre lies in the region's own frame.

Find: threshold the image the same way, select the regions whose area and shape features are
within the tolerances, and give each one's reference point and rotation. Centres use grey-value
weighted moments over the region's edge band, so they are sub-pixel; regions touching the image
border are skipped (their moments would be cut).

Built on OpenCV (``threshold``, ``connectedComponentsWithStats``, ``moments``); our own part is
the feature selection, the sub-pixel weighting and the 180° disambiguation.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.errors import TeachError
from vision.image import as_gray, wrap_deg
from vision.types import FindResult, Match, SearchParams

U8 = NDArray[np.uint8]


@dataclass(frozen=True)
class BlobParams:
    """Teach parameters of a blob model (stored in the model file)."""

    threshold: float | None = None
    """Fixed grey threshold; ``None``: Otsu's threshold of the ROI at teach time, of the image at find."""
    polarity: str = "auto"
    """``bright`` (part brighter than the background), ``dark``, or ``auto`` (decided at teach)."""
    area_tolerance: float = 0.25
    """Relative area difference still accepted."""
    shape_tolerance: float = 0.25
    """Relative elongation/compactness difference still accepted."""

    def to_dict(self) -> dict[str, Any]:
        return {"threshold": self.threshold, "polarity": self.polarity,
                "area_tolerance": self.area_tolerance, "shape_tolerance": self.shape_tolerance}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BlobParams:
        thr = d.get("threshold")
        return cls(None if thr is None else float(thr), str(d.get("polarity", "auto")),
                   float(d.get("area_tolerance", 0.25)), float(d.get("shape_tolerance", 0.25)))


@dataclass
class BlobModel:
    params: BlobParams
    polarity: str
    threshold: float
    """The threshold used at teach (Otsu's or the fixed one)."""
    area_px: float
    elongation: float
    """sqrt(major / minor second moment) >= 1."""
    compactness: float
    """4 pi area / perimeter^2 (1 for a disc)."""
    angle_rad: float
    """Direction of the major axis in the teach image (atan2 in image coordinates, y down)."""
    directed: bool
    """Whether the third moment fixes the direction (else the angle is known modulo 180°)."""
    offset_px: tuple[float, float]
    """Reference point minus region centre, in the teach image."""

    def to_dict(self) -> dict[str, Any]:
        return {"polarity": self.polarity, "threshold": self.threshold, "area_px": self.area_px,
                "elongation": self.elongation, "compactness": self.compactness,
                "angle_deg": math.degrees(self.angle_rad), "directed": self.directed,
                "offset_px": list(self.offset_px)}

    @classmethod
    def from_dict(cls, d: dict[str, Any], params: BlobParams) -> BlobModel:
        try:
            return cls(params, str(d["polarity"]), float(d["threshold"]), float(d["area_px"]),
                       float(d["elongation"]), float(d["compactness"]), math.radians(float(d["angle_deg"])),
                       bool(d["directed"]), (float(d["offset_px"][0]), float(d["offset_px"][1])))
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise TeachError(f"blob model is incomplete or corrupt ({exc})") from exc


@dataclass
class _Region:
    cx: float
    cy: float
    area: float
    elongation: float
    compactness: float
    angle: float
    directed: bool


def _binary(img: U8, threshold: float, polarity: str) -> U8:
    mode = cv2.THRESH_BINARY if polarity == "bright" else cv2.THRESH_BINARY_INV
    _, b = cv2.threshold(img, threshold, 1, mode)
    return b


def _otsu(img: U8) -> float:
    t, _ = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return float(t)


def _region(img: U8, labels: NDArray[np.int32], label: int, box: tuple[int, int, int, int],
            polarity: str, lo: float, hi: float) -> _Region | None:
    """Features of one labelled region; moments weighted by grey value over its edge band."""
    x, y, w, h = box
    m = 3
    H, W = img.shape
    x0, y0, x1, y1 = max(x - m, 0), max(y - m, 0), min(x + w + m, W), min(y + h + m, H)
    mask = (labels[y0:y1, x0:x1] == label).astype(np.uint8)
    band = cv2.dilate(mask, np.ones((5, 5), np.uint8))
    g = img[y0:y1, x0:x1].astype(np.float32)
    wgt = (g - lo) / max(hi - lo, 1e-3)
    if polarity == "dark":
        wgt = 1.0 - wgt
    wgt = np.clip(wgt, 0.0, 1.0) * band
    # pixels deep inside the region count fully (noise there must not move the centre)
    inner = cv2.erode(mask, np.ones((5, 5), np.uint8))
    wgt[inner > 0] = 1.0
    mo = cv2.moments(wgt, binaryImage=False)
    if mo["m00"] <= 1e-6:
        return None
    cx, cy = mo["m10"] / mo["m00"] + x0, mo["m01"] / mo["m00"] + y0
    mu20, mu02, mu11 = mo["mu20"] / mo["m00"], mo["mu02"] / mo["m00"], mo["mu11"] / mo["m00"]
    ang = 0.5 * math.atan2(2 * mu11, mu20 - mu02)
    common = math.sqrt(max(((mu20 - mu02) / 2) ** 2 + mu11 ** 2, 0.0))
    l1 = (mu20 + mu02) / 2 + common
    l2 = max((mu20 + mu02) / 2 - common, 1e-9)
    c, s = math.cos(ang), math.sin(ang)
    m3 = (c ** 3 * mo["mu30"] + 3 * c * c * s * mo["mu21"] + 3 * c * s * s * mo["mu12"]
          + s ** 3 * mo["mu03"]) / mo["m00"]
    scale3 = l1 ** 1.5
    directed = abs(m3) > 0.02 * scale3
    if m3 < 0:
        ang += math.pi
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    perim = sum(cv2.arcLength(cn, True) for cn in contours)
    area = float(mo["m00"])
    compact = 4 * math.pi * area / max(perim * perim, 1e-9)
    return _Region(cx, cy, area, math.sqrt(l1 / l2), compact, ang, directed)


def teach(image: NDArray[Any], roi: tuple[float, float, float, float],
          params: BlobParams | None = None) -> BlobModel:
    """Teach a blob model from the ROI ``(U, V, W, H)``; its centre is the reference point."""
    p = params or BlobParams()
    img = as_gray(image)
    u, v, w, h = roi
    x0, y0 = int(math.ceil(u)), int(math.ceil(v))
    x1, y1 = int(math.floor(u + w)), int(math.floor(v + h))
    crop = img[y0:y1 + 1, x0:x1 + 1]
    if crop.size < 16:
        raise TeachError("the ROI is too small for a blob model (fewer than 16 pixels)")
    thr = p.threshold if p.threshold is not None else _otsu(crop)
    polarities = [p.polarity] if p.polarity in ("bright", "dark") else ["bright", "dark"]
    best: tuple[float, str, _Region] | None = None
    for pol in polarities:
        b = _binary(crop, thr, pol)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(b, connectivity=8)
        for k in range(1, n):
            bx, by, bw, bh, area = (int(t) for t in stats[k])
            touches = bx == 0 or by == 0 or bx + bw >= crop.shape[1] or by + bh >= crop.shape[0]
            if touches or area < 16:
                continue
            if best is None or area > best[0]:
                lo, hi = _class_means(crop, thr)
                reg = _region(crop, labels, k, (bx, by, bw, bh), pol, lo, hi)
                if reg is not None:
                    best = (float(area), pol, reg)
    if best is None:
        raise TeachError("no region inside the ROI stands out from the background: enlarge the ROI "
                         "so it shows the whole part with some background around it, or set a threshold")
    _, pol, reg = best
    ref = (u + w / 2.0, v + h / 2.0)
    cx, cy = reg.cx + x0, reg.cy + y0
    return BlobModel(p, pol, float(thr), reg.area, reg.elongation, reg.compactness, reg.angle,
                     reg.directed, (ref[0] - cx, ref[1] - cy))


def _class_means(img: U8, thr: float) -> tuple[float, float]:
    lo_px = img[img <= thr]
    hi_px = img[img > thr]
    lo = float(np.median(lo_px)) if lo_px.size else 0.0
    hi = float(np.median(hi_px)) if hi_px.size else 255.0
    return lo, hi


def find(model: BlobModel, image: NDArray[Any], search: SearchParams | None = None) -> FindResult:
    """Regions matching the blob model, best score first."""
    sp = search or SearchParams()
    t0 = time.perf_counter()
    img = as_gray(image)
    H, W = img.shape
    thr = model.params.threshold if model.params.threshold is not None else _otsu(img)
    lo, hi = _class_means(img, thr)
    b = _binary(img, thr, model.polarity)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(b, connectivity=8)
    tol_a, tol_s = model.params.area_tolerance, model.params.shape_tolerance
    matches: list[Match] = []
    timed_out = False
    for k in range(1, n):
        bx, by, bw, bh, area = (int(t) for t in stats[k])
        if abs(area - model.area_px) > 1.5 * tol_a * model.area_px:
            continue
        if bx == 0 or by == 0 or bx + bw >= W or by + bh >= H:
            continue
        if sp.timeout_s is not None and time.perf_counter() - t0 > sp.timeout_s:
            timed_out = True
            break
        reg = _region(img, labels, k, (bx, by, bw, bh), model.polarity, lo, hi)
        if reg is None:
            continue
        da = abs(reg.area - model.area_px) / model.area_px
        de = abs(reg.elongation - model.elongation) / model.elongation
        dc = abs(reg.compactness - model.compactness) / model.compactness
        if da > tol_a or de > tol_s or dc > tol_s:
            continue
        score = max(0.0, 1.0 - (da / tol_a + de / tol_s + dc / tol_s) / 3.0)
        if score < sp.min_score:
            continue
        theta = model.angle_rad - reg.angle  # R(theta) turns the teach axis onto this region's axis
        if not (model.directed and reg.directed):
            theta = math.atan2(math.sin(2 * theta), math.cos(2 * theta)) / 2  # known modulo 180°
        c, s = math.cos(theta), math.sin(theta)
        ox, oy = model.offset_px
        u = reg.cx + c * ox + s * oy
        v = reg.cy - s * ox + c * oy
        if sp.roi is not None:
            su, sv, sw, sh = sp.roi
            if not (su <= u <= su + sw and sv <= v <= sv + sh):
                continue
        ang = wrap_deg(math.degrees(theta))
        rel = wrap_deg(ang - sp.angle_start_deg)
        if sp.angle_extent_deg < 360.0 and not (0.0 <= (rel % 360.0) <= sp.angle_extent_deg):
            continue
        matches.append(Match(u, v, ang, score))
    matches.sort(key=lambda m: -m.score)
    if sp.max_count is not None:
        matches = matches[:sp.max_count]
    return FindResult(matches, timed_out, time.perf_counter() - t0)
