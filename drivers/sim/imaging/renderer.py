"""Geometrically exact rendering of planar patterns seen by a camera model.

Inverse mapping: every pixel's ray (through the full lens model) is intersected with each
planar object, and the object's reflectance function is evaluated at the hit point in the
object's own frame. Pixels whose neighbourhood is not uniform are supersampled on an
``n x n`` grid (box filter over the pixel's area), so edges are anti-aliased and land where the
model projects them. Sub-pixel rays are interpolated linearly from the per-pixel ray field
(the field is smooth; the interpolation error is ~1e-9 px).

Why it is fast (a 1280x960 frame of the virtual cell in ~0.13x the time it took before; figures in
``bench/results/render.md``):
- the ray field (the lens inversion) is computed exactly on a 16 px grid and interpolated by a
  quintic spline (separable; its local B-spline basis as sparse products; error ~1e-7 px, checked
  against the exact inversion at sample pixels, with a fall-back to the per-pixel inversion),
  cached per model;
- a plane maps rays to its own coordinates by a homography, tested only inside the plane's
  window (the image box its ``extent_m`` can cover, found on a coarse grid), in compiled loops
  (``drivers.sim.imaging.kernels``) that hand the reflectance function only the rays that hit;
- planes are shaded front to back, so an occluded plane's reflectance is not evaluated;
- supersampling visits only the edge pixels, and a pixel whose neighbours all see one object
  only that object;
- the targets' own patterns (circle plate, chessboard, circle grid) are shaded in compiled loops,
  bit-identical to their numpy ``reflectance`` (``drivers.sim.imaging.patterns``), and an edge pixel
  that sees one such pattern is supersampled in one fused loop;
- bands of rows, then runs of edge pixels, go to a few threads (``RENDER_THREADS``); every
  pixel's result is independent of the split.

This is our own code: OpenCV has no renderer; the virtual cell and the benchmarks need one whose
geometry is known to better than 0.02 px. Grey levels and camera defects: ``drivers.sim.imaging.sensor``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cmp_to_key
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from drivers.errors import DriverInputError
from drivers.sim.imaging.field import ray_field
from drivers.sim.imaging.pool import Scratch, parallel
from drivers.sim.imaging.pool import scratch as scratch_for
from drivers.sim.imaging.sensor import Imaging, to_grey

if TYPE_CHECKING:
    from drivers.sim.imaging.patterns import Shader

__all__ = ["Imaging", "PlanarObject", "prepare", "ray_field", "render", "render_reflectance", "render_scene", "to_grey"]

Reflectance = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


class RenderError(DriverInputError):
    """An object handed to the renderer does not behave as the contract says."""


_WINDOW_PX = 8
"""Grid step (px) on which a plane's image window is found."""


@dataclass(frozen=True)
class PlanarObject:
    """A plane ``z = 0`` of frame ``obj`` placed at ``T_cam_obj``, with its printed pattern.

    ``reflectance(x, y)`` takes object-frame coordinates (metres, 1-D float64 arrays of the rays
    that hit the plane) and returns values in [0, 1], NaN where the object is not.
    ``extent_m`` ``(x_min, y_min, x_max, y_max)`` bounds where it may be non-NaN; it only saves
    work. It defaults to the target's own ``extent_m()`` when ``reflectance`` is a method of a
    target that has one, else the plane is unbounded.
    """

    T_cam_obj: NDArray[np.float64]
    reflectance: Reflectance
    extent_m: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.extent_m is None:
            extent = getattr(getattr(self.reflectance, "__self__", None), "extent_m", None)
            if callable(extent):
                box = tuple(float(v) for v in extent())
                if len(box) == 4:
                    object.__setattr__(self, "extent_m", box)


def _kernels(patterns: bool = False) -> ModuleType:
    """The compiled loops (or the targets' compiled shaders), imported on first use (numba's
    import and start-up take a while)."""
    if patterns:
        from drivers.sim.imaging import patterns as render_patterns

        return render_patterns
    from drivers.sim.imaging import kernels as render_kernels

    return render_kernels


