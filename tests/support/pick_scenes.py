"""Rendered pick scenes with known part poses: the ground truth for tests and ``bench/pick.py``.

A part is a polygon outline with polygonal holes in *part coordinates* (pixels at the teach
scale, origin = the part's reference point, x right, y down). An instance at ``(u, v, angle_deg)``
maps a part point ``p`` to the image point ``(u, v) + R(angle) p`` with
``R = [[cos, sin], [-sin, cos]]`` — a rotation counter-clockwise as seen on screen, the sense of
``cv2.getRotationMatrix2D`` — optionally followed by a homography (a slightly tilted camera).

Edges are anti-aliased by supersampling: the part is filled at 16x scale with ``cv2.fillPoly``
(sub-pixel vertices through ``shift`` bits) and reduced with ``cv2.resize(INTER_AREA)``, so an
output pixel holds the part's area coverage of that pixel (pixel centres at integers).
Then come optical blur, uneven light, clutter, occlusion (background pasted over a fraction of
the part) and noise. Own code: OpenCV has no scene generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.image import wrap_deg

SUPERSAMPLE = 16
_JITTERS = 1
_SHIFT = 8  # fixed-point bits for cv2.fillPoly vertices on the supersampled canvas

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PartShape:
    """Outline and holes of a flat part, in part coordinates (px; origin = reference point)."""

    name: str
    outer: FloatArray
    holes: tuple[FloatArray, ...] = ()

    def extent_px(self) -> float:
        """Largest distance of an outline vertex from the reference point."""
        return float(np.max(np.hypot(self.outer[:, 0], self.outer[:, 1])))

    def half_size_px(self) -> tuple[float, float]:
        """Half width and half height of the outline's bounding box around the reference point."""
        return float(np.max(np.abs(self.outer[:, 0]))), float(np.max(np.abs(self.outer[:, 1])))


def _circle(cx: float, cy: float, r: float, n: int = 48) -> FloatArray:
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    return np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1)


def _slot(cx: float, cy: float, half_len: float, r: float, n: int = 16) -> FloatArray:
    t1 = np.linspace(-math.pi / 2, math.pi / 2, n)
    t2 = np.linspace(math.pi / 2, 3 * math.pi / 2, n)
    right = np.stack([cx + half_len + r * np.cos(t1), cy + r * np.sin(t1)], axis=1)
    left = np.stack([cx - half_len + r * np.cos(t2), cy + r * np.sin(t2)], axis=1)
    return np.concatenate([right, left])


def part_bracket(scale: float = 1.0) -> PartShape:
    """An asymmetric bracket (~180 x 120 px): L-shaped outline, chamfer, notch, two holes, a slot."""
    outer = np.array(
        [[-90, -60], [40, -60], [40, -20], [90, -20], [90, 45], [70, 60], [-20, 60],
         [-20, 40], [-40, 40], [-40, 60], [-90, 60]], dtype=np.float64)
    holes = (_circle(-55, -25, 13), _circle(60, 20, 9), _slot(10, 25, 18, 7))
    return PartShape("bracket", outer * scale, tuple(h * scale for h in holes))


def part_flange(scale: float = 1.0) -> PartShape:
    """A hexagonal flange with an off-centre square window and one round hole (~150 px across)."""
    t = np.deg2rad(np.arange(0, 360, 60) + 10.0)
    outer = np.stack([75 * np.cos(t), 70 * np.sin(t)], axis=1)
    outer = np.insert(outer, 2, [[10.0, 75.0]], axis=0)  # a bump breaks the hexagon's symmetry
    window = np.array([[-30, -30], [5, -30], [5, 5], [-30, 5]], dtype=np.float64)
    holes = (window, _circle(35, 25, 10))
    return PartShape("flange", outer * scale, tuple(h * scale for h in holes))


def part_tee(scale: float = 1.0) -> PartShape:
    """A T-shaped bar with one hole (~170 x 110 px)."""
    outer = np.array(
        [[-85, -55], [85, -55], [85, -20], [20, -20], [20, 55], [-15, 55], [-15, -20], [-85, -20]],
        dtype=np.float64)
    holes = (_circle(-55, -37, 9), _circle(2, 30, 8))
    return PartShape("tee", outer * scale, tuple(h * scale for h in holes))


