"""Per-point precision of a detection: a 1-sigma position uncertainty (px) for every point.

The estimate, from each point's own local fit window:

- **corners** (chessboard, ChArUco) and **circle marks** (circle grid, circle plate; window = the
  mark's size): the Cramér-Rao-type bound of locating a known local pattern in noise,
  ``cov = s_n² (Σ w g gᵀ)⁻¹ (Σ w² g gᵀ) (Σ w g gᵀ)⁻¹`` over the point's window (Gaussian weights
  ``w``), with ``g`` the image gradient of the lightly smoothed image and ``s_n`` the image noise.
  Low contrast (small ``g``), blur (gradient energy spread thin), foreshortening and acute
  corners (an ill-conditioned tensor) all raise it.
- the circle plate's ellipse fit also yields the edge points' spread about the fitted ellipse
  (``calibration.detect.ellipse.refine_marks_precise``: ``s_e · sqrt(2 / n)``); it scatters too
  much from mark to mark to weight by: on rendered plates it made calibrations worse than
  unweighted, the gradient bound slightly better, so the detector reports the latter.

The image noise ``s_n`` is Immerkær's estimator (the response to a 3x3 Laplacian-difference
kernel that cancels planes and edges to first order), made robust by averaging only the smallest
80 % of the responses (a truncated half-normal mean: continuous, where a median of 8-bit
responses is an integer and took levels 0.25 grey apart), over the detection's bounding box,
floored at the 8-bit quantisation (1/sqrt(12) grey).

The numbers are estimates of the random part only; the solvers use them as *relative* weights
(``calibration.observations.point_weights``) and estimate the overall scale from the residuals.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detect.sampling import sample_bilinear

FloatArray = NDArray[np.float64]

QUANTISATION_GREY = 1.0 / np.sqrt(12.0)
MAX_SIGMA_PX = 10.0
"""Cap of a reported point uncertainty (a point whose window carries no structure)."""
CORNER_WINDOW_SIGMA_PX = 2.1
"""Gaussian window of the corner estimate: the saddle refinement's (half window 3 px, sigma 0.7 x 3)."""
NOISE_FRACTION = 0.8
"""The noise estimate averages this fraction of the smallest |responses| (the rest: edges, corners)."""
_LOW_MEAN_OF_HALF_NORMAL = 0.5586
"""Mean of the smallest 80 % of |N(0, 1)| draws: 2 (phi(0) - phi(1.2816)) / 0.8."""
_IMMERKAER = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], dtype=np.float32)


def image_noise_grey(grey: NDArray[np.uint8], uv: FloatArray, pad_px: int = 10) -> float:
    """Robust 1-sigma pixel noise (grey levels) in the bounding box of ``uv`` (Immerkær 1996)."""
    h, w = grey.shape[:2]
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        return float("nan")
    x0, y0 = np.maximum(np.floor(pts.min(axis=0)).astype(int) - pad_px, 0)
    x1, y1 = np.minimum(np.ceil(pts.max(axis=0)).astype(int) + pad_px, [w - 1, h - 1])
    roi = grey[y0:y1 + 1, x0:x1 + 1].astype(np.float32)
    if min(roi.shape) < 3:
        return QUANTISATION_GREY
    resp = np.sort(np.abs(cv2.filter2D(roi, cv2.CV_32F, _IMMERKAER)[1:-1, 1:-1]).ravel())
    # The kernel's sum of squares is 36. A median of 8-bit responses is an integer (the estimate
    # took a few levels 0.25 grey apart: issue 26), so the mean of the smallest NOISE_FRACTION of
    # the responses is used: as robust to the edges' large responses, and continuous.
    low = resp[: max(1, int(NOISE_FRACTION * resp.size))]
    sigma = float(np.mean(low, dtype=np.float64)) / _LOW_MEAN_OF_HALF_NORMAL / 6.0
    return max(sigma, QUANTISATION_GREY)


def gradient_sigma_px(grey: NDArray[np.uint8], uv: FloatArray, window_sigma_px: float | FloatArray,
                      smooth_sigma_px: float = 1.0) -> FloatArray:
    """(N,) 1-sigma position uncertainty (px, per axis, RMS of the two) of points ``uv`` located
    from the image structure in a Gaussian window of ``window_sigma_px`` around each (one for all
    points or one per point)."""
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(0)
    noise = image_noise_grey(grey, pts)
    img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), smooth_sigma_px)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    ws = np.broadcast_to(np.asarray(window_sigma_px, dtype=np.float64), (len(pts),))
    out = np.empty(len(pts))
    for w in np.unique(ws):
        sel = ws == w
        out[sel] = _window_sigma(gx, gy, pts[sel], float(w), noise)
    return out


def _window_sigma(gx: NDArray[np.float32], gy: NDArray[np.float32], pts: FloatArray, window_sigma_px: float,
                  noise: float) -> FloatArray:
    """``gradient_sigma_px`` for points sharing one window, from the image gradients (grey / px)."""
    # Large windows (big blobs) are sampled on a coarser lattice; each sample then stands for
    # step² pixels (and keeps cv2.remap's maps under its 32767-column limit).
    step = max(1.0, window_sigma_px / 3.0)
    half = max(2, int(np.ceil(2.5 * window_sigma_px / step)))
    r = np.arange(-half, half + 1, dtype=np.float64) * step
    du, dv = (a.ravel() for a in np.meshgrid(r, r))
    wts = np.exp(-(du**2 + dv**2) / (2 * window_sigma_px**2))
    mu = pts[:, 0:1] + du[None, :]
    mv = pts[:, 1:2] + dv[None, :]
    sx, sy = sample_bilinear(gx, mu, mv), sample_bilinear(gy, mu, mv)
    g = np.stack([sx, sy], axis=2)                                   # (N, k, 2)
    M = step**2 * np.einsum("k,nka,nkb->nab", wts, g, g)
    M2 = step**2 * np.einsum("k,nka,nkb->nab", wts**2, g, g)
    det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] ** 2
    ok = det > 1e-12 * np.maximum(np.einsum("naa->n", M) ** 2, 1e-300)
    M[~ok] = np.eye(2)
    Minv = np.linalg.inv(M)
    cov = noise**2 * Minv @ M2 @ Minv
    out = np.sqrt(np.maximum(np.einsum("naa->n", cov) / 2.0, 0.0))
    out[~ok] = np.inf
    return np.minimum(out, MAX_SIGMA_PX)