def prepare(camera: CameraModel) -> None:
    """Do the one-off work of a camera's first frame now: invert its lens and load the compiled
    loops (from numba's disk cache; compiled there on the very first run). Thread-safe; a device
    calls it in the background when it opens, so that its first frame costs what the others do."""
    from calibration.targets import CirclePlate

    tiny = CameraModel("opencv5", 16, 12, np.array([[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]]))
    T = np.eye(4)
    T[2, 3] = 1.0
    near = T.copy()
    near[:3, 3] = [-0.005, -0.005, 0.1]
    # A compiled pattern in front of a numpy one, every pass of a frame, and the imaging stage.
    objects = [PlanarObject(near, CirclePlate(2, 2, 10.0, 5.0).reflectance),
               PlanarObject(T, lambda x, y: (x > 0).astype(np.float64))]
    refl, depth = render_scene(tiny, objects, supersample=2)
    to_grey(refl, Imaging(noise_sigma=1.0, light_gradient=0.1, gain_dn_per_e=0.05, read_noise_dn=1.0),
            np.random.default_rng(0), depth)
    ray_field(camera)


# -- planes ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Plane:
    index: int
    H: NDArray[np.float64]
    """Rays ``[x, y, 1]`` to homogeneous object coordinates; row 2 is the plane normal ``n``."""
    d: float
    """``n . t``: the depth (z, m) of the hit is ``d / (n . ray)``."""
    window: tuple[int, int, int, int]
    """Image rows ``r0:r1`` and columns ``c0:c1`` the plane can be seen in."""
    coarse_depth: NDArray[np.float64]
    """Depth (m) at the window grid's samples, inf where the plane is not near or behind."""
    obj: PlanarObject
    shader: Shader | None
    """The compiled shading of the object's pattern (``drivers.sim.imaging.patterns``), if it has one."""


_Coarse = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_],
                NDArray[np.float64]]
"""A frame's hits on the window grid: depth, object x, y, in front of the camera, footprint."""


def _plane(index: int, obj: PlanarObject, field: NDArray[np.float64],
           memo: dict[bytes, _Coarse]) -> _Plane | None:
    T = np.asarray(obj.T_cam_obj, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    n = R[:, 2]
    d = float(n @ t)
    H = np.stack([d * R[:, 0] - float(R[:, 0] @ t) * n, d * R[:, 1] - float(R[:, 1] @ t) * n, n])
    s = _WINDOW_PX
    rows, cols, c = _coarse_rays(field)
    key = T.tobytes()
    if key not in memo:  # objects that share a frame (parts on the table) share the coarse hits
        with np.errstate(divide="ignore", invalid="ignore"):
            w = c[..., 0] * n[0] + c[..., 1] * n[1] + n[2]
            lam = d / w
            ox = (c[..., 0] * H[0, 0] + c[..., 1] * H[0, 1] + H[0, 2]) / w
            oy = (c[..., 0] * H[1, 0] + c[..., 1] * H[1, 1] + H[1, 2]) / w
        memo[key] = (lam, ox, oy, np.isfinite(lam) & (lam > 0), _footprint(ox, oy))
    lam, ox, oy, front, foot = memo[key]
    if not front.any():
        return None
    if obj.extent_m is None:
        near = front
    else:
        # A coarse sample is near the extent when it lies within its own grid step's footprint
        # of the box: every pixel that sees the box is then within one step of such a sample.
        # Samples whose neighbour is behind the camera (or at the horizon) count as near.
        x0, y0, x1, y1 = obj.extent_m
        m = 1.5 * foot
        near = front & (ox >= x0 - m) & (ox <= x1 + m) & (oy >= y0 - m) & (oy <= y1 + m)
        if not near.any():
            return None
    ri = np.flatnonzero(near.any(axis=1))
    ci = np.flatnonzero(near.any(axis=0))
    r0 = max(int(rows[ri[0]]) - s, 0)
    r1 = min(int(rows[ri[-1]]) + s + 1, field.shape[0])
    c0 = max(int(cols[ci[0]]) - s, 0)
    c1 = min(int(cols[ci[-1]]) + s + 1, field.shape[1])
    shader = _kernels(patterns=True).shader_for(obj.reflectance)
    return _Plane(index, H, d, (r0, r1, c0, c1), np.where(near, lam, np.inf), obj, shader)


_COARSE: dict[int, tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]] = {}


