"""A sub-pixel reference for the screw heads of the real-photo corpus: the centre of each head's rim.

The corpus's ``measured_estimate`` for the screw heads is a Hough circle on the grey image (+-4 px,
biased by the head's shadow), and ``bench/screw_heads.py``'s colour ellipse (an Otsu threshold of the
HSV saturation) moves 0.3-2.6 px with its threshold. Neither is good to 1 px. Here, two independent
measures of the same point, both on the photo's **saturation** ``(max - min) / max`` of its colour
channels (the zinc head is grey, the wood orange; the head's shadow on the wood scales its colour and
leaves its saturation, so the shading that drags a grey-value edge barely moves this one):

A. **Rim circle** (``rim_circle``): 720 rays from a start centre; along each, the saturation (Gaussian
   sigma 1 px) sampled every 0.25 px, and the rim where it rises fastest (grey head -> orange wood),
   to a sub-pixel parabola; a geometric least-squares circle through those points with Tukey weights
   (splinters, the wood's grain, a scratch on the rim drop out), then the rays again from the new
   centre (3 rounds, the window narrowed to +-6 px of the last circle). Its 1-sigma is the fit's
   (residual RMS over the inliers, through the normal matrix) widened by a block jackknife over 12
   sectors of the rim (errors that neighbouring rays share).
B. **Polar symmetry** (``symmetry_centre``): the centre about which the saturation of the rim's band
   (radius -8..+8 px of A's) is most nearly the same at every angle (least variance over the angle,
   summed over the radii; Nelder-Mead from the start centre). No edges, no threshold: the whole band.

Their accuracy on renders (``--renders``): discs of the heads' size with a soft edge (blur sigma
1.2 px), a one-sided shadow on the background, lighting gradient, sensor noise and JPEG q85, and a
dark square socket turned at random; A's and B's errors against the drawn centre (seed 8: A 0.52 px
RMS, B 0.30 px; A's own 1-sigma, 0.05-0.3 px, does not hold the pull of the shadow, where blurred grey
zinc and dark wood mix into a low saturation a little outside the rim).

Run: ``.venv/bin/python bench/screw_rim.py`` (the 13 heads of the teach and test images: A, B, their
difference, A's 1-sigma; a few seconds), ``--renders`` (A's and B's error on 40 rendered heads).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

F64 = NDArray[np.float64]
RAYS = 720
STEP_PX = 0.25
SECTORS = 12
TUKEY_C = 4.685


def saturation(bgr: NDArray[np.uint8], sigma_px: float = 1.0) -> F64:
    """Saturation ``(max - min) / max`` of the BGR channels (0-1: unchanged when the light scales the
    colour, so a shadow on the wood leaves it as it is), smoothed by a Gaussian of ``sigma_px``."""
    f = cv2.GaussianBlur(bgr.astype(np.float64), (0, 0), 0.7)
    mx, mn = f.max(axis=2), f.min(axis=2)
    c = (mx - mn) / np.maximum(mx, 8.0)
    return cv2.GaussianBlur(c, (0, 0), sigma_px) if sigma_px > 0 else c


def _rim_points(c: F64, cx: float, cy: float, r_lo: float, r_hi: float) -> tuple[F64, F64]:
    """Along each ray from (cx, cy): the radius (px) where the saturation rises fastest between r_lo and
    r_hi (sub-pixel parabola), the ray's angle (rad), and that rise's size."""
    th = np.linspace(0.0, 2 * math.pi, RAYS, endpoint=False)
    r = np.arange(r_lo, r_hi + 1e-9, STEP_PX)
    xs = cx + np.cos(th)[:, None] * r[None, :]
    ys = cy + np.sin(th)[:, None] * r[None, :]
    prof = map_coordinates(c, [ys.ravel(), xs.ravel()], order=1, mode="nearest").reshape(xs.shape)
    d = np.gradient(prof, STEP_PX, axis=1)
    k = np.clip(np.argmax(d[:, 1:-1], axis=1) + 1, 1, len(r) - 2)
    i = np.arange(RAYS)
    y0, y1, y2 = d[i, k - 1], d[i, k], d[i, k + 1]
    den = y0 - 2 * y1 + y2
    off = np.where(np.abs(den) > 1e-12, 0.5 * (y0 - y2) / np.where(den == 0, 1, den), 0.0)
    rr = r[k] + np.clip(off, -0.5, 0.5) * STEP_PX
    return np.stack([cx + np.cos(th) * rr, cy + np.sin(th) * rr], axis=1), y1


def fit_circle(pts: F64, w0: F64 | None = None) -> tuple[F64, F64, F64]:
    """Geometric least-squares circle (cx, cy, r) through ``pts`` with Tukey weights (robust scale from
    the residuals' median absolute deviation): the circle, the final weights, the residuals (px)."""
    w = np.ones(len(pts)) if w0 is None else w0.copy()
    # algebraic (Kasa) start
    A = np.column_stack([pts, np.ones(len(pts))])
    b = (pts ** 2).sum(axis=1)
    sol = np.linalg.lstsq(A * w[:, None], b * w, rcond=None)[0]
    p = np.array([sol[0] / 2, sol[1] / 2, 0.0])
    p[2] = math.sqrt(max(sol[2] + p[0] ** 2 + p[1] ** 2, 1e-9))
    res = np.zeros(len(pts))
    for _ in range(30):
        dx, dy = pts[:, 0] - p[0], pts[:, 1] - p[1]
        dist = np.hypot(dx, dy)
        res = dist - p[2]
        s = 1.4826 * float(np.median(np.abs(res - np.median(res)))) + 1e-6
        u = res / (TUKEY_C * s)
        w = np.where(np.abs(u) < 1, (1 - u ** 2) ** 2, 0.0)
        J = np.column_stack([-dx / dist, -dy / dist, -np.ones(len(pts))])
        H = J.T @ (J * w[:, None])
        step = np.linalg.solve(H, -J.T @ (w * res))
        p = p + step
        if np.abs(step).max() < 1e-6:
            break
    return p, w, res


def _circle_sigma(pts: F64, p: F64, w: F64, res: F64) -> float:
    """1-sigma (px) of the circle's centre: the fit's, widened by a block jackknife over ``SECTORS``
    sectors of the rim; the larger of the two."""
    dx, dy = pts[:, 0] - p[0], pts[:, 1] - p[1]
    dist = np.hypot(dx, dy)
    J = np.column_stack([-dx / dist, -dy / dist, -np.ones(len(pts))])
    H = J.T @ (J * w[:, None])
    s2 = float((w * res ** 2).sum() / max(w.sum() - 3, 1))
    cov = s2 * np.linalg.inv(H)
    textbook = math.sqrt(0.5 * (cov[0, 0] + cov[1, 1]))
    ang = np.arctan2(dy, dx) % (2 * math.pi)
    blk = (ang / (2 * math.pi) * SECTORS).astype(int) % SECTORS
    cs = []
    for b in range(SECTORS):
        m = blk != b
        q, _, _ = fit_circle(pts[m], w[m])
        cs.append(q[:2])
    c = np.array(cs)
    jk = math.sqrt((SECTORS - 1) / SECTORS * float(((c - c.mean(axis=0)) ** 2).sum(axis=1).sum()) / 2)
    return max(textbook, jk)


def rim_circle(bgr: NDArray[np.uint8], x: float, y: float, r: float) -> tuple[float, float, float, float, float]:
    """Method A of the module from a start centre (x, y) and radius r (px): centre x, y, radius, the
    centre's 1-sigma (px, per axis) and the inliers' residual RMS (px)."""
    c = saturation(bgr)
    p = np.array([x, y, r])
    lo, hi = 0.6 * r, 1.4 * r
    for _ in range(3):
        pts, _ = _rim_points(c, p[0], p[1], lo, hi)
        p, w, res = fit_circle(pts)
        lo, hi = p[2] - 6.0, p[2] + 6.0
    sig = _circle_sigma(pts, p, w, res)
    inl = w > 0
    return float(p[0]), float(p[1]), float(p[2]), sig, float(np.sqrt(np.mean(res[inl] ** 2)))


def symmetry_centre(bgr: NDArray[np.uint8], x: float, y: float, r: float) -> tuple[float, float]:
    """Method B of the module: the centre (x, y) about which the saturation of the band r-8..r+8 px varies
    least with the angle."""
    c = saturation(bgr)
    th = np.linspace(0.0, 2 * math.pi, 360, endpoint=False)
    rr = np.arange(r - 8.0, r + 8.0 + 1e-9, 0.5)
    ct, st = np.cos(th)[None, :], np.sin(th)[None, :]

    def cost(q: F64) -> float:
        xs = q[0] + rr[:, None] * ct
        ys = q[1] + rr[:, None] * st
        v = map_coordinates(c, [ys.ravel(), xs.ravel()], order=3, mode="nearest").reshape(xs.shape)
        return float(v.var(axis=1).sum())

    out = minimize(cost, np.array([x, y]), method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-9,
                            "initial_simplex": np.array([[x, y], [x + 1, y], [x, y + 1]])})
    return float(out.x[0]), float(out.x[1])


