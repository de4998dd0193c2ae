"""The camera contract as plain checks, so the same ones run in the test process and inside the
loopback-only network namespace (``netns.py``, for GigE Vision): each takes a camera *factory*
(a fresh, unopened adapter per call) and raises AssertionError when the adapter breaks the contract.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from drivers.base import Camera, CameraBase, DeviceUnavailable, DriverError, Frame

Factory = Callable[[], CameraBase]


def check_protocol_and_frames(make: Factory) -> None:
    """The adapter is a ``Camera``; ``with`` opens it; frames are numpy images, newer each grab."""
    cam = make()
    assert isinstance(cam, Camera), f"{type(cam).__name__} is not a Camera"
    with cam:
        a, b = cam.grab(5.0), cam.grab(5.0)
        for f in (a, b):
            assert isinstance(f, Frame) and isinstance(f.pixels, np.ndarray)
            assert f.pixels.ndim in (2, 3) and f.pixels.size > 0 and f.pixels.dtype in (np.uint8, np.uint16)
            assert f.camera_id == cam.camera_id and np.isfinite(f.timestamp_s) and f.timestamp_s > 0
            assert f.size == (f.pixels.shape[1], f.pixels.shape[0])
        assert (b.frame_id, b.timestamp_s) > (a.frame_id, a.timestamp_s), "the second frame is not newer"
        assert isinstance(cam.settings(), dict)


def check_lifecycle(make: Factory) -> None:
    """Grab before open is DeviceUnavailable; close twice is fine; the camera opens again after close."""
    cam = make()
    try:
        cam.grab(1.0)
    except DeviceUnavailable:
        pass
    else:
        raise AssertionError("grab() before open() did not raise DeviceUnavailable")
    cam.open()
    cam.grab(5.0)
    cam.close()
    cam.close()
    try:
        cam.grab(1.0)
    except DeviceUnavailable:
        pass
    else:
        raise AssertionError("grab() after close() did not raise DeviceUnavailable")
    cam.open()
    try:
        assert cam.grab(5.0).pixels.size > 0
    finally:
        cam.close()


def check_typed_refusals(make: Factory) -> None:
    """A setting the camera cannot take is refused with a DriverError naming what was wrong."""
    with make() as cam:
        try:
            cam.set_trigger("no-such-mode")
        except DriverError as exc:
            assert "no-such-mode" in str(exc) or "trigger" in str(exc), str(exc)
        else:
            raise AssertionError("set_trigger('no-such-mode') was accepted")
        cam.grab(5.0)  # the camera stays usable


CHECKS: dict[str, Callable[[Factory], None]] = {
    "protocol_and_frames": check_protocol_and_frames,
    "lifecycle": check_lifecycle,
    "typed_refusals": check_typed_refusals,
}


def run_all(make: Factory) -> dict[str, str]:
    """Every check; the failure text per check ('' when it passed), for reporting across processes."""
    out: dict[str, str] = {}
    for name, check in CHECKS.items():
        try:
            check(make)
            out[name] = ""
        except Exception as exc:  # noqa: BLE001 - reported to the test in the parent process
            out[name] = f"{type(exc).__name__}: {exc}"
    return out