def _coarse_rays(field: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """Rows, columns and rays of the window grid (every ``_WINDOW_PX``, and the last row and column)."""
    hit = _COARSE.get(id(field))
    if hit is not None and hit[0] is field:
        return hit[1], hit[2], hit[3]
    s = _WINDOW_PX
    rows, cols = np.arange(0, field.shape[0], s), np.arange(0, field.shape[1], s)
    rows = np.append(rows, field.shape[0] - 1) if rows[-1] != field.shape[0] - 1 else rows
    cols = np.append(cols, field.shape[1] - 1) if cols[-1] != field.shape[1] - 1 else cols
    c = np.ascontiguousarray(field[np.ix_(rows, cols)])
    if len(_COARSE) > 8:
        _COARSE.clear()
    _COARSE[id(field)] = (field, rows, cols, c)
    return rows, cols, c


def _footprint(ox: NDArray[np.float64], oy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per coarse sample, the largest object-frame distance (m) to a 4-neighbour (inf if undefined)."""
    foot = np.zeros(ox.shape)
    for axis in (0, 1):
        with np.errstate(invalid="ignore"):
            step = np.maximum(np.abs(np.diff(ox, axis=axis)), np.abs(np.diff(oy, axis=axis)))
        step[~np.isfinite(step)] = np.inf
        lo = [slice(None), slice(None)]
        hi = [slice(None), slice(None)]
        lo[axis] = slice(1, None)
        hi[axis] = slice(None, -1)
        np.maximum(foot[tuple(lo)], step, out=foot[tuple(lo)])
        np.maximum(foot[tuple(hi)], step, out=foot[tuple(hi)])
    return foot


def _planes(objects: Sequence[PlanarObject], field: NDArray[np.float64]) -> list[_Plane]:
    """The visible planes, nearest first (occluded reflectance is then never evaluated)."""
    memo: dict[bytes, _Coarse] = {}
    planes = [p for k, obj in enumerate(objects) if (p := _plane(k, obj, field, memo)) is not None]
    return sorted(planes, key=cmp_to_key(_nearer))


def _nearer(a: _Plane, b: _Plane) -> int:
    """-1 when ``a`` is mostly in front of ``b`` where both are seen (median on the coarse grid)."""
    both = np.isfinite(a.coarse_depth) & np.isfinite(b.coarse_depth)
    if not np.any(both):
        return a.index - b.index
    diff = float(np.median(a.coarse_depth[both] - b.coarse_depth[both]))
    return -1 if diff < 0 else 1 if diff > 0 else a.index - b.index


def _shade(p: _Plane, n: int, scratch: Scratch, value: NDArray[np.float64], depth: NDArray[np.float64],
           which: NDArray[np.int32]) -> None:
    """Evaluate ``p``'s reflectance at its ``n`` compacted hits and store the defined ones."""
    if n == 0:
        return
    ox, oy, lam, flat = scratch.ox[:n], scratch.oy[:n], scratch.lam[:n], scratch.flat[:n]
    if p.shader is not None:
        p.shader(n, ox, oy, lam, flat, p.index, value, depth, which)
        return
    refl = np.ascontiguousarray(p.obj.reflectance(ox, oy), dtype=np.float64).reshape(-1)
    if refl.size != n:
        raise RenderError(f"object {p.index}: its reflectance returned {refl.size} values for {n} points")
    _kernels().take_hits(n, refl, lam, flat, p.index, value, depth, which)


# -- rendering -------------------------------------------------------------------------------------
def render_scene(camera: CameraModel, objects: Sequence[PlanarObject], background: float = 0.45,
                 supersample: int = 8) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(H, W) mean reflectance over each pixel's area (box filter, in [0, 1]) and the depth
    (camera z, metres; +inf for background) of what the pixel's centre sees.

    The work is split into bands of rows (then into runs of edge pixels) shared by up to
    ``RENDER_THREADS`` threads; every pixel's result is independent of the split, so the image is
    the same for any thread count. Reflectance functions are called from those threads: they must
    be pure functions of their arguments.
    """
    k = _kernels()
    field = ray_field(camera)
    h, w = field.shape[:2]
    value = np.empty(h * w)
    depth = np.empty(h * w)
    which = np.empty(h * w, dtype=np.int32)
    planes = _planes(objects, field)
    # Bands of ~128k rays: scratch that stays in cache, allocated once per thread.
    band = max(_CHUNK_RAYS // w, 1)
    bands = [(ra, min(ra + band, h)) for ra in range(0, h, band)]

    def shade_band(rows: tuple[int, int]) -> None:
        ra, rb = rows
        value[ra * w : rb * w] = background
        depth[ra * w : rb * w] = np.inf
        which[ra * w : rb * w] = -1
        scratch = scratch_for(band * w)
        for p in planes:  # nearest first, so an occluded plane's hits are never shaded
            r0, r1, c0, c1 = p.window
            a, b = max(ra, r0), min(rb, r1)
            if a >= b:
                continue
            if p.shader is not None:
                p.shader.shade_pixels(field, a, b, c0, c1, p.H, p.d, p.index, value, depth, which)
            else:
                n = k.hit_pixels(field, a, b, c0, c1, p.H, p.d, p.index, depth, which, *scratch.hits)
                _shade(p, n, scratch, value, depth, which)

    parallel(shade_band, bands, RENDER_THREADS)
    value2, which2 = value.reshape(h, w), which.reshape(h, w)
    if supersample > 1 and planes:
        edges = parallel(lambda rows: k.edge_pixels(value2, which2, rows[0], rows[1]), bands, RENDER_THREADS)
        rows, cols, only = (np.concatenate([e[i] for e in edges]) for i in range(3))
        if rows.size:
            value2[rows, cols] = _supersample(field, rows, cols, only, planes, background, supersample)
    return value2, depth.reshape(h, w)


def render_reflectance(camera: CameraModel, objects: Sequence[PlanarObject], background: float = 0.45,
                       supersample: int = 8) -> NDArray[np.float64]:
    """(H, W) mean reflectance over each pixel's area (box filter), in [0, 1]."""
    return render_scene(camera, objects, background, supersample)[0]


_CHUNK_RAYS = 1 << 17
RENDER_THREADS = max(1, min(4, os.cpu_count() or 1))
"""Threads a frame is rendered on (the caller's and pool workers); set before the first frame."""

def _supersample(field: NDArray[np.float64], rows: NDArray[np.int64], cols: NDArray[np.int64],
                 only: NDArray[np.int64], planes: Sequence[_Plane], background: float,
                 n: int) -> NDArray[np.float64]:
    """Box-filtered reflectance of the given pixels from ``n x n`` sub-pixel rays each.

    A pixel whose 3x3 neighbourhood sees one object (``only``) is shaded against that object
    alone: another object inside the pixel would have shown at a neighbour's centre (the same
    sub-pixel limit as the choice of edge pixels itself). When that object has a compiled
    pattern, one compiled loop does the whole pixel; the others go through sub-ray buffers.
    """
    k = _kernels()
    n2 = n * n
    out = np.empty(rows.size)
    rest = np.ones(rows.size, dtype=bool)
    tasks: list[tuple[_Plane | None, NDArray[np.intp]]] = []
    for p in planes:
        if p.shader is not None and n2 <= 128:
            alone = np.flatnonzero(only == p.index)
            rest[alone] = False
            tasks += [(p, alone[i : i + _ALONE_PIXELS]) for i in range(0, alone.size, _ALONE_PIXELS)]
    others = np.flatnonzero(rest)
    chunk = max(_CHUNK_RAYS // n2, 1)
    tasks += [(None, others[i : i + chunk]) for i in range(0, others.size, chunk)]

    def run(task: tuple[_Plane | None, NDArray[np.intp]]) -> None:
        alone_in, sel = task
        r, c, o = rows[sel], cols[sel], only[sel]
        res = np.empty(sel.size)
        if alone_in is not None and alone_in.shader is not None:
            alone_in.shader.supersample_alone(field, r, c, n, alone_in.H, alone_in.d, background, res)
            out[sel] = res
            return
        m = sel.size * n2
        scratch = scratch_for(m)
        scratch.ensure_sub(m)
        v, dp, wh = scratch.sub_value[:m], scratch.sub_depth[:m], scratch.sub_which[:m]
        v.fill(background)
        dp.fill(np.inf)
        wh.fill(-1)
        for p in planes:
            r0, r1, c0, c1 = p.window
            hits = k.hit_subrays(field, r, c, o, n, r0, r1, c0, c1, p.H, p.d, p.index, dp, wh, *scratch.hits)
            _shade(p, hits, scratch, v, dp, wh)
        out[sel] = v.reshape(sel.size, n2).mean(axis=1)

    parallel(run, tasks, RENDER_THREADS)
    return out


_ALONE_PIXELS = 4096
"""Pixels per task of the fused supersampling of one compiled pattern."""


def render(camera: CameraModel, objects: Sequence[PlanarObject], imaging: Imaging | None = None,
           rng: np.random.Generator | None = None, supersample: int = 8) -> NDArray[np.uint8]:
    """Render planar objects seen by ``camera`` as an 8-bit grey image of ``camera.size``."""
    im = imaging if imaging is not None else Imaging()
    reflectance, depth = render_scene(camera, objects, im.background, supersample)
    return to_grey(reflectance, im, rng, depth)
