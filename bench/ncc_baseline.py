"""The OpenCV peer of the pick benchmarks: an NCC rotation sweep with ``cv2.matchTemplate``.

``cv2.matchTemplate`` (TM_CCOEFF_NORMED, absolute value so contrast reversal is allowed) over
templates rotated about the sub-pixel ROI centre — 4° steps at 1/4 scale, then 0.25° steps at
full scale around each candidate, with parabolic sub-pixel peaks in angle and position. Used by
``bench/pick.py`` (renders) and ``bench/pick_real.py`` (photographs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray


def wrap_deg(a: float) -> float:
    a = math.fmod(a, 360.0)
    if a <= -180.0:
        a += 360.0
    elif a > 180.0:
        a -= 360.0
    return a


@dataclass
class Found:
    u_px: float
    v_px: float
    angle_deg: float
    score: float





@dataclass
class TemplateBank:
    """Rotated templates about the sub-pixel reference point, at a scale."""

    scale: float
    angles_deg: NDArray[np.float64]
    templates: list[NDArray[np.uint8]]
    ref: tuple[float, float]  # reference point in template pixel coordinates


def _bank(teach: NDArray[np.uint8], ref: tuple[float, float], radius: float, scale: float,
          angles_deg: NDArray[np.float64]) -> TemplateBank:
    img = teach
    r = ref
    for _ in range(int(round(math.log2(1 / scale)))):
        img = cv2.pyrDown(img)
        r = (r[0] / 2, r[1] / 2)
    R = int(math.ceil(radius * scale)) + 1
    x0, y0 = int(math.floor(r[0])) - R, int(math.floor(r[1])) - R
    crop = img[y0:y0 + 2 * R + 1, x0:x0 + 2 * R + 1]
    c = (r[0] - x0, r[1] - y0)
    temps = []
    for a in angles_deg:
        M = cv2.getRotationMatrix2D(c, float(a), 1.0)
        temps.append(cv2.warpAffine(crop, M, (crop.shape[1], crop.shape[0]), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE))
    return TemplateBank(scale, angles_deg, temps, c)


def _parabola(ym: float, y0: float, yp: float) -> float:
    den = ym - 2 * y0 + yp
    return 0.0 if abs(den) < 1e-12 else float(np.clip(0.5 * (ym - yp) / den, -0.5, 0.5))


@dataclass
class Baseline:
    coarse: TemplateBank
    teach: NDArray[np.uint8]
    ref: tuple[float, float]
    radius: float
    fine_cache: dict[float, NDArray[np.uint8]] = field(default_factory=dict)

    @classmethod
    def build(cls, teach: NDArray[np.uint8], roi: tuple[float, float, float, float]) -> Baseline:
        u, v, w, h = roi
        ref = (u + w / 2, v + h / 2)
        radius = 0.5 * math.hypot(w, h)
        coarse = _bank(teach, ref, radius, 0.25, np.arange(-180.0, 180.0, 4.0))
        return cls(coarse, teach, ref, radius)

    def fine_template(self, angle: float) -> tuple[NDArray[np.uint8], tuple[float, float]]:
        key = round(angle, 4)
        b = _bank(self.teach, self.ref, self.radius, 1.0, np.array([key]))
        return b.templates[0], b.ref

    def find(self, img: NDArray[np.uint8], min_score: float = 0.5) -> list[Found]:
        small = cv2.pyrDown(cv2.pyrDown(img))
        maps = [np.abs(cv2.matchTemplate(small, t, cv2.TM_CCOEFF_NORMED)) for t in self.coarse.templates]
        stack = np.stack(maps)
        best = stack.max(axis=0)
        arg = stack.argmax(axis=0)
        dil = cv2.dilate(best, np.ones((5, 5), np.uint8))
        ys, xs = np.nonzero((best == dil) & (best >= 0.6 * min_score))
        order = np.argsort(-best[ys, xs])
        cands: list[tuple[float, float, float]] = []
        min_d = self.radius * 0.25 / 2
        for i in order[:40]:
            x, y = float(xs[i]), float(ys[i])
            if all((x - cx) ** 2 + (y - cy) ** 2 >= min_d ** 2 for cx, cy, _ in cands):
                cands.append((x, y, float(self.coarse.angles_deg[arg[ys[i], xs[i]]])))
        out: list[Found] = []
        for x, y, a in cands[:12]:
            # candidate reference point at full scale
            u0 = (x + self.coarse.ref[0]) * 4.0
            v0 = (y + self.coarse.ref[1]) * 4.0
            f = self._fine(img, u0, v0, a)
            if f is not None and f.score >= min_score:
                out.append(f)
        out.sort(key=lambda f: -f.score)
        final: list[Found] = []
        for f in out:
            if all(math.hypot(f.u_px - g.u_px, f.v_px - g.v_px) > self.radius / 3 for g in final):
                final.append(f)
        return final

    def _fine(self, img: NDArray[np.uint8], u0: float, v0: float, a0: float) -> Found | None:
        m = 8
        angles = a0 + np.arange(-4.0, 4.0 + 1e-9, 0.25)
        best: tuple[float, int, NDArray[np.float32], tuple[float, float], int, int] | None = None
        scores = []
        results = []
        for k, a in enumerate(angles):
            t, c = self.fine_template(float(a))
            x0 = int(round(u0 - c[0])) - m
            y0 = int(round(v0 - c[1])) - m
            if x0 < 0 or y0 < 0 or x0 + t.shape[1] + 2 * m > img.shape[1] or y0 + t.shape[0] + 2 * m > img.shape[0]:
                return None
            win = img[y0:y0 + t.shape[0] + 2 * m, x0:x0 + t.shape[1] + 2 * m]
            r = np.abs(cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED))
            s = float(r.max())
            scores.append(s)
            results.append((r, c, x0, y0))
            if best is None or s > best[0]:
                best = (s, k, r, c, x0, y0)
        if best is None:
            return None
        s, k, r, c, x0, y0 = best
        da = 0.0
        if 0 < k < len(angles) - 1:
            da = _parabola(scores[k - 1], scores[k], scores[k + 1]) * 0.25
        py, px = np.unravel_index(int(np.argmax(r)), r.shape)
        dx = _parabola(r[py, px - 1], r[py, px], r[py, px + 1]) if 0 < px < r.shape[1] - 1 else 0.0
        dy = _parabola(r[py - 1, px], r[py, px], r[py + 1, px]) if 0 < py < r.shape[0] - 1 else 0.0
        return Found(x0 + px + dx + c[0], y0 + py + dy + c[1], wrap_deg(float(angles[k] + da)), s)


