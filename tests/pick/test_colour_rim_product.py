"""Colour models and the rim fit through the product: ``cellctl pick teach --colour/--refine``, the model file,
the pick flow (``run_pick``) on a colour camera, and the refusals (a bad colour mode, a part that is not round).

The screw photos (tests/data/pick_real/tf-visual-inspection-screws, Apache-2.0) are colour JPEGs: four Robertson
screw heads in wood, taught from the teach image's four heads; their rim reference is the corpus's
``measured_estimate`` (a circle through the colour edges, bench/screw_rim.py)."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cellctl.config import default_config_text
from cellctl.mapping import active_mapping
from cellctl.pick.flow import Recipe, SearchSettings, run_pick
from cellctl.pick.model import PartModel
from cellctl.services import Services
from drivers.base import Frame
from drivers.recording import RecordingWriter
from tests.support.cli import run_cli
from tests.support.truth import calibrated_services
from vision import shape

SCREWS = Path(__file__).resolve().parents[1] / "data" / "pick_real" / "tf-visual-inspection-screws" / "train_val_set"
TEACH = SCREWS / "11_1111.jpg"
ROIS = ["66,194,114,114", "374,172,114,114", "91,544,114,114", "408,516,114,114"]
SCENE = SCREWS / "44_1110.jpg"
HEADS = [(126.09, 230.82), (436.92, 230.31), (127.34, 586.3)]
"""44_1110.jpg's heads, the corpus's rim reference (cases.yaml, measured_estimate)."""
HASH_PART = Path(__file__).resolve().parents[1] / "data" / "pick_real" / "sick-appspace-samples" / "EdgeMatcherMulti"
SEED = 11


def _read(path: Path, flags: int) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    assert img is not None, path
    return np.asarray(img)


def _teach_screws(out: Path, *extra: str) -> PartModel:
    args = ["pick", "teach", "--out", str(out), *extra]
    for roi in ROIS:
        args += ["--image", str(TEACH), "--roi", roi]
    r = run_cli(*args)
    assert r.returncode == 0, r.stderr
    return PartModel.load(out)


@pytest.fixture()
def colour_cell(tmp_path: Path) -> Iterator[Services]:
    """The virtual cell with its camera replaced by a replay of the colour screw photo (drivers.replay, a real
    camera driver) and the sim world's true camera and hand-eye active (as tests/cellctl/test_pick_flow.py)."""
    rec = RecordingWriter(tmp_path / "rec")
    frame = Frame(pixels=_read(SCENE, cv2.IMREAD_COLOR), timestamp_s=0.0, frame_id=1, camera_id="cam0",
                  metadata={})
    rec.add_frame("cam0", frame)
    rec.close()
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp_path / "cell.db")}
    data["cameras"]["cam0"] = {"kind": "replay", "settings": {"path": str(tmp_path / "rec"), "loop": True}}
    data["robots"]["robot0"]["settings"]["seed"] = SEED
    with calibrated_services(data, SEED) as svc:
        yield svc


def test_screws_taught_in_colour_from_the_cli_are_picked_at_their_rim_centres(colour_cell: Services,
                                                                             tmp_path: Path) -> None:
    model = _teach_screws(tmp_path / "screw.json", "--colour", "auto", "--refine", "rim")
    stored = json.loads((tmp_path / "screw.json").read_text())
    assert stored["refine"] == "rim" and stored["teach"]["params"]["colour"] == "auto"
    assert "colour" in stored["shape"] and model.shape is not None and model.shape.colour is not None
    recipe = Recipe(name="screws", models=[stored], plane_z_mm=0.0, grasp_z_mm=5.0, approach_height_mm=40.0,
                    search=SearchSettings(timeout_s=None))  # (the default 1 s answers with what it found so far)
    colour_cell.store.save_recipe(1, "screws", recipe.model_dump(mode="json"), "test")
    answer = run_pick(colour_cell, 1)
    picks = answer["picks"]
    assert len(picks) == 3, answer.get("reason")
    robot = colour_cell.cell.robot("robot0").ensure_open()
    mapping = active_mapping(colour_cell, "cam0", "robot0")
    T_capture = robot.state().T_base_tool
    for u, v in HEADS:
        p = min(picks, key=lambda p: math.hypot(p["u_px"] - u, p["v_px"] - v))
        assert p["refine"] == "rim"
        assert math.hypot(p["u_px"] - u, p["v_px"] - v) < 1.0, (p["u_px"], p["v_px"], u, v)
        s_px = p["sigma_px"]
        assert 0.02 < s_px < 1.0
        # the pick's sigma_mm carries the rim fit's: the calibration's alone, and the fit's at the local scale
        cal = mapping.map(np.array([p["u_px"], p["v_px"]]), 0.0, T_capture).sigma_mm
        a = mapping.map(np.array([p["u_px"], p["v_px"]]), 0.0, T_capture, with_uncertainty=False).xyz_mm
        b = mapping.map(np.array([p["u_px"] + 1.0, p["v_px"]]), 0.0, T_capture, with_uncertainty=False).xyz_mm
        s_fit = s_px * float(np.linalg.norm(b[:2] - a[:2]))
        got = p["uncertainty"]["sigma_mm"]
        assert got[0] == pytest.approx(math.hypot(cal[0], s_fit), rel=0.05)
        assert got[0] > cal[0] * 1.01
        assert got[2] == pytest.approx(cal[2])


