"""``cellctl pick teach`` / ``cellctl pick find`` through the real console script, and bad input."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from cellctl.pick.model import FORMAT_VERSION
from tests.support import pick_scenes as synth
from tests.support.cli import run_cli, run_process

SIZE = (640, 480)


run = run_cli  # the same main() in-process; run_process: the console script, once


@dataclass
class Files:
    dir: Path
    roi: str
    truth: list[synth.Truth]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Files:
    d = tmp_path_factory.mktemp("pick")
    part = synth.part_bracket()
    st = synth.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=6)
    teach, roi = synth.teach_scene(part, np.random.default_rng(0), centre=(320.0, 240.0), style=st)
    cv2.imwrite(str(d / "teach.png"), teach)
    insts = [synth.Instance(part, 170.25, 150.5, 120.0), synth.Instance(part, 470.6, 330.1, -35.0)]
    scene, truth = synth.render(insts, st, np.random.default_rng(1))
    cv2.imwrite(str(d / "scene.png"), scene)
    (d / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    return Files(d, ",".join(f"{x:g}" for x in roi), truth)


def test_teach_then_find(files: Files) -> None:
    d = files.dir
    model = d / "bracket.json"
    r = run_process("pick", "teach", "--image", str(d / "teach.png"), "--roi", files.roi, "--out", str(model))
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["mode"] == "shape" and summary["reference_px"] == [320.0, 240.0]
    assert json.loads(model.read_text())["format_version"] == FORMAT_VERSION

    out = d / "found.json"
    r = run("pick", "find", "--model", str(model), str(d / "scene.png"), "--max", "5", "--out", str(out))
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert json.loads(out.read_text()) == res
    assert res[0]["image"] == str(d / "scene.png")
    ms = res[0]["matches"]
    assert len(ms) == 2
    for t in files.truth:
        m = min(ms, key=lambda m: math.hypot(m["u_px"] - t.u_px, m["v_px"] - t.v_px))
        assert set(m) >= {"u_px", "v_px", "angle_deg", "score"}
        assert math.hypot(m["u_px"] - t.u_px, m["v_px"] - t.v_px) < 0.1
        assert abs(synth.wrap_deg(m["angle_deg"] - t.angle_deg)) < 0.1
        assert -180.0 < m["angle_deg"] <= 180.0

    r = run("pick", "find", "--model", str(model), str(d / "scene.png"), "--max", "1", "--min-score", "0.9")
    assert r.returncode == 0 and len(json.loads(r.stdout)[0]["matches"]) == 1


def test_blob_mode_and_two_models(files: Files) -> None:
    d = files.dir
    r = run("pick", "teach", "--image", str(d / "teach.png"), "--roi", files.roi, "--mode", "blob",
            "--out", str(d / "blob.json"))
    assert r.returncode == 0, r.stderr
    r = run("pick", "find", "--model", str(d / "blob.json"), str(d / "scene.png"))
    assert r.returncode == 0, r.stderr
    assert len(json.loads(r.stdout)[0]["matches"]) == 2
    # two models: recognition answers name the part
    run("pick", "teach", "--image", str(d / "teach.png"), "--roi", files.roi, "--out",
        str(d / "bracket.json"))
    r = run("pick", "find", "--model", str(d / "bracket.json"), "--model", str(d / "blob.json"),
            str(d / "scene.png"))
    assert r.returncode == 0, r.stderr
    for m in json.loads(r.stdout)[0]["matches"]:
        assert m["part"] in ("bracket", "blob") and "margin" in m


@pytest.mark.parametrize("roi, words", [
    ("600,100,100,100", "outside"),
    ("-5,10,100,100", "outside"),
    ("100,100,0,50", "empty"),
    ("100,100,50", "U,V,W,H"),
    ("a,b,c,d", "U,V,W,H"),
])
def test_bad_roi(files: Files, roi: str, words: str) -> None:
    d = files.dir
    r = run("pick", "teach", "--image", str(d / "teach.png"), f"--roi={roi}", "--out", str(d / "x.json"))
    assert r.returncode != 0
    assert words in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) <= 3


def test_newer_model_version(files: Files) -> None:
    d = files.dir
    run("pick", "teach", "--image", str(d / "teach.png"), "--roi", files.roi, "--out",
        str(d / "m.json"))
    data = json.loads((d / "m.json").read_text())
    data["format_version"] = FORMAT_VERSION + 1
    (d / "future.json").write_text(json.dumps(data))
    r = run("pick", "find", "--model", str(d / "future.json"), str(d / "scene.png"))
    assert r.returncode == 2
    assert "newer than this cellctl reads" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("name, words", [("broken.png", "cannot read image"), ("missing.png", "does not exist")])
def test_bad_images(files: Files, name: str, words: str) -> None:
    d = files.dir
    r = run("pick", "teach", "--image", str(d / name), "--roi", "10,10,50,50", "--out", str(d / "y.json"))
    assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr
    run("pick", "teach", "--image", str(d / "teach.png"), "--roi", "200,160,240,160", "--out",
        str(d / "z.json"))
    r = run("pick", "find", "--model", str(d / "z.json"), str(d / name))
    assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr


def test_corrupt_model_file(files: Files) -> None:
    d = files.dir
    (d / "corrupt.json").write_text('{"format_version": 1, "mode": "shape", "teach": {"roi": [1, 2]}}')
    r = run("pick", "find", "--model", str(d / "corrupt.json"), str(d / "scene.png"))
    assert r.returncode == 2 and "corrupt" in r.stderr and "Traceback" not in r.stderr


def test_strict_size_refuses_other_image_sizes(files: Files) -> None:
    d = files.dir
    run("pick", "teach", "--image", str(d / "teach.png"), "--roi", files.roi, "--out", str(d / "s.json"))
    full = cv2.imread(str(d / "scene.png"), cv2.IMREAD_GRAYSCALE)
    assert full is not None
    cv2.imwrite(str(d / "small.png"), full[:400, :600])
    r = run("pick", "find", "--strict-size", "--model", str(d / "s.json"), str(d / "small.png"))
    assert r.returncode == 2 and "600x400" in r.stderr and "640x480" in r.stderr
    assert "Traceback" not in r.stderr


def test_a_half_of_the_part_is_refused_unless_min_surround_allows_it(tmp_path: Path) -> None:
    """The rejection names `min_surround`; the CLI's `--min-surround` is that setting."""
    teach, roi = synth.teach_scene(synth.part_bracket(), np.random.default_rng(1))
    cv2.imwrite(str(tmp_path / "teach.png"), teach)
    model = tmp_path / "bracket.json"
    r = run("pick", "teach", "--image", str(tmp_path / "teach.png"), "--roi", ",".join(f"{x:g}" for x in roi),
            "--out", str(model))
    assert r.returncode == 0, r.stderr
    half = synth.distractor_scene(synth.part_half(synth.part_bracket(), 180.0), np.random.default_rng(100))
    cv2.imwrite(str(tmp_path / "halves.png"), half)
    found = {}
    for surround in ("0.2", "-1"):
        r = run("pick", "find", "--model", str(model), str(tmp_path / "halves.png"), "--min-surround", surround)
        assert r.returncode == 0, r.stderr
        found[surround] = json.loads(r.stdout)[0]["matches"]
    assert found["0.2"] == [] and found["-1"], found
    r = run("pick", "find", "--model", str(model), str(tmp_path / "halves.png"), "--min-surround", "2")
    assert r.returncode != 0 and "min_surround 2 must be -1..1" in r.stderr and "Traceback" not in r.stderr


def test_teach_from_several_images(files: Files) -> None:
    """Two --image/--roi pairs make one model (the edges seen in both); a missing ROI is named."""
    d = files.dir
    r = run("pick", "teach", "--image", str(d / "teach.png"), "--roi", files.roi, "--image", str(d / "teach.png"),
            "--roi", files.roi, "--out", str(d / "two.json"))
    assert r.returncode == 0, r.stderr
    out = run("pick", "find", "--model", str(d / "two.json"), str(d / "scene.png"))
    assert out.returncode == 0, out.stderr
    found = json.loads(out.stdout)
    assert len(found[0]["matches"]) == 2
    r = run("pick", "teach", "--image", str(d / "teach.png"), "--image", str(d / "scene.png"), "--roi", files.roi,
            "--out", str(d / "bad.json"))
    assert r.returncode != 0 and "one --roi per --image" in r.stderr and "Traceback" not in r.stderr
