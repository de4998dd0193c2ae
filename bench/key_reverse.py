"""Why the reverse-side key of the real-photo corpus is not found (issue 37): where its edges differ.

``tests/data/pick_real/opencv-generalizedhough-example``: ``image.png`` shows two keys, the upper one the
template's own, the lower one lying with its other face up (``cases.yaml`` marks it optional). If the lower
key were the template's key turned over, the mirrored model (``SearchParams(mirrored=True)``) would fit it
as well as the upper key. This script fits the mirrored and the unmirrored model to it (from the
search's own best candidate near the lower key at min_score 0.25, which is unmirrored, then for the
mirrored model the best score over +-16 px and the whole turn, and for both the best score over a grid
of +-4 px, +-4 deg around it: the corpus's estimate lies ~45 px down the blade from where every fit puts the
template centre) and prints the share of model points that find their edge (agreement > 0.5), per
part of the key: the bow (the round head with its hole; template rows >= 150) and the blade (rows < 150),
and the blade's two long edges (template columns left / right of the blade's middle line).
For comparison the upper key at its own estimate.

Run: ``.venv/bin/python bench/key_reverse.py`` (a few seconds; prints a Markdown table).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.pick_cases import load_cases, read_grey  # noqa: E402
from vision import shape  # noqa: E402
from vision.image import gradients  # noqa: E402
from vision.shape.model import ShapeModel  # noqa: E402
from vision.shape.score import direction_detail  # noqa: E402
from vision.types import SearchParams  # noqa: E402


def parts(model: ShapeModel, roi: tuple[float, float, float, float]) -> dict[str, np.ndarray]:
    """Masks of the level-0 model points by part of the key (template pixels)."""
    u, v, w, h = roi
    p = model.levels[0].points + np.array([u + w / 2.0, v + h / 2.0])
    blade = p[:, 1] < 150.0
    mid = float(np.median(p[blade, 0])) if blade.any() else 0.0
    return {"bow": ~blade, "blade": blade, "blade, left edge": blade & (p[:, 0] < mid),
            "blade, right edge": blade & (p[:, 0] >= mid), "all": np.ones(len(p), bool)}


def best_fit(model: ShapeModel, G: np.ndarray, x: float, y: float, a_deg: float, mirrored: bool,
             wide: bool = False) -> tuple[float, np.ndarray, tuple[float, float, float]]:
    """The best mean agreement over a grid around (x, y, a) (reference point = the template centre,
    which is the ROI centre here: +-4 px, +-4 deg; ``wide``: first +-16 px and the whole turn in 2-px,
    2-deg steps), and the per-point agreement there."""
    lv = model.levels[0].mirrored() if mirrored else model.levels[0]
    best: tuple[float, np.ndarray, tuple[float, float, float]] = (-1.0, np.zeros(0), (x, y, a_deg))
    grids = [(np.arange(-16.0, 16.01, 2.0), np.arange(-180.0, 180.0, 2.0))] if wide else []
    grids += [(np.arange(-4.0, 4.01, 1.0), np.arange(-4.0, 4.01, 0.5))]
    for offs, turns in grids:
        x0, y0, a00 = best[2]
        for da in turns:
            a = math.radians(a00 + da)
            R = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
            for dx in offs:
                for dy in offs:
                    q = lv.points @ R.T + np.array([x0 + dx, y0 + dy])
                    s, _, _, det = direction_detail(G, q, lv.normals @ R.T, np.ones(len(q), bool), 3.0,
                                                    "ignore_local_polarity", 0.5)
                    if s > best[0]:
                        best = (float(s), det.agree, (x0 + dx, y0 + dy, a00 + da))
    return best


def main() -> None:
    case = next(c for c in load_cases() if c.id == "generalized_hough_keys")
    model = shape.teach(case.teach_image(), case.roi)
    test = case.tests[0]
    img = read_grey(test.path)
    G = cv2.merge(list(gradients(img, model.params.edge_sigma_px)))
    masks = parts(model, case.roi)
    names = list(masks)
    print("| key, model | score | pose (x, y, deg) | " + " | ".join(f"{n} agree" for n in names) + " |")
    print("| --- " * (3 + len(names)) + "|")
    upper, lower = test.instances[0], test.instances[1]
    cands = shape.find(model, img, SearchParams(min_score=0.25, mirrored=True, min_surround=-1.0)).matches

    def start(x: float, y: float, mirrored: bool, a: float) -> tuple[float, float, float]:
        near = [m for m in cands if m.mirrored == mirrored and math.hypot(m.u_px - x, m.v_px - y) < 80]
        if not near:
            return x, y, a
        m = max(near, key=lambda m: m.score)
        return m.u_px, m.v_px, m.angle_deg

    rows = [("upper key, unmirrored model", start(upper.x, upper.y, False, 0.0), False),
            ("lower key, mirrored model", start(lower.x, lower.y, False, lower.angle_deg or 0.0), True),
            ("lower key, unmirrored model", start(lower.x, lower.y, False, lower.angle_deg or 0.0), False)]
    for name, (x0, y0, a0), mir in rows:
        s, agree, pose = best_fit(model, G, x0, y0, a0, mir, wide=mir)
        cells = [f"{float(np.mean(agree[m] > 0.5)):.2f} ({int(m.sum())})" for m in masks.values()]
        print(f"| {name} | {s:.2f} | ({pose[0]:.1f}, {pose[1]:.1f}, {pose[2]:.1f}) | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