def render_head(rng: np.random.Generator, size: int = 200) -> tuple[NDArray[np.uint8], float, float, float]:
    """A rendered head: a grey disc (radius 46-54 px) with a dark square socket turned at random on an
    orange background with a one-sided shadow, a lighting gradient, blur sigma 1.2 px, noise sigma 3
    and JPEG q85. Returns the BGR image and the drawn centre (x, y) and radius (pixel-centre convention)."""
    ss = 8
    cx, cy = size / 2 + rng.uniform(-5, 5), size / 2 + rng.uniform(-5, 5)
    r = rng.uniform(46, 54)
    yy, xx = np.mgrid[0:size * ss, 0:size * ss]
    X, Y = (xx + 0.5) / ss - 0.5, (yy + 0.5) / ss - 0.5
    wood = np.array([40.0, 110.0, 190.0])  # BGR
    zinc = np.array([150.0, 150.0, 145.0])
    sa = rng.uniform(0, 2 * math.pi)
    out = np.clip(np.hypot(X - cx - 6 * math.cos(sa), Y - cy - 6 * math.sin(sa)) - r, 0, None)
    shadow = np.clip(1.0 - 0.45 * np.exp(-out / 4.0), 0, 1)
    disc = np.hypot(X - cx, Y - cy) <= r
    a = rng.uniform(0, math.pi / 2)
    u, v = (X - cx) * math.cos(a) + (Y - cy) * math.sin(a), -(X - cx) * math.sin(a) + (Y - cy) * math.cos(a)
    sock = (np.abs(u) < 0.35 * r) & (np.abs(v) < 0.35 * r)
    img = np.where(disc[..., None], zinc, wood * np.where(disc, 1.0, shadow)[..., None])
    img = np.where(sock[..., None], 0.55 * zinc, img)
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    ramp = np.linspace(-1, 1, size)
    g = 1.0 + 0.3 * (ramp[None, :] * math.cos(sa) + ramp[:, None] * math.sin(sa))
    img = img * g[..., None]
    img = cv2.GaussianBlur(img, (0, 0), 1.2) + rng.normal(0, 3.0, img.shape)
    ok, enc = cv2.imencode(".jpg", np.clip(img, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 85])
    out = cv2.imdecode(enc, cv2.IMREAD_COLOR)
    if not ok or out is None:
        raise RuntimeError("JPEG round trip failed")
    return np.asarray(out, dtype=np.uint8), cx, cy, r