PARTS = {"bracket": part_bracket, "flange": part_flange, "tee": part_tee}


def rotation(angle_deg: float) -> FloatArray:
    """2x2 rotation counter-clockwise on screen (y down), as cv2.getRotationMatrix2D."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, s], [-s, c]])


def _apply_h(H: FloatArray | None, pts: FloatArray) -> FloatArray:
    if H is None:
        return pts
    ph = np.concatenate([pts, np.ones((len(pts), 1))], axis=1) @ H.T
    return ph[:, :2] / ph[:, 2:3]


@dataclass(frozen=True)
class Instance:
    """One placed part: reference point (u, v) before the homography and rotation angle."""

    part: PartShape
    u_px: float
    v_px: float
    angle_deg: float
    occlusion: float = 0.0

    def image_points(self, pts: FloatArray, H: FloatArray | None = None) -> FloatArray:
        return _apply_h(H, np.array([self.u_px, self.v_px]) + pts @ rotation(self.angle_deg).T)


@dataclass
class Truth:
    """Ground truth of one instance in the image (after the homography)."""

    part: str
    u_px: float
    v_px: float
    angle_deg: float
    occlusion: float


def truth_of(inst: Instance, H: FloatArray | None) -> Truth:
    """Image of the reference point and the angle of the part's x axis (local affine of H)."""
    c = inst.image_points(np.zeros((1, 2)), H)[0]
    eps = 1e-3
    d = inst.image_points(np.array([[eps, 0.0]]), H)[0] - c
    angle = math.degrees(math.atan2(-d[1], d[0]))
    return Truth(inst.part.name, float(c[0]), float(c[1]), wrap_deg(angle), inst.occlusion)


def coverage(polys_outer: list[FloatArray], polys_holes: list[FloatArray],
             shape: tuple[int, int]) -> tuple[NDArray[np.float32], tuple[int, int]]:
    """Area coverage of (outer minus holes) on the pixel grid, cropped to the polygon's box.

    Returns ``(alpha, (x0, y0))``: ``alpha[j, i]`` is the coverage of image pixel ``(x0+i, y0+j)``.
    """
    h_img, w_img = shape
    allp = np.concatenate(polys_outer)
    x0 = max(int(math.floor(allp[:, 0].min())) - 2, 0)
    y0 = max(int(math.floor(allp[:, 1].min())) - 2, 0)
    x1 = min(int(math.ceil(allp[:, 0].max())) + 2, w_img - 1)
    y1 = min(int(math.ceil(allp[:, 1].max())) + 2, h_img - 1)
    if x1 < x0 or y1 < y0:
        return np.zeros((0, 0), np.float32), (x0, y0)
    S = SUPERSAMPLE
    size = (x1 - x0 + 1, y1 - y0 + 1)
    alpha = np.zeros((size[1], size[0]), np.float32)
    for j in range(_JITTERS):
        # fillPoly snaps edges to canvas rows/columns (1/S px); averaging renders whose sample
        # grids are offset by a quarter canvas pixel brings that to 1/(4S) px
        delta = (j + 0.5) / _JITTERS - 0.5
        canvas = np.zeros((size[1] * S, size[0] * S), np.uint8)

        def to_canvas(p: FloatArray, delta: float = delta) -> NDArray[np.int32]:
            # canvas pixel k (centre k) covers image x in [x0-0.5+k/S, x0-0.5+(k+1)/S]
            c = (p - np.array([x0, y0]) + 0.5) * S - 0.5 - delta
            return np.round(c * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2)

        cv2.fillPoly(canvas, [to_canvas(p) for p in polys_outer], 255, cv2.LINE_8, _SHIFT)
        if polys_holes:
            cv2.fillPoly(canvas, [to_canvas(p) for p in polys_holes], 0, cv2.LINE_8, _SHIFT)
        # INTER_AREA averages each S x S block: the pixel's coverage (to 1/255)
        alpha += cv2.resize(canvas, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    alpha /= _JITTERS
    return alpha.astype(np.float32) / 255.0, (x0, y0)


def _composite(img: NDArray[np.float32], alpha: NDArray[np.float32], org: tuple[int, int],
               value: float | NDArray[np.float32]) -> None:
    x0, y0 = org
    h, w = alpha.shape
    if h == 0:
        return
    win = img[y0:y0 + h, x0:x0 + w]
    win *= 1.0 - alpha
    win += alpha * value


@dataclass
class SceneStyle:
    """Imaging conditions of a rendered scene."""

    background: float = 90.0
    part_value: float = 190.0
    blur_sigma_px: float = 0.7
    noise_sigma: float = 2.0
    light_gradient: float = 0.0
    """Relative brightness change across the image (uneven light), e.g. 0.4."""
    vignetting: float = 0.0
    clutter: int = 0
    size: tuple[int, int] = (1280, 960)
    homography: FloatArray | None = None
    light_dir_deg: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)


