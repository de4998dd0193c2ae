"""``cellctl pick find`` shows the verification: each match's scores and 1-sigma, and the candidates
it rejected with why (a bracket beside a bracket that lacks one of its holes)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from tests.support import pick_scenes as synth
from tests.support.cli import run_cli

SIZE = (640, 480)


def test_find_answers_scores_and_rejected(tmp_path: Path) -> None:
    part = synth.part_bracket()
    st = synth.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=4)
    teach, roi = synth.teach_scene(part, np.random.default_rng(0), centre=(320.0, 240.0), style=st)
    cv2.imwrite(str(tmp_path / "teach.png"), teach)
    look_alike = synth.part_without_hole(part, 0)
    insts = [synth.Instance(part, 170.25, 150.5, 120.0), synth.Instance(look_alike, 450.6, 330.1, -35.0)]
    scene, truth = synth.render(insts, st, np.random.default_rng(1))
    cv2.imwrite(str(tmp_path / "scene.png"), scene)
    model = tmp_path / "bracket.json"
    r = run_cli("pick", "teach", "--image", str(tmp_path / "teach.png"), "--roi", ",".join(f"{x:g}" for x in roi),
                "--out", str(model))
    assert r.returncode == 0, r.stderr
    r = run_cli("pick", "find", "--model", str(model), str(tmp_path / "scene.png"))
    assert r.returncode == 0, r.stderr
    item = json.loads(r.stdout)[0]
    (m,) = item["matches"]
    assert math.hypot(m["u_px"] - truth[0].u_px, m["v_px"] - truth[0].v_px) < 0.2
    assert m["scores"]["edge"] == round(m["score"], 4) and m["scores"]["missing_features"] == 0
    assert 0 < m["sigma_angle_deg"] < 0.1 and 0 < m["sigma_px"] < 0.1
    (rej,) = item["rejected"]
    assert math.hypot(rej["u_px"] - truth[1].u_px, rej["v_px"] - truth[1].v_px) < 1.0
    assert rej["score"] >= 0.5 and "missing" in rej["reason"] and rej["scores"]["missing_features"] >= 1
    assert "reason" not in item  # a match was found
    # alone, the look-alike leaves the answer empty, and the reason says why
    only = tmp_path / "only.png"
    img, _ = synth.render([insts[1]], st, np.random.default_rng(2))
    cv2.imwrite(str(only), img)
    item = json.loads(run_cli("pick", "find", "--model", str(model), str(only)).stdout)[0]
    assert item["matches"] == [] and "verification" in item["reason"] and "missing" in item["reason"]