def test_a_grey_model_file_is_as_before_and_finds_alike_in_the_colour_photo(tmp_path: Path) -> None:
    """``--colour grey`` (the default before session 16) reads the files' grey values and writes the file as
    before, byte for byte: no ``colour``, ``refine`` or ``origin_px`` key; the model finds the same in the
    colour image (its grey value) as in the grey one."""
    model = _teach_screws(tmp_path / "screw.json", "--colour", "grey")
    grey = [_read(TEACH, cv2.IMREAD_GRAYSCALE)] * 4
    rois = [(a, b, c, d) for a, b, c, d in (tuple(float(x) for x in r.split(",")) for r in ROIS)]
    before = PartModel("screw", "shape", rois[0], (grey[0].shape[1], grey[0].shape[0]), str(TEACH),
                       shape=shape.teach_many(grey, rois, shape.TeachParams(colour="grey")))
    before.save(tmp_path / "before.json")
    assert (tmp_path / "screw.json").read_bytes() == (tmp_path / "before.json").read_bytes()
    stored = json.loads((tmp_path / "screw.json").read_text())
    assert "refine" not in stored and "colour" not in stored["teach"]["params"]
    assert "colour" not in stored["shape"] and "origin_px" not in stored["shape"]
    assert model.shape is not None and model.shape.colour is None and model.refine is None
    colour = _read(SCENE, cv2.IMREAD_COLOR)
    a = model.find(cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)).matches
    b = model.find(colour).matches
    assert len(a) >= 1 and [x.as_dict() for x in a] == [y.as_dict() for y in b]
    assert all("refine" not in x.as_dict() for x in a)
    # (the JPEG decoded straight to grey, as the CLI reads a grey model's images, differs from the colour
    # decode's grey value by a level here and there: the same heads, not the same sub-pixels)
    assert len(model.find(_read(SCENE, cv2.IMREAD_GRAYSCALE)).matches) == len(a)


def test_the_default_colour_mode_is_auto_colour_for_the_screws_grey_as_before_for_a_grey_part(tmp_path: Path) -> None:
    """``cellctl pick teach`` without ``--colour``: ``auto`` (session 16). The screws (zinc on orange wood) make
    a colour model; a part that is not coloured against its background (the shaft support of a colour JPEG)
    makes the grey model ``--colour grey`` makes, from the file's grey values (the JPEG decoded straight to
    grey, as before), its file differing only by ``teach.params.colour``; a blob model stays grey."""
    model = _teach_screws(tmp_path / "screw.json")
    stored = json.loads((tmp_path / "screw.json").read_text())
    assert stored["teach"]["params"]["colour"] == "auto" and "colour" in stored["shape"]
    assert model.shape is not None and model.shape.colour is not None
    shaft = Path(__file__).resolve().parents[1] / "data" / "pick_real" / "invariant-templatematching" / "images"
    base = ["pick", "teach", "--image", str(shaft / "template_1.jpg"), "--roi", "325,64,175,150"]
    for name, extra in (("auto.json", ()), ("grey.json", ("--colour", "grey"))):
        r = run_cli(*base, "--out", str(tmp_path / name), "--name", "shaft", *extra)
        assert r.returncode == 0, r.stderr
    auto, grey = (json.loads((tmp_path / n).read_text()) for n in ("auto.json", "grey.json"))
    assert auto["teach"]["params"].pop("colour") == "auto" and "colour" not in grey["teach"]["params"]
    assert auto == grey
    r = run_cli(*base, "--out", str(tmp_path / "blob.json"), "--mode", "blob")
    assert r.returncode == 0, r.stderr
    assert "colour" not in json.loads((tmp_path / "blob.json").read_text())["teach"].get("params", {})


