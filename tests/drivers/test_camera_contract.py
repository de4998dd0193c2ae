"""One camera contract, the same checks (``camera_contract.py``) over every camera adapter.

- ``sim``: the virtual cell's rendered camera;
- ``replay``: a recording played back;
- ``opencv_file`` / ``opencv_stream``: a video file, and a live MJPEG stream from 127.0.0.1;
- ``aravis_fake``: Aravis's in-process Fake camera;
- ``aravis_gige``: ``arv-fake-gv-camera`` over real GVCP/GVSP, inside a loopback-only network
  namespace (the checks run there; their results come back as JSON).

Each check builds fresh adapters, so the order of the tests does not matter.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from drivers.base import CameraBase, Frame
from drivers.camera.aravis import AravisCamera
from drivers.camera.opencv import OpenCVCamera
from drivers.recording import RecordingWriter
from drivers.registry import adapter_class
from drivers.replay import ReplayCamera, ReplaySettings
from tests.drivers.camera_contract import CHECKS, Factory
from tests.drivers.netns import run_scenario
from tests.drivers.peers import MjpegServer

KINDS = ["sim", "replay", "opencv_file", "opencv_stream", "aravis_fake"]


def _recording(tmp_path: Path) -> Path:
    writer = RecordingWriter(tmp_path / "rec")
    for i in range(4):
        writer.add_frame("cam0", Frame(pixels=np.full((48, 64), 30 * i, np.uint8), timestamp_s=100.0 + 0.1 * i,
                                       frame_id=i + 1, camera_id="cam0"))
    writer.close()
    return tmp_path / "rec"


def _video(tmp_path: Path) -> Path:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 25.0, (64, 48))
    for i in range(6):
        writer.write(np.full((48, 64, 3), 30 * i + 20, np.uint8))
    writer.release()
    return path


@pytest.fixture
def factory(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Factory]:
    kind: str = request.param
    stream: MjpegServer | None = None
    make: Callable[[], CameraBase]
    if kind == "sim":
        sim_cls: Any = adapter_class("camera", "sim")
        make = lambda: sim_cls("cam0", sim_cls.Settings(seed=5))  # noqa: E731
    elif kind == "replay":
        rec = _recording(tmp_path)
        make = lambda: ReplayCamera("cam0", ReplaySettings(path=str(rec), loop=True))  # noqa: E731
    elif kind == "opencv_file":
        video = _video(tmp_path)
        make = lambda: OpenCVCamera("cam0", {"source": str(video)})  # noqa: E731
    elif kind == "opencv_stream":
        stream = MjpegServer().start()
        url = stream.url
        make = lambda: OpenCVCamera("cam0", {"source": url, "stall_timeout_s": 1.0})  # noqa: E731
    else:
        make = lambda: AravisCamera("cam0", {"device_id": "Fake_1", "interfaces": ["Fake"]})  # noqa: E731
    try:
        yield make
    finally:
        if stream is not None:
            stream.stop()


@pytest.mark.parametrize("check", sorted(CHECKS))
@pytest.mark.parametrize("factory", KINDS, indirect=True)
def test_camera_contract(factory: Factory, check: str) -> None:
    CHECKS[check](factory)


def test_camera_contract_over_gige_in_a_loopback_namespace() -> None:
    results = run_scenario("contract", 180.0)
    assert set(results) == set(CHECKS)
    failed = {name: err for name, err in results.items() if err}
    assert not failed, failed
