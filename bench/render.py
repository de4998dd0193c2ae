"""Renderer benchmark (issue 15): frame time of the virtual camera against an OpenCV texture warp.

Ours: ``drivers.sim.imaging.renderer`` (exact inverse mapping through the lens model, edges supersampled)
and the virtual cell's ``SimWorld.render`` (every frame from a new pose, so nothing is cached).
Peers, in the same run on the same poses:
- the usual OpenCV way to render a plane — the target rasterised once into a texture (0.05 mm per
  texel; 0.1 mm, drawn by ``cv2.circle``, for the geometry test), per frame ``cv2.warpPerspective``
  into the ideal pinhole image and ``cv2.remap`` through the lens (maps from ``cv2.undistortPoints``
  of every pixel, computed once) — followed by the same grey-level stage (``drivers.sim.imaging.to_grey``);
  both render the built-in cell's circle plate at 1280x960 through its camera;
- this renderer as it was at the start of this work (git ``SESSION_START``: render, kernels and
  sensor modules loaded from the history) and before issue 15 (git ``PREVIOUS``), on the whole cell.

Geometry: 63 small disks on a plane facing the camera (as ``tests/drivers/test_imaging_render.py``):
the error of each disk's centroid against the projected centre, for ours and for the texture warp.

    .venv/bin/python bench/render.py [--frames N] [--out bench/results/render.md]

Prints the markdown tables and writes them to ``--out``. Wall-clock and process CPU medians
(``time.process_time``: all threads of the process), ours and the peers' interleaved pose by pose
so that all see the same machine load; the load average and the CPU are stated with them.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import cpu_model  # noqa: E402
from bench.render_peers import (  # noqa: E402
    PREVIOUS,
    SESSION_START,
    TexturePeer,
    autogroup,
    circle_grid_texture,
    first_frame,
    git_module,
    session_start_renderer,
    texture_from_reflectance,
)
from calibration import geometry as g  # noqa: E402
from calibration.camera_model import CameraModel  # noqa: E402
from calibration.targets import CircleGrid  # noqa: E402
from drivers.sim.imaging import Imaging, PlanarObject, ray_field, render_scene, to_grey  # noqa: E402  # noqa: E402
from drivers.sim.imaging import renderer as render  # noqa: E402
from drivers.sim.scene import BUILTIN_SCENE, load_scene  # noqa: E402
from drivers.sim.world import SimWorld  # noqa: E402

TEXEL_M = 0.05e-3
GRID_TEXEL_M = 0.1e-3
TARGET_MS = 150.0
DEFECTS_SCENE = BUILTIN_SCENE.with_name("virtual-cell-real-defects.yaml")


def poses(world: SimWorld, n: int) -> list[NDArray[np.float64]]:
    """``n`` tool poses around home (a few cm and degrees apart), seeded."""
    rng = np.random.default_rng(15)
    home = g.ur_pose_to_transform(world.scene.robot.home)
    out = []
    for _ in range(n):
        R = g.rotvec_to_matrix(rng.normal(0, np.radians(4), 3))
        T = home @ g.make_transform(R, rng.normal(0, 0.02, 3))
        out.append(T)
    return out


def median_ms(ts: list[float]) -> float:
    return float(np.median(ts) * 1000)


class Timer:
    """Wall-clock and process CPU time of each call (the CPU figure is less hurt by other load)."""

    def __init__(self) -> None:
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def __call__(self, fn: Callable[..., object]) -> None:
        t, c = time.perf_counter(), time.process_time()
        fn()
        self.wall.append(time.perf_counter() - t)
        self.cpu.append(time.process_time() - c)

    def stats(self) -> tuple[float, float, float]:
        """(median wall, min wall, median CPU) in ms."""
        return median_ms(self.wall), min(self.wall) * 1000, median_ms(self.cpu)


def bench_frames(n: int, tmp: Path) -> tuple[dict[str, tuple[float, float, float]], tuple[int, int, float]]:
    """Per frame kind (wall median, wall min, CPU median) in ms, and (poses whose reflectance equals
    the session-start renderer's bit for bit, poses compared, largest depth difference in m)."""
    scene = load_scene()
    world = SimWorld(scene)
    im = scene.camera.imaging
    imaging = Imaging(**im.model_dump(exclude={"supersample"}))
    plate_spec = scene.targets[0]
    plate = plate_spec.parsed()
    cam = world.camera_model
    x0, y0 = plate.extent_m()[:2]
    texture = texture_from_reflectance(plate.reflectance, plate.extent_m(), TEXEL_M, im.background)
    peer = TexturePeer(cam, texture, (x0, y0), TEXEL_M, im.background)
    world.render()  # the lens inversion and the compiled loops, once
    defects = SimWorld(load_scene(DEFECTS_SCENE))
    defects.render()
    rng = np.random.default_rng(1)
    names = ("ours_plate", "peer_plate", "cell", "cell_1thread", "grey_only", "cell_defects", "grey_defects",
             "start", "start_plate", "start_defects", "previous")
    timers = {k: Timer() for k in names}
    old = git_module(PREVIOUS, "calibration/render.py", "previous_render", tmp)
    start = session_start_renderer(tmp)
    if start is not None:  # compile its loops outside the timed frames
        start[1].to_grey(start[0].render_scene(cam, world.planar_objects(), im.background, im.supersample)[0],
                         start[1].Imaging(**imaging.__dict__), rng)
    threads = render.RENDER_THREADS
    if start is not None:
        s_render, s_sensor = start
        s_imaging = s_sensor.Imaging(**imaging.__dict__)
        dim = defects.scene.camera.imaging
        s_dimaging = s_sensor.Imaging(**dim.model_dump(exclude={"supersample"}))
    frames: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    identical = compared = 0
    depth_diff = 0.0
    for T in poses(world, n):
        world.place_tool(T)
        defects.place_tool(T)
        T_cam_plate = g.invert(world.T_base_cam()) @ world.T_base_target(plate_spec.name)
        objs = world.planar_objects()

        def ours(T_cam_plate: NDArray[np.float64] = T_cam_plate) -> None:
            refl, depth = render_scene(cam, [PlanarObject(T_cam_plate, plate.reflectance)], im.background,
                                       im.supersample)
            to_grey(refl, imaging, rng, depth)

        def theirs(T_cam_plate: NDArray[np.float64] = T_cam_plate) -> None:
            to_grey(peer.render(T_cam_plate).astype(np.float64), imaging, rng)

        def one_thread(objs: list[PlanarObject] = objs) -> None:
            render.RENDER_THREADS = 1
            try:
                refl, depth = render_scene(cam, objs, im.background, im.supersample)
                to_grey(refl, imaging, rng, depth)
                frames["ours"] = (refl, depth)
            finally:
                render.RENDER_THREADS = threads

        # The start renderer's frames (timed only when its modules loaded).
        def at_start(objs: list[PlanarObject] = objs) -> None:
            refl, depth = s_render.render_scene(cam, objs, im.background, im.supersample)
            s_sensor.to_grey(refl, s_imaging, rng, depth)
            frames["start"] = (refl, depth)

        def start_plate(T_cam_plate: NDArray[np.float64] = T_cam_plate) -> None:
            refl, depth = s_render.render_scene(cam, [PlanarObject(T_cam_plate, plate.reflectance)],
                                                im.background, im.supersample)
            s_sensor.to_grey(refl, s_imaging, rng, depth)

        def start_defects() -> None:  # the objects built inside, as SimWorld.render does
            refl, depth = s_render.render_scene(defects.camera_model, defects.planar_objects(), dim.background,
                                                dim.supersample)
            s_sensor.to_grey(refl, s_dimaging, rng, depth)

        # Each of ours next to the start renderer's same frame, the pair's order alternating pose by
        # pose, so that neither always runs on caches the step before it has just flushed.
        flip = len(timers["cell"].wall) % 2 == 1
        with_start = start is not None
        def group(*items: tuple[str, Callable[..., object]] | None) -> list[tuple[str, Callable[..., object]]]:
            return [item for item in items if item is not None]

        steps = [
            group(("ours_plate", ours), ("start_plate", start_plate) if with_start else None),
            group(("peer_plate", theirs)),
            group(("cell", world.render), ("start", at_start) if with_start else None),
            group(("grey_only", world.render)),  # same pose: the geometry is cached, only the imaging runs
            group(("cell_1thread", one_thread)),
            group(("cell_defects", defects.render), ("start_defects", start_defects) if with_start else None),
            group(("grey_defects", defects.render)),
        ]
        for pair in steps:
            for name, fn in pair[::-1] if flip else pair:
                timers[name](fn)
        if start is not None:
            compared += 1
            identical += np.array_equal(frames["ours"][0], frames["start"][0])
            finite = np.isfinite(frames["start"][1])
            same_seen = np.array_equal(finite, np.isfinite(frames["ours"][1]))
            depth_diff = max(depth_diff, float(np.max(np.abs(frames["ours"][1][finite] - frames["start"][1][finite])))
                             if same_seen else np.inf)
        if old is not None:
            old_imaging = old.Imaging(im.black_level, im.white_level, im.background, im.blur_sigma_px,
                                      im.noise_sigma, im.light_gradient)

            def previous(objs: list[PlanarObject] = objs, old_imaging: object = old_imaging) -> None:
                old.to_grey(old.render_reflectance(cam, objs, im.background, im.supersample), old_imaging, rng)

            timers["previous"](previous)
    out = {k: t.stats() for k, t in timers.items() if t.wall}
    out["peer_lens"] = (peer.lens_inversion_s * 1000,) * 3
    out["cell_max"] = (max(timers["cell"].wall) * 1000,) * 3
    return out, (identical, compared, depth_diff)


def new_camera_frame(runs: int = 5) -> tuple[float, float, float]:
    """(lens inversion, whole first frame) wall ms and the frame's CPU ms of a camera new to a
    running process (its compiled loops already loaded), medians: each run a lens never seen."""
    scene = load_scene()
    world = SimWorld(scene)
    world.render()
    base = scene.camera.camera_model()
    field, frame, cpu = [], [], []
    for i in range(runs):
        cam = CameraModel(base.model, base.width, base.height, base.K, base.dist * (1.0 + 0.01 * (i + 1)))
        t, c = time.perf_counter(), time.process_time()
        ray_field(cam)
        t_field = time.perf_counter() - t
        refl, depth = render_scene(cam, world.planar_objects(), scene.camera.imaging.background,
                                   scene.camera.imaging.supersample)
        to_grey(refl, Imaging(**scene.camera.imaging.model_dump(exclude={"supersample"})),
                np.random.default_rng(i), depth)
        field.append(t_field)
        frame.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return median_ms(field), median_ms(frame), median_ms(cpu)


def geometry_errors() -> dict[str, tuple[float, float]]:
    """Max and RMS centroid error (px) of 63 disks facing the camera, ours and the peer's."""
    K = np.array([[1400.0, 0.0, 640.0], [0.0, 1400.0, 480.0], [0.0, 0.0, 1.0]])
    cam = CameraModel("opencv5", 1280, 960, K, np.array([-0.2, 0.1, 0.001, -0.0005, 0.0]))
    grid = CircleGrid(9, 7, 40.0, 5.0)
    T = g.make_transform(g.rotvec_to_matrix([0.0, 0.0, 0.1]), [-0.17, -0.12, 0.5])
    ours = render_scene(cam, [PlanarObject(T, grid.reflectance)], background=1.0, supersample=8)[0]
    x0, y0 = grid.extent_m()[:2]
    peer_r = TexturePeer(cam, circle_grid_texture(grid, GRID_TEXEL_M), (x0, y0), GRID_TEXEL_M, 1.0)
    peer = peer_r.render(T).astype(np.float64)
    truth = cam.project(g.transform_points(T, grid.points().xyz_m))
    out = {}
    for name, refl in (("ours", ours), ("peer", peer)):
        errors = []
        for u, v in truth:
            u0, v0, h = int(round(u)), int(round(v)), 14
            w = 1.0 - refl[v0 - h : v0 + h + 1, u0 - h : u0 + h + 1]
            vv, uu = np.mgrid[v0 - h : v0 + h + 1, u0 - h : u0 + h + 1]
            errors.append([(w * uu).sum() / w.sum() - u, (w * vv).sum() / w.sum() - v])
        err = np.linalg.norm(errors, axis=1)
        out[name] = (float(err.max()), float(np.sqrt(np.mean(err**2))))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=15, help="poses to render (default 15)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "render.md")
    args = ap.parse_args()
    t_run = time.perf_counter()
    load0 = os.getloadavg()[0]
    imp_ms, _, first_ms = first_frame(prepared=False)
    _, prep_ms, first_prepared_ms = first_frame(prepared=True)
    with tempfile.TemporaryDirectory() as tmp:
        f, same = bench_frames(args.frames, Path(tmp))
    geo = geometry_errors()
    field_ms, new_cam_ms, new_cam_cpu = new_camera_frame()
    load1 = os.getloadavg()[0]
    cell, cell_min, cell_cpu = f["cell"]
    peer, peer_min, peer_cpu = f["peer_plate"]

    def verdict(ok: bool) -> str:
        return "met" if ok else "**missed**"

    def row(label: str, key: str, with_peer: bool = False, start_key: str | None = None) -> str:
        w, mn, c = f[key]
        vs_start = (f"{w / f[start_key][0]:.2f} / {c / f[start_key][2]:.2f}" if start_key is not None
                    and start_key in f else "-")
        if with_peer:
            return (f"| {label} | {w:.0f} ({mn:.0f}) | {c:.0f} | {peer:.0f} ({peer_min:.0f}) | {peer_cpu:.0f} | "
                    f"{w / peer:.2f} / {c / peer_cpu:.2f} | {vs_start} |")
        return f"| {label} | {w:.0f} ({mn:.0f}) | {c:.0f} | - | - | {w / peer:.2f} / {c / peer_cpu:.2f} | {vs_start} |"

    start_txt = (f"; {cell / f['start'][0]:.2f}x wall / {cell_cpu / f['start'][2]:.2f}x CPU of the renderer at "
                 f"git {SESSION_START} ({f['start'][0]:.0f} ms, {f['start'][2]:.0f} ms CPU)" if "start" in f else "")
    one_w, _, one_c = f["cell_1thread"]
    lines = [
        f"## Renderer benchmark (bench/render.py, {args.frames} poses)",
        "",
        f"The built-in virtual cell's camera (1280x960, opencv5, f 1400 px), each frame from a new pose around "
        f"home. Machine: {cpu_model()}, {os.cpu_count()} logical CPUs, shared (load average {load0:.1f} at the "
        f"start, {load1:.1f} at the end; scheduler autogroup {autogroup()}); OpenCV {cv2.__version__}, numba "
        f"{importlib.metadata.version('numba')}; the renderer on {render.RENDER_THREADS} threads. Peers in the same "
        f"run, interleaved pose by pose: OpenCV texture warp (texture 0.05 mm/texel, `cv2.warpPerspective` + "
        f"`cv2.remap` through the lens, the same grey-level stage after it), and this renderer at git "
        f"{SESSION_START} (before this work) and {PREVIOUS} (before issue 15). Whole run "
        f"{time.perf_counter() - t_run:.0f} s.",
        "",
        "### Against the targets (issue 15)",
        "",
        "| target | measured | verdict |",
        "| --- | --- | --- |",
        f"| a 1280x960 frame of the virtual cell <= {TARGET_MS:.0f} ms (wall clock) | {cell:.0f} ms median "
        f"(fastest {cell_min:.0f}, slowest {f['cell_max'][0]:.0f}; {cell_cpu:.0f} ms CPU); {cell / peer:.2f}x the "
        f"OpenCV peer's one-plane frame{start_txt} | {verdict(cell <= TARGET_MS)} |",
        f"| the first frame of a camera new to a running process <= {TARGET_MS:.0f} ms | {new_cam_ms:.0f} ms "
        f"({new_cam_cpu:.0f} ms CPU; its lens inversion {field_ms:.0f} ms of it) | "
        f"{verdict(new_cam_ms <= TARGET_MS)} |",
        f"| the first frame after start <= {TARGET_MS:.0f} ms: grab right after open, fresh process | "
        f"{first_ms:.0f} ms (numba's start-up, the lens inversion and a frame; imports {imp_ms:.0f} ms before "
        f"it) | {verdict(first_ms <= TARGET_MS)} |",
        f"| the first frame after start <= {TARGET_MS:.0f} ms: grab once open's background preparation is done "
        f"| {first_prepared_ms:.0f} ms (the preparation: {prep_ms:.0f} ms after open) | "
        f"{verdict(first_prepared_ms <= TARGET_MS)} |",
        f"| geometric exactness kept (disk centroids, test_imaging_render.py: max < 0.02 px) | ours max "
        f"{geo['ours'][0]:.4f} px, RMS {geo['ours'][1]:.4f} px | {verdict(geo['ours'][0] < 0.02)} |",
        f"| frames bit-identical to the renderer at git {SESSION_START} (reflectance, every pose) | "
        f"{same[0]} of {same[1]} poses identical; depth within {same[2]:.1e} m (the ray field's last bits) | "
        f"{verdict(same[0] == same[1] and same[1] > 0)} |",
        "",
        "### Frame time",
        "",
        "Wall-clock median (fastest) and process CPU median per frame, ms; ratios (wall / CPU) to the OpenCV "
        f"peer's one-plane frame and to the renderer at git {SESSION_START} rendering the same frame (plate, "
        "cell, defects cell).",
        "",
        "| frame | ours wall | ours CPU | peer wall | peer CPU | ours / peer | ours / start |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        row("circle plate on background, scene imaging (blur, noise, light gradient)", "ours_plate", True,
            "start_plate"),
        row(f"virtual cell (table, two parts, plate), `SimWorld.render`, new pose, {render.RENDER_THREADS} "
            "threads", "cell", start_key="start"),
        row("the same frames on 1 thread", "cell_1thread", start_key="start"),
        row("virtual cell with real defects (virtual-cell-real-defects.yaml), new pose", "cell_defects",
            start_key="start_defects"),
        *([row(f"renderer at git {SESSION_START}, the same virtual cell frame", "start", start_key="start")]
          if "start" in f else []),
        *([row(f"renderer at git {PREVIOUS} (before issue 15), the same frame", "previous")] if "previous" in f
          else []),
        row("imaging stage only, scene defaults (same pose, geometry cached)", "grey_only"),
        row("imaging stage only, all defects on", "grey_defects"),
        f"| first frame in a fresh process (grab right after open) | {first_ms:.0f} | - | "
        f"{f['peer_lens'][0] + peer:.0f} (undistortPoints of every pixel + a frame) | - | "
        f"{first_ms / (f['peer_lens'][0] + peer):.2f} / - | - |",
        "",
        "### Geometry (63 disks, 5 mm at 0.5 m, facing the camera; centroid vs projected centre)",
        "",
        "| renderer | max error (px) | RMS error (px) |",
        "| --- | --- | --- |",
        f"| ours (supersample 8) | {geo['ours'][0]:.4f} | {geo['ours'][1]:.4f} |",
        f"| peer: texture 0.1 mm/texel (cv2.circle anti-aliased), warpPerspective + remap (bilinear) | "
        f"{geo['peer'][0]:.4f} | {geo['peer'][1]:.4f} |",
        "",
        "Notes:",
        "- Where the wall time goes beyond the CPU time: waiting for a core. With scheduler autogroup on, the "
        "kernel shares the cores between sessions, not threads. In this run the process got "
        f"{100 * one_c / max(one_w, 1e-9):.0f} % of a core on 1 thread ({one_c:.0f} ms CPU in {one_w:.0f} ms) and "
        f"{100 * cell_cpu / max(cell, 1e-9):.0f} % on {render.RENDER_THREADS} threads ({cell_cpu:.0f} ms CPU in "
        f"{cell:.0f} ms): a second thread raises the share only while a core is free (on the loaded machine, "
        "load ~7-12, it did not; the 1-minute load average lags what the run saw). The threads take bands of rows, "
        "then runs of edge pixels; the image is the same for any thread count.",
        "- What the frame costs now, by pass: the targets' patterns (circle plate, chessboard, circle grid) are "
        "shaded in compiled loops bit-identical to their numpy `reflectance` (`drivers/sim/imaging/patterns.py`), "
        "and an edge pixel that sees one such pattern is supersampled in one fused loop (vectorised for the circle "
        "plate); the ray field's spline is evaluated through its local basis; the imaging stage's per-pixel "
        "arithmetic is compiled passes around OpenCV's blur, pow and JPEG. The virtual cell's parts and table are "
        "numpy functions of `drivers/sim/world.py`: their polygon tests are now the largest numpy cost of a frame, "
        "and compiling them (as for the targets) is the next step.",
        "- The peer renders one plane with bilinear texture sampling (no area integration: edges alias, and "
        "the texture's own sampling moves them); ours intersects each pixel's ray with every plane, "
        "integrates edge pixels over their area (6x6 in the scene, 8x8 in the geometry test) and handles "
        "occlusion between planes. A peer frame of the whole cell would need one warp per plane and compositing.",
        "- The first frame: the lens inversion (a quintic spline through an exact inversion on a 16 px grid) is "
        "per camera; numba's start-up (its import and loading the compiled loops from the disk cache) is per "
        "process and no per-frame work removes it. The simulated camera starts both in the background when it "
        "opens, so a grab after that pays a normal frame.",
        "- A missed target is missed as measured in this run, under this load; the CPU column says what the "
        "renderer itself costs, the ratios to the peers (same run, same poses) are the comparable figures.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)


if __name__ == "__main__":
    main()
