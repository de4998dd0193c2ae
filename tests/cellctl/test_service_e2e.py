"""End to end: the service's routes with a real HTTP client, checked against the virtual cell's truth.

The routes run on the app in this process (``tests.support.app.in_process_cell``: the same routes,
middleware and lifespan as ``cellctl serve``); ``cellctl sim truth`` runs in-process too
(``run_cli``). One test keeps the real ``cellctl serve`` process (``served_virtual_cell``): that it
starts, listens, refuses a missing token and sends a frame over a socket (slow: a new interpreter).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.targets import target_from_dict
from tests.conftest import Served
from tests.support.app import AppCell, in_process_cell
from tests.support.cli import run_cli


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AppCell]:
    with in_process_cell(tmp_path_factory.mktemp("e2e")) as app:
        yield app


@pytest.fixture()
def http(cell: AppCell) -> Iterator[httpx.Client]:
    """A client with the engineer's token."""
    with cell.http() as client:
        yield client


def test_health_is_open(cell: AppCell) -> None:
    r = cell.client.get("/health")
    assert r.status_code == 200
    assert r.json()["cameras"] == {"cam0": True}


def test_routes_need_a_token(cell: AppCell) -> None:
    assert cell.client.get("/cameras").status_code == 401
    r = cell.client.get("/robots/robot0/state", headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401
    assert r.json()["error"]["code"] == "unauthorized"


def truth_by_cli(tmp: Path) -> dict[str, Any]:
    """``cellctl sim truth`` in this process: the truth of this process's virtual cell (the in-process app's)."""
    truth = run_cli("sim", "truth", env={"CELLCTL_DATA_DIR": str(tmp / "data"), "PATH": "/usr/bin:/bin"})
    assert truth.returncode == 0, truth.stderr
    out: dict[str, Any] = json.loads(truth.stdout)
    return out


def check_plate_where_truth_says(png: bytes, t: dict[str, Any]) -> None:
    """Each mark of the plate in ``png`` is a dark disk centred on its true projection (``t``: the truth of the
    virtual cell that rendered it)."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
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


def test_image_shows_the_plate_where_truth_says(http: httpx.Client, tmp_path: Path) -> None:
    r = http.get("/cameras/cam0/image")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    check_plate_where_truth_says(r.content, truth_by_cli(tmp_path))


def test_jpeg_by_accept_header(http: httpx.Client) -> None:
    r = http.get("/cameras/cam0/image", headers={"Accept": "image/jpeg"})
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"


def test_robot_state_in_ur_form_and_4x4(http: httpx.Client) -> None:
    r = http.get("/robots/robot0/state")
    assert r.status_code == 200
    s = r.json()
    T = np.array(s["T_base_tool"])
    p = s["pose_ur"]
    assert np.allclose(T, g.ur_pose_to_transform([p["x_m"], p["y_m"], p["z_m"], p["rx_rad"], p["ry_rad"],
                                                  p["rz_rad"]]), atol=1e-9)
    assert abs(p["z_m"] - 0.55) < 0.001
    assert s["age_s"] < 1.0


def test_unknown_device_is_404_with_code(http: httpx.Client) -> None:
    r = http.get("/cameras/nope/image")
    assert r.status_code == 404
    assert r.json()["error"]["code"] == "unknown_camera"


def test_the_served_process_answers_over_a_socket(served_virtual_cell: Served) -> None:
    """``cellctl serve`` itself: /health open, a route without a token 401, the frame a PNG of the truth."""
    base = served_virtual_cell.base_url
    r = httpx.get(base + "/health")
    assert r.status_code == 200 and r.json()["cameras"] == {"cam0": True}
    assert httpx.get(base + "/cameras").status_code == 401
    with served_virtual_cell.client() as client:
        r = client.get("/cameras/cam0/image")
        # the served process's own truth: this test process's virtual cell may have moved (another test's
        # in-process cell on this worker jogged its robot: a mark 4.4 px off in one CI run)
        truth = client.get("/sim/truth")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert truth.status_code == 200, truth.text
    check_plate_where_truth_says(r.content, truth.json())
