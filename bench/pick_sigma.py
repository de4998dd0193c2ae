"""Is a pick's position 1-sigma honest? Rendered scenes on the virtual cell, its true calibration.

Teaches the bracket once, then puts it down ``--scenes`` times at random places and turns (seeded), picks it
through the product's own path (``cellctl.pick.candidate.locate``: grab, search, ``candidate``), and compares
the pick's reference point with the scene's truth, per base axis, against the pick's ``uncertainty.sigma_mm``.
The calibration is the cell's truth (camera and hand-eye) stored with **no** uncertainty of its own (a
covariance of zeros, no robot noise), so ``sigma_mm`` is the match's own pixel 1-sigma at the local scale
alone, and the ratio judges it. Prints a markdown table (paste into ``bench/results/pick.md``).

    .venv/bin/python bench/pick_sigma.py [--scenes 24] [--seed 5]

Honest: RMS of (actual error / reported sigma) over x and y of every scene within 0.5-2.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SEED = 11


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    import yaml

    from calibration import geometry as g
    from cellctl.cell import Cell
    from cellctl.config import default_config_text, parse_config
    from cellctl.jobs import JobManager
    from cellctl.pick.candidate import locate
    from cellctl.pick.model import teach
    from cellctl.pick.recipe import Recipe, SearchSettings
    from cellctl.services import Services
    from cellctl.store import open_store
    from drivers.sim.world import world_for

    tmp = Path(tempfile.mkdtemp(prefix="pick-sigma-"))
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    data["cameras"]["cam0"]["settings"]["seed"] = SEED
    data["robots"]["robot0"]["settings"]["seed"] = SEED
    config = parse_config(data)
    svc = Services(config, Cell(config), open_store(config), JobManager())
    world = world_for(None, SEED)
    truth = world.truth()
    cam = svc.store.save_calibration("camera", "cam0", None, truth["camera"], {}, creator="bench", note="truth")
    he = {"setup": "eye-in-hand", "T_tool_cam": truth["T_tool_cam"], "T_base_target": np.eye(4).tolist(),
          "uncertainty": {"covariance": np.zeros((6, 6)).tolist()}, "pixel_sigma_px": 0.0,
          "robot_noise": {"sigma_mm": 0.0, "sigma_deg": 0.0}}
    h = svc.store.save_calibration("handeye", "cam0", "robot0", he, {}, creator="bench", note="truth")
    svc.store.activate(cam.id, "bench")
    svc.store.activate(h.id, "bench")
    try:
        part = world.scene.parts[0]
        x0, y0, a0 = part.x_mm, part.y_mm, part.angle_deg
        robot = svc.cell.robot("robot0").ensure_open()

        def pixel(x_mm: float, y_mm: float) -> tuple[float, float]:
            uv = world.camera_model.project(g.transform_points(g.invert(world.T_base_cam()),
                                                               [x_mm * 1e-3, y_mm * 1e-3, 0.0]))[0]
            return float(uv[0]), float(uv[1])

        u, v = pixel(x0, y0)
        frame = svc.cell.camera("cam0").ensure_open().grab(timeout_s=5.0)
        model = teach(frame.pixels, (u - 100, v - 100, 200, 200), mode="shape", name="bracket")
        recipe = Recipe(name="bracket", models=[model.to_dict()], plane_z_mm=0.0, grasp_z_mm=5.0,
                        approach_height_mm=40.0, search=SearchSettings(timeout_s=None, max_count=1))
        svc.store.save_recipe(1, "bracket", recipe.model_dump(mode="json"), "bench")
        rng = np.random.default_rng(args.seed)
        rows, ratios, before, poor = [], [], [], []
        for i in range(args.scenes):
            part.x_mm = x0 + rng.uniform(-25.0, 25.0)
            part.y_mm = y0 + rng.uniform(-25.0, 25.0)
            part.angle_deg = a0 + rng.uniform(-180.0, 180.0)
            located = locate(svc, 1, 1, recipe, "cam0", robot)
            if not located.candidates:
                rows.append(f"| {i} | not found | | | | |")
                continue
            c = located.candidates[0]
            err = [c.T_base_part[0, 3] * 1e3 - part.x_mm, c.T_base_part[1, 3] * 1e3 - part.y_mm]
            r = [err[k] / c.sigma_mm[k] for k in range(2)]
            ratios += r
            # before (issue 37): every non-rim match was given the calibration's pixel sigma (0.1 px by default)
            old = located.mapping.map(np.array([c.match.u_px, c.match.v_px]), 0.0, located.T_capture,
                                      pixel_sigma_px=0.1).sigma_mm
            before += [err[k] / old[k] for k in range(2)]
            poor += [c.match.score < 0.95] * 2
            rows.append(f"| {i} | {c.match.sigma_px:.4f} | {c.sigma_mm[0]:.4f} / {c.sigma_mm[1]:.4f} | "
                        f"{err[0]:+.4f} / {err[1]:+.4f} | {r[0]:+.2f} / {r[1]:+.2f} | {c.match.score:.3f} |")
        part.x_mm, part.y_mm, part.angle_deg = x0, y0, a0
    finally:
        svc.close()
    print("| scene | match sigma_px | reported sigma_mm x / y | actual error mm x / y | error / sigma x / y | score |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))
    def rms(x: list[float]) -> float:
        return math.sqrt(float(np.mean(np.square(x)))) if x else float("nan")

    sharp = [r for r, p in zip(ratios, poor, strict=True) if not p]
    soft = [r for r, p in zip(ratios, poor, strict=True) if p]
    sharp_b = [r for r, p in zip(before, poor, strict=True) if not p]
    soft_b = [r for r, p in zip(before, poor, strict=True) if p]
    print(f"\nfound {len(ratios) // 2} of {args.scenes}; RMS(actual error / reported sigma) over x and y: "
          f"**{rms(ratios):.2f}** (honest: 0.5-2); median |ratio| {float(np.median(np.abs(ratios))):.2f}; "
          f"scenes with score >= 0.95: {rms(sharp):.2f} ({len(sharp) // 2}), "
          f"< 0.95: {rms(soft):.2f} ({len(soft) // 2})")
    print(f"before (every non-rim match given the calibration's 0.1 px): RMS ratio {rms(before):.2f}; "
          f"score >= 0.95: {rms(sharp_b):.2f}, < 0.95: {rms(soft_b):.2f}")


if __name__ == "__main__":
    main()