def render(instances: list[Instance], style: SceneStyle,
           rng: np.random.Generator) -> tuple[NDArray[np.uint8], list[Truth]]:
    """Render the instances (each with its occlusion fraction) into one uint8 image."""
    w, h = style.size
    img = np.full((h, w), style.background, np.float32)
    for _ in range(style.clutter):
        _draw_clutter(img, rng)
    clean = img.copy() if any(inst.occlusion > 0 for inst in instances) else img  # (what an occlusion pastes back)
    H = style.homography
    truths = []
    for inst in instances:
        outer = [inst.image_points(inst.part.outer, H)]
        holes = [inst.image_points(p, H) for p in inst.part.holes]
        alpha, org = coverage(outer, holes, (h, w))
        _composite(img, alpha, org, style.part_value)
        if inst.occlusion > 0 and alpha.size:
            _occlude(img, clean, alpha, org, inst.occlusion, rng)
        truths.append(truth_of(inst, H))
    if style.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), style.blur_sigma_px)
    if style.light_gradient or style.vignetting:
        # the pixel grid as a column and a row, broadcast: the values of a full grid (float32) without making it
        yy, xx = np.arange(h, dtype=np.float32)[:, None], np.arange(w, dtype=np.float32)[None, :]
        a = math.radians(style.light_dir_deg)
        t = ((xx - w / 2) * math.cos(a) + (yy - h / 2) * math.sin(a)) / max(w, h)
        r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        img *= (1.0 + style.light_gradient * t) * (1.0 - style.vignetting * r2)
    if style.noise_sigma > 0:
        img += rng.normal(0.0, style.noise_sigma, img.shape).astype(np.float32)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), truths


def _occlude(img: NDArray[np.float32], clean: NDArray[np.float32], alpha: NDArray[np.float32],
             org: tuple[int, int], fraction: float, rng: np.random.Generator) -> None:
    """Paste background over the part beyond a random straight cut hiding ``fraction`` of its area."""
    x0, y0 = org
    hh, ww = alpha.shape
    yy, xx = np.mgrid[0:hh, 0:ww].astype(np.float64)
    a = rng.uniform(0, 2 * math.pi)
    proj = xx * math.cos(a) + yy * math.sin(a)
    wts = alpha.astype(np.float64).ravel()
    order = np.argsort(-proj.ravel())
    cum = np.cumsum(wts[order])
    k = int(np.searchsorted(cum, fraction * cum[-1]))
    thr = proj.ravel()[order[min(k, len(order) - 1)]]
    mask = proj >= thr
    win = img[y0:y0 + hh, x0:x0 + ww]
    win[mask] = clean[y0:y0 + hh, x0:x0 + ww][mask]


def _draw_clutter(img: NDArray[np.float32], rng: np.random.Generator) -> None:
    h, w = img.shape
    val = float(rng.uniform(40, 230))
    kind = rng.integers(0, 4)
    cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
    if kind == 0:
        cv2.circle(img, (cx, cy), int(rng.integers(5, 40)), val, -1, cv2.LINE_AA)
    elif kind == 1:
        box = ((float(cx), float(cy)), (float(rng.uniform(10, 90)), float(rng.uniform(5, 60))),
               float(rng.uniform(0, 180)))
        pts = cv2.boxPoints(box).astype(np.int32)
        cv2.fillConvexPoly(img, pts, val, cv2.LINE_AA)
    elif kind == 2:
        p2 = (cx + int(rng.integers(-150, 150)), cy + int(rng.integers(-150, 150)))
        cv2.line(img, (cx, cy), p2, val, int(rng.integers(1, 5)), cv2.LINE_AA)
    else:
        pts = np.array([[cx + rng.integers(-40, 40), cy + rng.integers(-40, 40)] for _ in range(3)],
                       np.int32)
        cv2.fillConvexPoly(img, pts, val, cv2.LINE_AA)


