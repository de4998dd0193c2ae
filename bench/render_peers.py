"""Peers and context of the renderer benchmark (``bench/render.py``): the OpenCV texture warp,
this renderer as it was at earlier commits (loaded from git), and the machine's description."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import time
import types
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.targets import CircleGrid

ROOT = Path(__file__).resolve().parents[1]


def texture_from_reflectance(reflectance: object, extent_m: tuple[float, float, float, float], texel_m: float,
                             background: float) -> NDArray[np.float32]:
    """The target's reflectance sampled at texel centres (row j, column i: y, x)."""
    x0, y0, x1, y1 = extent_m
    nx, ny = int(np.ceil((x1 - x0) / texel_m)), int(np.ceil((y1 - y0) / texel_m))
    xs = x0 + (np.arange(nx) + 0.5) * texel_m
    tex = np.empty((ny, nx), dtype=np.float32)
    for j in range(ny):  # row by row: a few MB at a time
        y = np.full(nx, y0 + (j + 0.5) * texel_m)
        tex[j] = reflectance(xs, y)  # type: ignore[operator]
    return np.where(np.isfinite(tex), tex, np.float32(background))


def circle_grid_texture(grid: CircleGrid, texel_m: float) -> NDArray[np.float32]:
    """A circle grid drawn with OpenCV's anti-aliased circles (white paper, black disks)."""
    x0, y0, x1, y1 = grid.extent_m()
    nx, ny = int(np.ceil((x1 - x0) / texel_m)), int(np.ceil((y1 - y0) / texel_m))
    tex = np.full((ny, nx), 255, dtype=np.uint8)
    shift = 4
    r = grid.diameter_mm * 1e-3 / 2 / texel_m
    for cx, cy in grid.points().xyz_m[:, :2]:
        # Texel (i, j) has its centre at x0 + (i + 0.5) texel: centre in texel coordinates minus 0.5.
        c = (int(round(((cx - x0) / texel_m - 0.5) * 2**shift)), int(round(((cy - y0) / texel_m - 0.5) * 2**shift)))
        cv2.circle(tex, c, int(round(r * 2**shift)), 0, -1, cv2.LINE_AA, shift)
    return tex.astype(np.float32) / 255.0


class TexturePeer:
    """The OpenCV texture-warp renderer of one planar target (see the module docstring)."""

    def __init__(self, camera: CameraModel, texture: NDArray[np.float32], origin_m: tuple[float, float],
                 texel_m: float, background: float) -> None:
        self.camera = camera
        self.background = background
        self.texture = texture
        self.origin = origin_m
        self.texel = texel_m
        t = time.perf_counter()
        uu, vv = np.meshgrid(np.arange(camera.width, dtype=np.float32), np.arange(camera.height, dtype=np.float32))
        pts = np.stack([uu, vv], axis=-1).reshape(-1, 1, 2)
        ideal = cv2.undistortPoints(pts, camera.K, camera.dist, P=camera.K).reshape(camera.height, camera.width, 2)
        self.map_u = np.ascontiguousarray(ideal[..., 0])
        self.map_v = np.ascontiguousarray(ideal[..., 1])
        self.lens_inversion_s = time.perf_counter() - t

    def render(self, T_cam_obj: NDArray[np.float64]) -> NDArray[np.float32]:
        """Reflectance image (H, W) of the target at ``T_cam_obj``."""
        # Texel (i, j) centre -> object (x0 + (i + 0.5) s, y0 + (j + 0.5) s, 0) -> ideal pixel.
        s = self.texel
        S = np.array([[s, 0, self.origin[0] + 0.5 * s], [0, s, self.origin[1] + 0.5 * s], [0, 0, 1]])
        Hm = self.camera.K @ T_cam_obj[:3, [0, 1, 3]] @ S
        size = (self.camera.width, self.camera.height)
        ideal = cv2.warpPerspective(self.texture, Hm, size, flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=self.background)
        return cv2.remap(ideal, self.map_u, self.map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=self.background)


PREVIOUS = "7b520d0"
"""The commit whose renderer issue 15 replaced (loaded from git when the history is there)."""
SESSION_START = "bca30e5"
"""The renderer before this round of speed work (issue 15, item 1 of the second session)."""


MOVED_IMPORTS: tuple[tuple[str, str], ...] = (
    ("from calibration.sensor import", "from drivers.sim.imaging.sensor import"),
    ("from calibration import render_kernels", "from drivers.sim.imaging import kernels as render_kernels"),
)
"""Imports of the historic renderer rewritten to where those modules live now (same code)."""


def git_module(commit: str, path: str, name: str, tmp: Path) -> types.ModuleType | None:
    """``path`` as it was at ``commit``, imported as module ``name`` (None without the history).

    Written to ``tmp`` and imported from there, so that its numba loops compile (and cache) like
    any module's, apart from the current ones.
    """
    try:
        src = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    for was, now in MOVED_IMPORTS:  # the renderer has moved since (calibration/ -> drivers/sim/imaging/)
        src = src.replace(was, now)
    file = tmp / f"{name}.py"
    file.write_text(src)
    spec = importlib.util.spec_from_file_location(name, file)
    if spec is None or spec.loader is None:
        return None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # its dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def session_start_renderer(tmp: Path) -> tuple[types.ModuleType, types.ModuleType] | None:
    """(render, sensor) of ``SESSION_START``: its render module wired to its own kernels."""
    kernels = git_module(SESSION_START, "calibration/render_kernels.py", "start_render_kernels", tmp)
    render = git_module(SESSION_START, "calibration/render.py", "start_render", tmp)
    sensor = git_module(SESSION_START, "calibration/sensor.py", "start_sensor", tmp)
    if kernels is None or render is None or sensor is None:
        return None
    render._kernels = lambda: kernels  # type: ignore[attr-defined]
    return render, sensor


def autogroup() -> str:
    """Whether the kernel shares the CPU between sessions rather than threads (see the notes)."""
    try:
        return "on" if Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1" else "off"
    except OSError:
        return "unknown"


_FIRST_FRAME = """
import threading, time
t0 = time.perf_counter()
from drivers.camera.sim import SimCamera, SimCameraSettings
t1 = time.perf_counter()
cam = SimCamera("cam0", SimCameraSettings())
cam.open()
if PREPARED:
    for th in threading.enumerate():
        if th.name == "cam0-prepare":
            th.join()
t2 = time.perf_counter()
cam.grab()
t3 = time.perf_counter()
print(t1 - t0, t2 - t1, t3 - t2)
"""


def first_frame(prepared: bool, runs: int = 3) -> tuple[float, float, float]:
    """(imports, open [+ its background preparation], first grab) in ms, fresh processes, medians.

    Not prepared: the grab right after ``open()``, which waits for the one-off work (lens
    inversion, numba start-up). Prepared: the grab once open's background preparation is done.
    """
    rows = []
    for _ in range(runs):
        code = f"PREPARED = {prepared}\n" + _FIRST_FRAME
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split()
        rows.append([float(x) for x in out])
    m = np.median(np.array(rows), axis=0) * 1000
    return float(m[0]), float(m[1]), float(m[2])
