"""End-to-end: ``cellctl serve`` as a real process, a real HTTP client, the virtual cell's truth."""

from __future__ import annotations

import subprocess

import cv2
import numpy as np

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.targets import target_from_dict
from tests.conftest import CELLCTL, Served


def test_health_is_open(served_virtual_cell: Served) -> None:
    import httpx

    r = httpx.get(served_virtual_cell.base_url + "/health")
    assert r.status_code == 200
    assert r.json()["cameras"] == {"cam0": True}


def test_routes_need_a_token(served_virtual_cell: Served) -> None:
    import httpx

    base = served_virtual_cell.base_url
    assert httpx.get(base + "/cameras").status_code == 401
    r = httpx.get(base + "/robots/robot0/state", headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401
    assert r.json()["error"]["code"] == "unauthorized"


def test_image_shows_the_plate_where_truth_says(served_virtual_cell: Served) -> None:
    with served_virtual_cell.client() as http:
        r = http.get("/cameras/cam0/image")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img is not None
    truth = subprocess.run([CELLCTL, "sim", "truth"], capture_output=True, check=True, text=True).stdout
    import json

    t = json.loads(truth)
    cam = CameraModel.from_dict(t["camera"])
    plate = t["targets"]["plate"]
    target = target_from_dict(plate["target"])
    T_cam_target = g.invert(np.array(t["T_base_cam"])) @ np.array(plate["T_base_target"])
    uv = cam.project(g.transform_points(T_cam_target, target.points().xyz_m))
    assert img.shape == (cam.height, cam.width)
    # Each mark is a dark disk centred on its projection: dark at the centre, its centroid on it.
    for u, v in uv:
        u0, v0, h = int(round(u)), int(round(v)), 12
        patch = img[v0 - h : v0 + h + 1, u0 - h : u0 + h + 1].astype(float)
        assert patch[h, h] < 80
        w = np.clip(200.0 - patch, 0, None)
        vv, uu = np.mgrid[v0 - h : v0 + h + 1, u0 - h : u0 + h + 1]
        cu, cv = (w * uu).sum() / w.sum(), (w * vv).sum() / w.sum()
        assert np.hypot(cu - u, cv - v) < 0.5  # centroid of a tilted, noisy disk: bias < 0.5 px


def test_jpeg_by_accept_header(served_virtual_cell: Served) -> None:
    with served_virtual_cell.client() as http:
        r = http.get("/cameras/cam0/image", headers={"Accept": "image/jpeg"})
        assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"


def test_robot_state_in_ur_form_and_4x4(served_virtual_cell: Served) -> None:
    with served_virtual_cell.client() as http:
        r = http.get("/robots/robot0/state")
    assert r.status_code == 200
    s = r.json()
    T = np.array(s["T_base_tool"])
    p = s["pose_ur"]
    assert np.allclose(T, g.ur_pose_to_transform([p["x_m"], p["y_m"], p["z_m"], p["rx_rad"], p["ry_rad"],
                                                  p["rz_rad"]]), atol=1e-9)
    assert abs(p["z_m"] - 0.55) < 0.001
    assert s["age_s"] < 1.0


def test_unknown_device_is_404_with_code(served_virtual_cell: Served) -> None:
    with served_virtual_cell.client() as http:
        r = http.get("/cameras/nope/image")
    assert r.status_code == 404
    assert r.json()["error"]["code"] == "unknown_camera"