def renders(n: int = 40, seed: int = 8) -> None:
    """A's and B's error on ``n`` rendered heads (started 3 px off), RMS and largest (px)."""
    rng = np.random.default_rng(seed)
    ea, eb, ratio = [], [], []
    for _ in range(n):
        img, cx, cy, r = render_head(rng)
        x0, y0 = cx + rng.uniform(-3, 3), cy + rng.uniform(-3, 3)
        ax, ay, ar, sig, _ = rim_circle(img, x0, y0, r * rng.uniform(0.9, 1.1))
        bx, by = symmetry_centre(img, ax, ay, ar)
        ea.append(math.hypot(ax - cx, ay - cy))
        eb.append(math.hypot(bx - cx, by - cy))
        ratio.append(ea[-1] / (sig * math.sqrt(2)))
    for name, e in (("A rim circle", ea), ("B polar symmetry", eb)):
        a = np.array(e)
        print(f"{name}: RMS {math.sqrt(float((a ** 2).mean())):.3f} px, largest {a.max():.3f} px ({n} renders)")
    print(f"A: |error| / (sqrt(2) 1-sigma) RMS {math.sqrt(float((np.array(ratio) ** 2).mean())):.2f}")


def heads() -> list[tuple[Path, float, float]]:
    """Every screw head of the case (the teach image's four, then the tests' nine): image, start centre
    (the colour ellipse of ``bench/screw_heads.py``)."""
    from bench.pick_cases import load_cases
    from bench.screw_heads import colour_centre

    case = next(c for c in load_cases() if c.id == "robertson_screw_heads")
    out = []
    for u, v, w, h in [case.roi, *case.more_rois]:
        out.append((case.teach_path, u + w / 2.0, v + h / 2.0))
    for t in case.tests:
        for i in t.instances:
            out.append((t.path, i.x, i.y))
    res = []
    for path, x, y in out:
        cx, cy, _ = colour_centre(path, x, y)
        res.append((path, cx, cy))
    return res


def measure(path: Path, x: float, y: float) -> tuple[tuple[float, float, float, float, float], tuple[float, float]]:
    """Methods A and B on the head near (x, y) of image ``path``."""
    bgr = cv2.imread(str(path))
    if bgr is None:
        raise FileNotFoundError(path)
    a = rim_circle(bgr, x, y, 50.0)
    return a, symmetry_centre(bgr, a[0], a[1], a[2])


def main() -> None:
    if "--renders" in sys.argv[1:]:
        renders()
        return
    print("| image | A: rim circle x, y px | radius px | A 1-sigma px | rim residual RMS px | B: symmetry x, y px "
          "| A - B px |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    d = []
    for path, x, y in heads():
        (ax, ay, ar, sig, rms), (bx, by) = measure(path, x, y)
        d.append(math.hypot(ax - bx, ay - by))
        print(f"| {path.name} | ({ax:.2f}, {ay:.2f}) | {ar:.2f} | {sig:.3f} | {rms:.2f} | ({bx:.2f}, {by:.2f}) | "
              f"{d[-1]:.2f} |")
    rms = math.sqrt(float((np.array(d) ** 2).mean()))
    print(f"\nA - B: RMS {rms:.2f} px, largest {max(d):.2f} px over {len(d)} heads")


if __name__ == "__main__":
    main()
