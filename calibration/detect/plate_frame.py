"""Circle plate segmentation and grid assignment: the dark frame, its marks, the mark grid and the
orientation triangle (steps 1-3 of ``calibration.detect.circle_plate``; our own)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

TRIANGLE_INSET = 0.5 / (2.0 + np.sqrt(2.0))
"""Incentre of the orientation triangle, from the frame's inner corner along both legs, in pitches."""


@dataclass
class Frame:
    corners: FloatArray  # (4, 2) inner frame corners, clockwise on screen
    marks: FloatArray  # (n, 2) coarse mark centres inside the frame
    ellipses: list[tuple[tuple[float, float], tuple[float, float], float]]


# ---------------------------------------------------------------------------------------------
# segmentation


def binarizations(grey: NDArray[np.uint8]) -> Iterator[NDArray[np.uint8]]:
    """Dark-is-255 masks to try in order: global Otsu, then local mean thresholds (uneven light)."""
    smooth = cv2.GaussianBlur(grey, (5, 5), 0)
    _, otsu = cv2.threshold(smooth, 0, 255, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
    yield otsu
    h, w = grey.shape
    for frac in (0.25, 0.08):
        block = max(int(min(h, w) * frac) | 1, 31)
        yield cv2.adaptiveThreshold(smooth, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, block, 10)


def _mark_like(contour: NDArray[np.int32]) -> tuple[tuple[float, float], tuple[float, float], float] | None:
    if len(contour) < 6:
        return None
    area = cv2.contourArea(contour)
    if area < 12:
        return None
    ell = cv2.fitEllipse(contour)
    (_, _), (a, b), _ = ell
    if a <= 2 or b <= 2:
        return None
    ell_area = np.pi * a * b / 4
    if not 0.8 < area / ell_area < 1.2:
        return None
    hull_area = cv2.contourArea(cv2.convexHull(contour))
    if hull_area <= 0 or area / hull_area < 0.93:
        return None
    return ell


def find_frames(binary: NDArray[np.uint8]) -> list[Frame]:
    """Candidate frames: dark regions with a large bright hole containing mark-like blobs."""
    contours, hier = cv2.findContours(binary, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
    if hier is None:
        return []
    h = hier[0]
    frames = []
    for j in range(len(contours)):
        parent = h[j][3]
        if parent < 0:
            continue
        # j is a hole (a bright region's boundary inside a dark one) if its depth is odd.
        depth, p = 0, parent
        while p >= 0:
            depth += 1
            p = h[p][3]
        if depth % 2 == 0:
            continue
        hole = contours[j]
        hole_area = cv2.contourArea(hole)
        if hole_area < 400:
            continue
        marks, ells = [], []
        k = h[j][2]
        while k >= 0:
            ell = _mark_like(contours[k])
            if ell is not None:
                marks.append(ell[0])
                ells.append(ell)
            k = h[k][0]
        if len(marks) < 4:
            continue
        quad = _quad(hole)
        if quad is None:
            continue
        frames.append(Frame(quad, np.asarray(marks, dtype=np.float64), ells))
    frames.sort(key=lambda f: -len(f.marks))
    return frames


def _quad(hole: NDArray[np.int32]) -> FloatArray | None:
    """Four inner frame corners (clockwise on screen) from line fits to the hole's sides."""
    hull = cv2.convexHull(hole)
    peri = cv2.arcLength(hull, True)
    approx = cv2.approxPolyDP(hull, 0.02 * peri, True).reshape(-1, 2).astype(np.float64)
    while len(approx) > 4:
        # drop the vertex whose removal loses the least area
        n = len(approx)
        loss = []
        for i in range(n):
            a, b, c = approx[i - 1], approx[i], approx[(i + 1) % n]
            loss.append(abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])))
        approx = np.delete(approx, int(np.argmin(loss)), axis=0)
    if len(approx) != 4:
        return None
    pts = hole.reshape(-1, 2).astype(np.float64)
    lines = []
    for i in range(4):
        a, b = approx[i], approx[(i + 1) % 4]
        d = b - a
        length = float(np.hypot(*d))
        if length < 8:
            return None
        t = ((pts - a) @ d) / length**2
        nrm = np.array([-d[1], d[0]]) / length
        dist = np.abs((pts - a) @ nrm)
        sel = pts[(t > 0.2) & (t < 0.8) & (dist < 0.05 * length + 2)]
        if len(sel) < 5:
            return None
        vx, vy, x0, y0 = cv2.fitLine(sel.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        lines.append((np.array([x0, y0], dtype=np.float64), np.array([vx, vy], dtype=np.float64)))
    corners = []
    for i in range(4):
        (p1, d1), (p2, d2) = lines[i - 1], lines[i]
        A = np.column_stack([d1, -d2])
        if abs(np.linalg.det(A)) < 1e-9:
            return None
        s = np.linalg.solve(A, p2 - p1)
        corners.append(p1 + s[0] * d1)
    Q = np.asarray(corners)
    x, y = Q[:, 0], Q[:, 1]
    signed = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    if signed < 0:
        Q = Q[::-1].copy()
    return Q


# ---------------------------------------------------------------------------------------------
# grid assignment


def _apply_h(H: FloatArray, p: FloatArray) -> FloatArray:
    q = np.column_stack([p, np.ones(len(p))]) @ H.T
    return q[:, :2] / q[:, 2:3]


def _match(H: FloatArray, marks: FloatArray, cols: int, rows: int, tol: float = 0.3
           ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Marks that lie within ``tol`` pitches of a grid node under ``H`` (grid -> image), one per node.

    Returns (mark indices, node ids)."""
    g = _apply_h(np.asarray(np.linalg.inv(H), dtype=np.float64), marks)
    node = np.rint(g)
    res = np.hypot(*(g - node).T)
    ok = (res < tol) & (node[:, 0] >= 0) & (node[:, 0] < cols) & (node[:, 1] >= 0) & (node[:, 1] < rows)
    ok &= np.all(np.isfinite(g), axis=1)
    idx = np.nonzero(ok)[0]
    ids = (node[idx, 1] * cols + node[idx, 0]).astype(np.int64)
    # a node claimed twice: keep the closer mark
    order = np.lexsort((res[idx], ids))
    idx, ids = idx[order], ids[order]
    first = np.ones(len(ids), dtype=bool)
    first[1:] = ids[1:] != ids[:-1]
    return idx[first], ids[first]


def grid_xy(ids: NDArray[np.int64], cols: int) -> FloatArray:
    return np.column_stack([ids % cols, ids // cols]).astype(np.float64)


def _fit_h(src: FloatArray, dst: FloatArray) -> FloatArray | None:
    if len(src) < 4:
        return None
    H, _ = cv2.findHomography(src, dst, 0)
    return None if H is None else np.asarray(H, dtype=np.float64)


def assign_grid(frame: Frame, cols: int, rows: int, mirrored: bool
            ) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64], bool] | None:
    """Best grid hypothesis of one handedness: (H grid->image, mark indices, ids, mirrored)."""
    C, R = cols, rows
    plate = np.array([[-1, -1], [C, -1], [C, R], [-1, R]], dtype=np.float64)
    best: tuple[int, float, FloatArray, NDArray[np.int64], NDArray[np.int64], bool] | None = None
    Q = frame.corners if not mirrored else frame.corners[::-1]
    for s in range(4):
        Qs = np.roll(Q, -s, axis=0)
        H = cv2.getPerspectiveTransform(plate.astype(np.float32), Qs.astype(np.float32)).astype(np.float64)
        idx, ids = _match(H, frame.marks, C, R, 0.35)
        for _ in range(2):
            H2 = _fit_h(grid_xy(ids, C), frame.marks[idx])
            if H2 is None:
                break
            H = H2
            idx, ids = _match(H, frame.marks, C, R, 0.3)
        # consistency of the frame with the grid: predicted inner corners vs measured ones
        pred = _apply_h(H, plate)
        pitch_px = np.median(np.hypot(*np.diff(pred, axis=0).T)) / max(C, R) if len(ids) else 1.0
        frame_err = float(np.max(np.hypot(*(pred - Qs).T))) / max(pitch_px, 1e-9)
        key = (len(ids), -frame_err)
        if best is None or key > (best[0], best[1]):
            best = (len(ids), -frame_err, H, idx, ids, mirrored)
    if best is None:
        return None
    n, neg_err, H, idx, ids, mirrored = best
    if -neg_err > 0.5:
        return None
    return H, idx, ids, mirrored


def _disc_mean(grey: NDArray[np.uint8], uv: FloatArray, radius: float) -> float:
    h, w = grey.shape
    r = max(1.0, radius)
    u0, u1 = int(np.floor(uv[0] - r)), int(np.ceil(uv[0] + r))
    v0, v1 = int(np.floor(uv[1] - r)), int(np.ceil(uv[1] + r))
    if u0 < 0 or v0 < 0 or u1 >= w or v1 >= h:
        return float("nan")
    vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
    m = (uu - uv[0]) ** 2 + (vv - uv[1]) ** 2 <= r * r
    return float(grey[v0 : v1 + 1, u0 : u1 + 1][m].mean())


def read_orientation(grey: NDArray[np.uint8], H: FloatArray, cols: int, rows: int,
                 grid_xy: FloatArray | None = None, uv: FloatArray | None = None) -> tuple[int, str]:
    """Which inner frame corner holds the triangle: 0 (-1,-1), 1 (C,-1), 2 (C,R), 3 (-1,R); -1 if unreadable.

    Each corner is probed through a homography fitted to the marks near that corner (lens
    distortion makes the plate-wide ``H`` extrapolate poorly to the frame), falling back to ``H``.
    """
    C, R = cols, rows
    e = TRIANGLE_INSET
    corners = np.array([[-1, -1], [C, -1], [C, R], [-1, R]], dtype=np.float64)
    inward = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    probes = corners + e * inward
    white = corners + 0.5 * inward  # bright plate between the frame corner and the corner mark
    dark = corners - 0.25 * inward  # on the frame itself
    Hk = []
    for k in range(4):
        Hc = None
        if grid_xy is not None and uv is not None:
            near = np.max(np.abs(grid_xy - (corners[k] + inward[k])), axis=1) <= 2
            if near.sum() >= 6:
                Hc = _fit_h(grid_xy[near], uv[near])
        Hk.append(H if Hc is None else Hc)
    scale = np.hypot(*(_apply_h(H, np.array([[0.0, 0.0], [1.0, 0.0]]))[1] - _apply_h(H, np.array([[0.0, 0.0]]))[0]))
    r = max(1.0, 0.06 * scale)
    t = []
    for k in range(4):
        p = _disc_mean(grey, _apply_h(Hk[k], probes[k : k + 1])[0], r)
        wv = _disc_mean(grey, _apply_h(Hk[k], white[k : k + 1])[0], r)
        dv = _disc_mean(grey, _apply_h(Hk[k], dark[k : k + 1])[0], r)
        if not (np.isfinite(p) and np.isfinite(wv) and np.isfinite(dv)) or wv - dv < 10:
            t.append(np.nan)
        else:
            t.append((p - dv) / (wv - dv))
    tt = np.asarray(t)
    if np.any(~np.isfinite(tt)):
        return -1, "orientation unreadable: an inner frame corner is outside the image or has no contrast"
    dark_corners = np.nonzero(tt < 0.5)[0]
    if len(dark_corners) != 1:
        return -1, (f"orientation unreadable: expected the triangle in exactly one inner frame corner, "
                    f"found it in {len(dark_corners)}")
    k = int(dark_corners[0])
    others = np.delete(tt, k)
    if tt[k] > 0.35 or np.min(others) < 0.65:
        return -1, "orientation unreadable: the orientation triangle is not clearly dark against the plate"
    return k, ""
