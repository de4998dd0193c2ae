"""Camera controls over REST (issue 36 item 8): the virtual cell's camera has exposure, gain and its trigger
modes (exposure and gain scale the light it renders); a camera whose driver has none (an OpenCV image
folder) says so on GET and refuses a PUT with the reason; every change, refused ones included, is audited
(engineer only). Aravis over real GigE Vision: ``tests/drivers/test_aravis.py``."""

from __future__ import annotations

from pathlib import Path

import cv2
import httpx
import numpy as np
import yaml

from cellctl.config import default_config_text
from tests.conftest import REPO
from tests.support.app import in_process_cell

FOLDER = REPO / "tests" / "data" / "udacity_camera_cal_9x6"


def _mean(http: httpx.Client, camera_id: str) -> float:
    r = http.get(f"/cameras/{camera_id}/image", params={"format": "png"})
    assert r.status_code == 200, r.text
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    return float(img.mean())


def test_camera_controls_set_checked_and_audited(tmp_path: Path) -> None:
    cfg = yaml.safe_load(default_config_text())
    cfg["cameras"]["folder"] = {"kind": "opencv", "settings": {"source": str(FOLDER)}}
    cfg["store"]["path"] = str(tmp_path / "cell.db")
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with in_process_cell(tmp_path, path) as a, a.http() as http:
        got = http.get("/cameras/cam0/controls").json()
        c = got["controls"]
        assert got["kind"] == "sim" and all(c[k]["supported"] for k in ("exposure_us", "gain_db", "trigger"))
        assert c["exposure_us"]["value"] == 10000 and c["gain_db"]["min"] == 0 and c["gain_db"]["max"] == 48
        assert c["trigger"]["options"] == ["software", "free_run"]

        dark = _mean(http, "cam0")
        r = http.put("/cameras/cam0/controls", json={"exposure_us": 5000, "gain_db": 0})
        assert r.status_code == 200, r.text
        assert r.json()["controls"]["exposure_us"]["value"] == 5000
        half = _mean(http, "cam0")
        assert abs(half - dark / 2) < 0.05 * dark, (dark, half)  # half the exposure, half the light
        assert http.get("/cameras/cam0/settings").json()["exposure_us"] == 5000

        r = http.put("/cameras/cam0/controls", json={"gain_db": 60})
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_control", r.text
        assert "outside the camera's range 0..48 dB" in r.json()["error"]["message"]
        r = http.put("/cameras/cam0/controls", json={"trigger": "hardware", "exposure_us": 8000})
        assert r.status_code == 422 and "software, free_run" in r.json()["error"]["message"], r.text
        assert http.get("/cameras/cam0/controls").json()["controls"]["exposure_us"]["value"] == 5000  # all or none
        r = http.put("/cameras/cam0/controls", json={"exposure_ms": 5})
        assert r.status_code == 422 and "exposure_ms" in r.text
        assert http.put("/cameras/cam0/controls", json={}).status_code == 422

        none = http.get("/cameras/folder/controls").json()
        assert none["kind"] == "opencv" and not any(v["supported"] for v in none["controls"].values())
        assert none["controls"]["gain_db"]["why"] == "the opencv camera driver has no gain db control"
        r = http.put("/cameras/folder/controls", json={"gain_db": 3})
        assert r.status_code == 422 and r.json()["error"]["code"] == "control_unsupported", r.text
        assert "has no gain_db control (its driver offers: none)" in r.json()["error"]["message"]

        audit = [e for e in http.get("/audit", params={"limit": 50}).json() if e["action"] == "camera.controls"]
        assert len(audit) == 4, audit  # one ok, three refused (the empty body never reached the camera)
        ok = next(e for e in audit if e["result"] == "ok")
        assert ok["target"] == "camera:cam0" and ok["detail"]["before"] == {"exposure_us": 10000, "gain_db": 0}
        assert ok["detail"]["after"] == {"exposure_us": 5000, "gain_db": 0}
        assert sum(e["result"].startswith("refused") for e in audit) == 3
        assert http.get("/cameras/nope/controls").status_code == 404