def teach_scene(part: PartShape, rng: np.random.Generator, *, style: SceneStyle | None = None,
                centre: tuple[float, float] = (640.0, 480.0), margin_px: float = 12.0,
                ) -> tuple[NDArray[np.uint8], tuple[float, float, float, float]]:
    """One upright instance with its reference point at ``centre``; returns (image, ROI U,V,W,H).

    The ROI is centred on the reference point, so the model's reference point is the part's.
    """
    st = style or SceneStyle()
    img, _ = render([Instance(part, centre[0], centre[1], 0.0)], st, rng)
    hw, hh = part.half_size_px()
    w, h = 2 * (hw + margin_px), 2 * (hh + margin_px)
    return img, (centre[0] - w / 2, centre[1] - h / 2, w, h)


def tilt_homography(size: tuple[int, int], tilt_deg: float, axis_deg: float,
                    focal_px: float = 1800.0) -> FloatArray:
    """Perspective of a camera turned by ``tilt_deg`` about an in-plane axis: ``K R K^-1``.

    Shifted so that the image centre stays where it was (a slightly tilted view of the table).
    """
    w, h = size
    K = np.array([[focal_px, 0, w / 2], [0, focal_px, h / 2], [0, 0, 1.0]])
    ax = np.array([math.cos(math.radians(axis_deg)), math.sin(math.radians(axis_deg)), 0.0])
    R, _ = cv2.Rodrigues(ax * math.radians(tilt_deg))
    Hm = K @ R @ np.linalg.inv(K)
    c = np.array([w / 2, h / 2, 1.0])
    m = Hm @ c
    m = m[:2] / m[2]
    T = np.array([[1, 0, w / 2 - m[0]], [0, 1, h / 2 - m[1]], [0, 0, 1.0]])
    return np.asarray(T @ Hm, dtype=np.float64)


def random_scene(rng: np.random.Generator, parts: list[PartShape], *, n_min: int = 1, n_max: int = 5,
                 occlusion_max: float = 0.0, tilt_deg: float = 0.0, clutter: int = 25,
                 size: tuple[int, int] = (1280, 960)) -> tuple[NDArray[np.uint8], list[Truth]]:
    """A scene of 1..5 non-overlapping random instances with random light, noise and clutter."""
    n = int(rng.integers(n_min, n_max + 1))
    w, h = size
    placed: list[Instance] = []
    tries = 0
    while len(placed) < n and tries < 500:
        tries += 1
        part = parts[int(rng.integers(0, len(parts)))]
        r = part.extent_px() + 4
        u, v = rng.uniform(r, w - r), rng.uniform(r, h - r)
        if any(math.hypot(u - p.u_px, v - p.v_px) < r + p.part.extent_px() + 4 for p in placed):
            continue
        occ = float(rng.uniform(0.0, occlusion_max)) if occlusion_max > 0 else 0.0
        placed.append(Instance(part, float(u), float(v), float(rng.uniform(-180, 180)), occ))
    H = None
    if tilt_deg > 0:
        H = tilt_homography(size, float(rng.uniform(0.5, 1.0)) * tilt_deg, float(rng.uniform(0, 360)))
    bright = rng.uniform() < 0.7
    style = SceneStyle(
        background=float(rng.uniform(60, 110)) if bright else float(rng.uniform(160, 200)),
        part_value=float(rng.uniform(170, 220)) if bright else float(rng.uniform(40, 90)),
        blur_sigma_px=float(rng.uniform(0.5, 0.9)),
        noise_sigma=float(rng.uniform(1.0, 3.0)),
        light_gradient=float(rng.uniform(0.0, 0.5)),
        vignetting=float(rng.uniform(0.0, 0.3)),
        light_dir_deg=float(rng.uniform(0, 360)),
        clutter=clutter, size=size, homography=H)
    return render(placed, style, rng)