def test_a_bad_colour_mode_and_a_part_that_is_not_round_are_refused_naming_what_to_do(tmp_path: Path) -> None:
    r = run_cli("pick", "teach", "--image", str(TEACH), "--roi", ROIS[0], "--out", str(tmp_path / "m.json"),
                "--colour", "rgb")
    assert r.returncode == 2 and "rgb" in r.stderr and all(c in r.stderr for c in ("grey", "chroma", "auto"))
    r = run_cli("pick", "teach", "--image", str(HASH_PART / "Teach.bmp"), "--roi", "252,180,120,110",
                "--out", str(tmp_path / "hash.json"), "--refine", "rim")
    assert r.returncode == 2 and "round" in r.stderr, r.stderr
    assert not (tmp_path / "hash.json").exists()
    r = run_cli("pick", "teach", "--image", str(HASH_PART / "Teach.bmp"), "--roi", "252,180,120,110",
                "--out", str(tmp_path / "hash.json"), "--colour", "chroma")
    assert r.returncode == 2 and "colour teach images" in r.stderr, r.stderr
    r = run_cli("pick", "teach", "--image", str(TEACH), "--roi", ROIS[0], "--out", str(tmp_path / "b.json"),
                "--mode", "blob", "--colour", "auto")
    assert r.returncode == 2 and "shape" in r.stderr, r.stderr
    # a model file whose refine this cellctl does not know is refused, not run without it
    d = json.loads(json.dumps(PartModel.from_dict({"format_version": 1, "mode": "blob", "teach": {
        "roi": [0, 0, 4, 4], "image_size": [8, 8]}, "blob": {"polarity": "dark", "threshold": 100.0, "area_px": 9.0,
        "elongation": 1.0, "compactness": 1.0, "angle_deg": 0.0, "directed": False, "offset_px": [0.0, 0.0]}}
                                                 ).to_dict()))
    d["refine"] = "rim"
    with pytest.raises(ValueError, match="refine"):
        PartModel.from_dict(d)


def test_the_rest_teach_takes_the_colour_mode_more_rois_and_refine_and_refuses_bad_ones(tmp_path: Path) -> None:
    """``POST /pick/teach`` on the virtual cell (a grey camera; its bracket is not round)."""
    from tests.support.app import in_process_cell

    bracket = [906, 141, 200, 200]
    with in_process_cell(tmp_path) as c:
        r = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "colour": "rgb"})
        assert r.status_code == 422 and all(x in r.text for x in ("grey", "chroma", "auto")), r.text
        r = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "refine": "rim"})
        assert r.status_code == 422 and r.json()["error"]["code"] == "not_round", r.text
        assert "round" in r.json()["error"]["message"]
        r = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "colour": "chroma"})
        assert r.status_code == 422 and "colour teach images" in r.text, r.text
        plain = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket})
        auto = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "colour": "auto"})
        assert plain.status_code == 200 and auto.status_code == 200, auto.text
        assert "refine" not in plain.json() and "colour" not in plain.json()["shape"]
        # auto on a grey camera: the grey value (each grab has its own noise: the same keys, not the same points)
        assert "colour" not in auto.json()["shape"] and auto.json()["shape"].keys() == plain.json()["shape"].keys()
        assert auto.json()["teach"]["params"]["colour"] == "auto"
        # the default is auto (session 16): the plain teach's params say so; a blob model stays grey
        assert plain.json()["teach"]["params"]["colour"] == "auto"
        blob = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "mode": "blob"})
        assert blob.status_code == 200, blob.text
        r = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "mode": "blob", "colour": "auto"})
        assert r.status_code == 422 and "shape" in r.text, r.text
        two = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "more_rois": [bracket]})
        assert two.status_code == 200, two.text
        r = c.client.post("/pick/teach", headers=c.auth(), json={"roi": bracket, "more_rois": [[5000, 0, 10, 10]]})
        assert r.status_code == 422 and "outside" in r.text, r.text
