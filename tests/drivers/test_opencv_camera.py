"""The OpenCV camera adapter on an image folder, a video file and a live MJPEG stream (127.0.0.1)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.base import DeviceInitError, DeviceOperationError, DeviceTimeout, DeviceUnavailable
from drivers.camera.opencv import OpenCVCamera
from drivers.registry import adapter_class
from tests.drivers.peers import MjpegServer, free_port


def _images(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, (40, 60, 3), dtype=np.uint8) for _ in range(n)]


def test_registry_and_settings() -> None:
    cls = adapter_class("camera", "opencv")
    assert cls is OpenCVCamera
    with pytest.raises(ValueError, match="fourcc"):
        cls.Settings.model_validate({"source": "/dev/video0", "fourcc": "MJPEG"})
    with pytest.raises(ValueError, match="extra"):
        cls.Settings.model_validate({"source": 0, "exposure": 100})


def test_image_folder_in_sorted_order_and_loop(tmp_path: Path) -> None:
    imgs = _images(3)
    cv2.imwrite(str(tmp_path / "b.png"), imgs[1])
    cv2.imwrite(str(tmp_path / "a.png"), imgs[0])
    cv2.imwrite(str(tmp_path / "c.bmp"), imgs[2])
    (tmp_path / "notes.txt").write_text("not an image")
    with OpenCVCamera("cam0", {"source": str(tmp_path)}) as cam:
        assert cam.settings()["images"] == 3
        frames = [cam.grab() for _ in range(4)]
    assert [f.metadata["file"] for f in frames] == ["a.png", "b.png", "c.bmp", "a.png"]
    for f, img in zip(frames, imgs + imgs[:1], strict=True):
        np.testing.assert_array_equal(f.pixels, img)
    assert [f.frame_id for f in frames] == [1, 2, 3, 4] and frames[0].size == (60, 40)
    cam.close()  # idempotent

    with OpenCVCamera("cam0", {"source": str(tmp_path), "loop": False, "grey": True}) as cam:
        grey = [cam.grab() for _ in range(3)]
        with pytest.raises(DeviceUnavailable, match="exhausted"):
            cam.grab()
    assert grey[0].pixels.shape == (40, 60)
    np.testing.assert_array_equal(grey[0].pixels, cv2.cvtColor(imgs[0], cv2.COLOR_BGR2GRAY))


def test_folder_faults(tmp_path: Path) -> None:
    with pytest.raises(DeviceUnavailable, match="does not exist"):
        OpenCVCamera("cam0", {"source": str(tmp_path / "missing"), "source_type": "folder"}).open()
    with pytest.raises(DeviceInitError, match="has no"):
        OpenCVCamera("cam0", {"source": str(tmp_path)}).open()
    cv2.imwrite(str(tmp_path / "a.png"), _images(1)[0])
    (tmp_path / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")  # malformed file
    with OpenCVCamera("cam0", {"source": str(tmp_path)}) as cam:
        cam.grab()
        with pytest.raises(DeviceOperationError, match="b.png is not a readable image"):
            cam.grab()
        assert cam.grab().metadata["file"] == "a.png"  # the camera stays usable


def test_video_file(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 25.0, (64, 48))
    for i in range(5):
        writer.write(np.full((48, 64, 3), 40 * i + 20, np.uint8))
    writer.release()
    with OpenCVCamera("cam0", {"source": str(path)}) as cam:
        assert cam.source_type == "file" and cam.settings()["frames"] == 5
        means = [float(cam.grab().pixels.mean()) for _ in range(7)]
    np.testing.assert_allclose(means, [20, 60, 100, 140, 180, 20, 60], atol=3)
    with OpenCVCamera("cam0", {"source": str(path), "loop": False}) as cam:
        for _ in range(5):
            cam.grab()
        with pytest.raises(DeviceUnavailable, match="no more frames"):
            cam.grab()
    with pytest.raises(DeviceUnavailable, match="does not exist"):
        OpenCVCamera("cam0", {"source": str(tmp_path / "nope.avi")}).open()
    (tmp_path / "bad.avi").write_bytes(b"RIFF0000AVI garbage" * 10)
    with pytest.raises(DeviceUnavailable, match="cannot open"):
        OpenCVCamera("cam0", {"source": str(tmp_path / "bad.avi")}).open()


def test_stream_newest_frame_and_recovery_after_the_peer_restarts() -> None:
    peer = MjpegServer().start()
    cam = OpenCVCamera("cam0", {"source": peer.url, "stall_timeout_s": 0.5, "reconnect_initial_s": 0.1,
                                "reconnect_max_s": 0.5})
    try:
        cam.open()
        a = cam.grab(timeout_s=5)
        b = cam.grab(timeout_s=2)
        assert b.frame_id > a.frame_id and b.timestamp_s >= a.timestamp_s
        assert b.pixels.shape == (48, 64, 3)
        port = peer.port
        peer.stop()  # killed mid-stream
        time.sleep(0.2)
        with pytest.raises(DeviceTimeout, match="no frame within"):
            cam.grab(timeout_s=0.3)
        peer = MjpegServer(port=port).start()
        cam.grab(timeout_s=8)  # recovers by itself: stall 0.5 s + backoff <= 0.5 s + reopen
        h = cam.health()
        assert h.available and h.outages == 1 and h.reconnects >= 1
    finally:
        cam.close()
        peer.stop()


def test_stream_connect_and_read_timeouts() -> None:
    port = free_port()  # nothing listens: refused at once
    t0 = time.monotonic()
    with pytest.raises(DeviceUnavailable, match="cannot open stream"):
        OpenCVCamera("cam0", {"source": f"http://127.0.0.1:{port}/stream.mjpg", "open_timeout_s": 2}).open()
    assert time.monotonic() - t0 < 1.0
    # a peer that accepts and then says nothing: bounded by open_timeout_s, no hang
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(4)
    try:
        t0 = time.monotonic()
        with pytest.raises(DeviceUnavailable, match="cannot open stream"):
            OpenCVCamera("cam0", {"source": f"http://127.0.0.1:{silent.getsockname()[1]}/stream.mjpg",
                                  "open_timeout_s": 1.0, "stall_timeout_s": 1.0}).open()
        assert time.monotonic() - t0 < 3.0
    finally:
        silent.close()
