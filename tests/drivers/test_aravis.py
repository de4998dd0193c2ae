"""The Aravis camera adapter: Aravis's in-process Fake camera, and arv-fake-gv-camera over real
GVCP/GVSP inside a loopback-only network namespace (no packet leaves the namespace)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.base import DeviceInitError
from drivers.camera.aravis import AravisCamera
from drivers.registry import adapter_class
from tests.drivers.netns import REPO, run_scenario
from tests.drivers.peers import answers_within

FAKE = {"device_id": "Fake_1", "interfaces": ["Fake"]}  # GigEVision/USB3Vision stay disabled: no broadcast


def test_registry_and_settings() -> None:
    assert adapter_class("camera", "aravis") is AravisCamera
    with pytest.raises(ValueError, match="pixel_format"):
        AravisCamera.Settings.model_validate({"device_id": "x", "pixel_format": "Mono10p"})
    with pytest.raises(ValueError, match="buffer_count"):
        AravisCamera.Settings.model_validate({"device_id": "x", "buffer_count": 1})


def test_missing_binding_names_the_packages() -> None:
    code = ("import sys; sys.modules['gi'] = None\n"
            "from drivers.camera.aravis import AravisCamera\n"
            "from drivers.base import DeviceInitError\n"
            "try:\n    AravisCamera('c', {'device_id': 'Fake_1', 'interfaces': ['Fake']})\n"
            "except DeviceInitError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60).stdout
    assert "gir1.2-aravis-0.8" in out and "PyGObject" in out and "libaravis-0.8-0" in out


def test_fake_camera_frames_formats_and_roi() -> None:
    with AravisCamera("cam0", {**FAKE, "frame_rate_hz": 50}) as cam:
        a = cam.grab(3.0)
        b = cam.grab(3.0)
        assert b.frame_id > a.frame_id and a.pixels.shape == (512, 512) and a.pixels.dtype == np.uint8
        assert abs(time.time() - b.timestamp_s) < 0.5 and b.metadata["camera_timestamp_ns"] > 0
        cam.set_exposure_us(2000)
        cam.set_gain_db(6)
        s = cam.settings()
        assert s["exposure_us"] == pytest.approx(2000) and s["gain_db"] == pytest.approx(6)
        assert (cam.health().frames_received or 0) >= 2 and cam.health().frames_lost == 0
    roi = {"x_px": 32, "y_px": 16, "width_px": 200, "height_px": 100}
    for fmt, shape, dtype in (("Mono16", (100, 200), np.uint16), ("BayerRG8", (100, 200, 3), np.uint8),
                              ("RGB8", (100, 200, 3), np.uint8)):
        with AravisCamera("cam0", {**FAKE, "pixel_format": fmt, "roi": roi}) as cam:
            f = cam.grab(3.0)
            assert f.pixels.shape == shape and f.pixels.dtype == dtype and f.metadata["pixel_format"] == fmt
            assert f.pixels.max() > 0
    with pytest.raises(DeviceInitError, match="Mono12 is not offered"):
        AravisCamera("cam0", {**FAKE, "pixel_format": "Mono12"}).open()


def test_fake_camera_triggers() -> None:
    # (Aravis's in-process Fake keeps streaming in trigger mode; that trigger mode really gates frames
    # is checked against arv-fake-gv-camera in test_gige_fake_camera_in_loopback_namespace)
    with AravisCamera("cam0", {**FAKE, "frame_rate_hz": 5, "trigger": "software"}) as cam:
        assert cam.settings()["trigger"] == "software"
        # a software trigger fires at grab: the frame comes at once, not after a timeout
        assert answers_within(lambda: cam.grab(3.0), 1.0) is None
        cam.set_trigger("free_run")
        cam.grab(3.0)
        cam.grab(3.0)
        with pytest.raises(DeviceInitError, match="TriggerSource 'Line7' is not accepted"):
            AravisCamera("cam1", {**FAKE, "trigger": "hardware", "trigger_source": "Line7"}).open()


def test_gige_fake_camera_in_loopback_namespace() -> None:
    r = run_scenario("gige")
    for key in ("open_127.0.0.1", "open_Aravis-Fake-GV01", "open_GV01"):  # by IP, device id, serial
        assert r[key]["shape"] == [512, 512] and r[key]["serial"] == "GV01" and r[key]["age_s"] < 0.5
    c = r["configured"]
    assert c["shape"] == [128, 256] and c["dtype"] == "uint16"
    s = c["settings"]
    assert s["roi"] == {"x_px": 16, "y_px": 8, "width_px": 256, "height_px": 128}
    assert s["exposure_us"] == pytest.approx(5000) and s["gain_db"] == pytest.approx(3)
    assert s["frame_rate_hz"] == pytest.approx(30, rel=1e-3)
    assert c["ids"] == sorted(c["ids"]) and c["health"]["frames_lost"] == 0 and c["health"]["frames_incomplete"] == 0
    assert r["software_trigger"]["frames_without_trigger"] == 0 and r["software_trigger"]["error"] == ""
    assert "TriggerSource 'Line1' is not accepted" in r["hardware_trigger_error"]


def test_gige_faults_in_loopback_namespace() -> None:
    r = run_scenario("faults")
    assert r["connect_without_camera"]["error"].startswith("DeviceUnavailable")
    assert r["connect_without_camera"]["s"] < 6.0
    assert r["garbage_peer"]["error"].startswith("DeviceUnavailable") and r["garbage_peer"]["s"] < 6.0
    assert r["grab_after_kill"]["error"].startswith(("DeviceTimeout", "DeviceUnavailable"))
    assert r["grab_after_kill"]["s"] < 2.5  # no hang
    assert r["unavailable_after_s"] < 6.0 and r["health_down"]["available"] is False
    assert "reconnecting" in r["health_down"]["reason"]
    rec = r["recovered"]
    assert rec["error"] == "" and rec["s"] < 10.0  # recovers by itself (backoff <= 1 s)
    assert rec["health"]["outages"] == 1 and rec["health"]["reconnects"] >= 1


def test_camera_controls_over_rest_on_gige(tmp_path: Path) -> None:
    """``GET``/``PUT /cameras/{id}/controls`` on arv-fake-gv-camera (the service in process, in the namespace):
    the camera's own GenICam bounds, a change set and read back, one outside the bounds refused, audited."""
    r = run_scenario("controls", 120.0, str(tmp_path))
    c = r["get"]["controls"]
    assert r["get"]["kind"] == "aravis" and all(c[k]["supported"] for k in ("exposure_us", "gain_db", "trigger"))
    assert c["exposure_us"]["min"] > 0 and c["exposure_us"]["max"] > c["exposure_us"]["min"]
    assert set(c["trigger"]["options"]) >= {"free_run", "software"}
    assert r["put"]["status"] == 200, r["put"]
    assert r["settings"]["exposure_us"] == pytest.approx(4000) and r["settings"]["gain_db"] == pytest.approx(2)
    assert r["settings"]["trigger"] == "software" and r["image_status"] == 200 and r["image_s"] < 3.0
    assert r["too_long"]["status"] == 422 and r["too_long"]["body"]["error"]["code"] in ("invalid_control",
                                                                                         "invalid_request")
    assert r["free_run"] == {"status": 200, "trigger": "free_run"}
    assert [e["result"] for e in r["audit"]][-1] == "ok" and len(r["audit"]) >= 2