def tray_scene(part: PartShape, rng: np.random.Generator) -> tuple[NDArray[np.uint8], list[Truth]]:
    """A full tray: 30 instances of ``part`` in 6 x 5 cells (212 x 190 px) of a 1280 x 960 image, each
    turned at random, with clutter, noise 2 grey levels and optical blur 0.7 px."""
    inst = [Instance(part, 110 + i * 212 + rng.uniform(-5, 5), 100 + j * 190 + rng.uniform(-5, 5),
                     float(rng.uniform(-180, 180))) for i in range(6) for j in range(5)]
    style = SceneStyle(size=(1280, 960), noise_sigma=2.0, clutter=10, blur_sigma_px=0.7)
    return render(inst, style, rng)


def roi_at_scale(roi: tuple[float, float, float, float], k: float) -> tuple[float, float, float, float]:
    """The ROI ``(U, V, W, H)`` in the image shrunk by ``k``, its centre (the reference point) mapped
    with the pixel-centre convention (the centre of the top-left pixel is (0, 0) at every size)."""
    u, v, w, h = roi
    cx, cy = (u + w / 2.0 + 0.5) / k - 0.5, (v + h / 2.0 + 0.5) / k - 0.5
    return (cx - w / (2 * k), cy - h / (2 * k), w / k, h / k)


# ----------------------------------------------------------------------------- look-alike distractors


def mirrored_part(part: PartShape) -> PartShape:
    """The part's mirror image (x -> -x about its reference point): the part lying face down."""
    flip = np.array([-1.0, 1.0])
    return PartShape(f"{part.name}-mirrored", part.outer[::-1] * flip, tuple(h[::-1] * flip for h in part.holes))


def part_without_hole(part: PartShape, index: int) -> PartShape:
    """The part with its hole ``index`` left out: a similar part lacking one feature."""
    holes = tuple(h for k, h in enumerate(part.holes) if k != index)
    return PartShape(f"{part.name}-without-hole-{index}", part.outer, holes)


def _clip_half(poly: FloatArray, normal: FloatArray) -> FloatArray:
    """The polygon's part where ``p . normal <= 0`` (Sutherland-Hodgman against one line)."""
    out: list[FloatArray] = []
    n = len(poly)
    for k in range(n):
        a, b = poly[k], poly[(k + 1) % n]
        da, db = float(a @ normal), float(b @ normal)
        if da <= 0:
            out.append(a)
        if (da <= 0) != (db <= 0):
            out.append(a + (b - a) * (da / (da - db)))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


def part_half(part: PartShape, angle_deg: float = 0.0) -> PartShape:
    """The part cut in two through its reference point by a line at ``angle_deg`` (part frame): the
    half on the side the line's normal points away from. Holes cut by the line open into notches
    (drawn as holes of the clipped outline); holes beyond it go."""
    a = math.radians(angle_deg)
    normal = np.array([-math.sin(a), math.cos(a)])
    outer = _clip_half(part.outer, normal)
    holes = tuple(c for c in (_clip_half(h, normal) for h in part.holes) if len(c) >= 3)
    return PartShape(f"{part.name}-half-{angle_deg:g}", outer, holes)


def distractor_scene(distractor: PartShape, rng: np.random.Generator, n: int = 4,
                     size: tuple[int, int] = (1280, 960)) -> NDArray[np.uint8]:
    """``n`` instances of a look-alike at random poses on the bench's imaging conditions (clutter,
    uneven light, noise 1-3 grey levels): an image where the part itself is nowhere."""
    w, h = size
    placed: list[Instance] = []
    r = distractor.extent_px() + 6
    tries = 0
    while len(placed) < n and tries < 500:
        tries += 1
        u, v = rng.uniform(r, w - r), rng.uniform(r, h - r)
        if all(math.hypot(u - p.u_px, v - p.v_px) >= 2 * r for p in placed):
            placed.append(Instance(distractor, float(u), float(v), float(rng.uniform(-180, 180))))
    style = SceneStyle(background=float(rng.uniform(60, 110)), part_value=float(rng.uniform(170, 220)),
                       blur_sigma_px=float(rng.uniform(0.5, 0.9)), noise_sigma=float(rng.uniform(1.0, 3.0)),
                       light_gradient=float(rng.uniform(0.0, 0.4)), light_dir_deg=float(rng.uniform(0, 360)),
                       clutter=15, size=size)
    img, _ = render(placed, style, rng)
    return img
