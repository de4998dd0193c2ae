"""HALCON-style circle plate detection: our own (OpenCV has no detector for framed, oriented plates).

Geometry (docs/targets.md, ``calibration.targets.CirclePlate``): black marks on white, a
black frame whose inner edge lies one pitch outside the outer mark centres, and a black right
triangle in the frame's inner corner nearest mark (0, 0).

Steps:

1. Segment dark regions (Otsu, then a local-mean threshold for uneven light), and look for a
   dark region with a bright hole holding mark-like blobs: the frame and its marks.
2. The frame's inner edge gives four lines and corners; every way of laying the target's
   corners on them (four turns, and the mirror images for mirrored views) predicts the mark
   grid through a homography, refined on the matched marks. The hypothesis matching the most
   marks wins; too few matched marks, or more blobs than marks, is a "mark count mismatch".
3. The orientation triangle is read by sampling the four inner frame corners: exactly one must
   be dark (else "orientation unreadable"); it is the target's corner (-pitch, -pitch), so ids
   follow the plate, never the image. A square plate in a *mirrored* image (not a real camera)
   cannot be told from its transpose; we assume the printed side faces the camera.
4. Each mark's edge is located with sub-pixel precision along rays from its centre (the
   crossing of the half-way grey level between the local dark and light levels of each ray, so
   uneven light does not shift it); a direct least-squares ellipse (Fitzgibbon/Halir-Flusser)
   is fitted to those edge points, with outlier rejection (partly hidden marks are dropped).
   Each centre's 1-sigma uncertainty (``Detection.uv_sigma_px``) is the gradient-energy bound over
   the mark (``calibration.detect.precision``); the edge points' spread about the fit
   (``refine_marks_precise``) scattered too much from mark to mark to weight by (measured).
5. Perspective bias (Heikkilä, PAMI 2000): the imaged ellipse's centre is not the image of the
   mark's centre. The plate-to-image mapping is modelled around each mark from its grid
   neighbours (Gaussian-weighted: a homography plus a quadratic correction, so that lens
   distortion is followed too), the mark's rim is mapped through it and fitted with an ellipse, and (ellipse centre -
   mapped centre) is subtracted; twice, refitting on the corrected centres. ``Detection.uv``
   holds the corrected centres, ``uv_ellipse`` the raw ellipse centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detect.ellipse import conic_centres, fit_ellipses_direct, refine_marks
from calibration.detect.mark_grid import consistent_marks, local_homographies, perspective_bias
from calibration.detect.plate_frame import assign_grid, binarizations, find_frames, grid_xy, read_orientation
from calibration.detect.precision import gradient_sigma_px
from calibration.observations import Detection
from calibration.targets import CirclePlate

__all__ = ["conic_centres", "detect_circle_plate", "fit_ellipses_direct", "local_homographies", "perspective_bias",
           "refine_marks"]

FloatArray = NDArray[np.float64]

EDGE_SMOOTH_SIGMA_PX = 1.0
"""Gaussian smoothing before the edge rays are sampled: bilinear sampling of very sharp edges
otherwise leaves a systematic ~0.01 px centre error; a symmetric blur does not move a centre."""

@dataclass
class _Failure:
    stage: int  # how far the attempt got: 0 no frame, 1 count mismatch, 2 orientation
    reason: str



# ---------------------------------------------------------------------------------------------
# the detector


def _attempt(grey: NDArray[np.uint8], img: NDArray[np.float32], binary: NDArray[np.uint8], target: CirclePlate,
             image_name: str) -> Detection | _Failure:
    cols, rows = target.cols, target.rows
    n_expected = cols * rows
    max_missing = max(2, n_expected // 10)
    frames = find_frames(binary)
    if not frames:
        return _Failure(0, "no frame: no dark frame around a bright field with marks was found "
                        "(plate cropped, occluded frame, or too little contrast)")
    failure: _Failure | None = None
    for frame in frames[:3]:
        if len(frame.marks) > n_expected + max_missing:
            f = _Failure(1, f"mark count mismatch: {len(frame.marks)} marks inside the frame, the target "
                         f"has {cols}x{rows} = {n_expected}")
            failure = failure if failure and failure.stage > f.stage else f
            continue
        found_k: tuple[int, FloatArray, NDArray[np.int64], NDArray[np.int64]] | None = None
        # The printed side faces the camera unless only the mirror image fits (mirrored views).
        for mirrored in (False, True):
            assigned = assign_grid(frame, cols, rows, mirrored)
            if assigned is None:
                f = _Failure(1, f"mark count mismatch: the {len(frame.marks)} marks inside the frame do not "
                             f"form the target's {cols}x{rows} grid")
                failure = failure if failure and failure.stage > f.stage else f
                continue
            H, idx, ids, _ = assigned
            unmatched = len(frame.marks) - len(idx)
            if len(idx) < n_expected - max_missing or unmatched > max_missing:
                f = _Failure(1, f"mark count mismatch: {len(idx)} of {n_expected} marks of the {cols}x{rows} "
                             f"grid found ({unmatched} other blobs inside the frame)")
                failure = failure if failure and failure.stage > f.stage else f
                continue
            k, why = read_orientation(grey, H, cols, rows, grid_xy(ids, cols), frame.marks[idx])
            if k >= 0 and cols != rows and k in (1, 3):
                k, why = -1, ("orientation unreadable: the triangle is in a corner that does not fit the "
                              f"plate's {cols}x{rows} shape")
            if k < 0:
                f = _Failure(2, why)
                failure = failure if failure and failure.stage > f.stage else f
                continue
            found_k = (k, H, idx, ids)
            break
        if found_k is None:
            continue
        k, H, idx, ids = found_k
        # re-express ids so that the triangle corner is the target's (-1, -1)
        gx, gy = ids % cols, ids // cols
        if k == 0:
            nx, ny = gx, gy
        elif k == 2:
            nx, ny = cols - 1 - gx, rows - 1 - gy
        elif k == 1:
            nx, ny = gy, cols - 1 - gx
        else:
            nx, ny = rows - 1 - gy, gx
        new_ids = (ny * cols + nx).astype(np.int64)
        # sub-pixel ellipses
        ells = [frame.ellipses[m] for m in idx]
        c0 = np.array([e[0] for e in ells], dtype=np.float64)
        axes = np.array([e[1] for e in ells], dtype=np.float64) / 2
        angs = np.deg2rad(np.array([e[2] for e in ells], dtype=np.float64))
        centres, ok = refine_marks(img, c0, axes, angs)
        uv_ell = centres[ok]
        new_ids = new_ids[ok]
        if len(new_ids) < n_expected - max_missing:
            f = _Failure(1, f"mark count mismatch: only {len(new_ids)} of {n_expected} marks have a clean edge "
                         "(occluded or blurred)")
            failure = failure if failure and failure.stage > f.stage else f
            continue
        order = np.argsort(new_ids)
        new_ids, uv_ell = new_ids[order], uv_ell[order]
        grid = grid_xy(new_ids, cols)
        radius_pitch = target.diameter_mm / 2 / target.pitch_mm
        # a mark that its neighbours do not predict is partly hidden or merged: leave it out
        keep = consistent_marks(grid, uv_ell)
        new_ids, uv_ell, grid = new_ids[keep], uv_ell[keep], grid[keep]
        if len(new_ids) < n_expected - max_missing:
            f = _Failure(1, f"mark count mismatch: only {len(new_ids)} of {n_expected} marks fit the plate "
                         "(occluded or damaged)")
            failure = failure if failure and failure.stage > f.stage else f
            continue
        uv = uv_ell.copy()
        for _ in range(2):
            uv = uv_ell - perspective_bias(grid, uv, radius_pitch)
        return Detection(image_name, True, ids=new_ids, uv=uv, uv_ellipse=uv_ell,
                         uv_sigma_px=gradient_sigma_px(grey, uv_ell, float(np.median(axes))))
    return failure or _Failure(0, "no frame with marks was usable")


def detect_circle_plate(grey: NDArray[np.uint8], target: CirclePlate, image_name: str = "") -> Detection:
    """Marks of ``target`` in ``grey`` with plate-frame ids, bias-corrected centres, or a reason why not."""
    img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), EDGE_SMOOTH_SIGMA_PX)
    best: _Failure | None = None
    for binary in binarizations(grey):
        r = _attempt(grey, img, binary, target, image_name)
        if isinstance(r, Detection):
            return r
        if best is None or r.stage > best.stage:
            best = r
    return Detection(image_name, False, reason=best.reason if best else "no frame: nothing dark in the image")
