"""``vision.shape.warm_up()`` loads every compiled kernel a search uses, with the signatures the
search calls it with: after it, a first search compiles nothing, so it costs what the next ones
cost and a recipe's 1 s ``timeout_s`` is not spent compiling (the service warms up at start).

Run in a fresh interpreter: in this one, earlier tests may already have compiled the kernels.
"""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import REPO

SCRIPT = r"""
import importlib, json, pkgutil
import numpy as np
from numba.core.registry import CPUDispatcher
import vision.shape as shape
from tests.support import pick_scenes as scenes
from vision.types import SearchParams

def compiled():
    out = {}
    for info in pkgutil.iter_modules(shape.__path__, "vision.shape."):
        mod = importlib.import_module(info.name)
        for name, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.__module__ == info.name:
                out[f"{info.name}.{name}"] = sorted(str(s) for s in obj.signatures)
    return out

shape.warm_up()
before = compiled()
part = scenes.part_bracket()
style = scenes.SceneStyle(size=(640, 480), noise_sigma=1.5, clutter=0)
img, roi = scenes.teach_scene(part, np.random.default_rng(1), centre=(320.0, 240.0), style=style)
model = shape.teach(img, roi)
scene, _ = scenes.render([scenes.Instance(part, 300.4, 250.7, 33.0)], style, np.random.default_rng(2))
for params in (SearchParams(), SearchParams(scale_min=0.9, scale_max=1.1), SearchParams(mirrored=True),
               SearchParams(polarity="use_polarity"), SearchParams(polarity="ignore_global_polarity")):
    shape.find(model, scene, params)
print(json.dumps({"before": before, "after": compiled()}))
"""


def test_a_first_search_after_warm_up_compiles_nothing() -> None:
    r = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    seen = json.loads(r.stdout.strip().splitlines()[-1])
    assert seen["after"], "no compiled kernels found in vision.shape"
    missing = {k: sorted(set(v) - set(seen["before"].get(k, []))) for k, v in seen["after"].items()}
    missing = {k: v for k, v in missing.items() if v}
    assert not missing, f"compiled during the first search, not by warm_up(): {missing}"
