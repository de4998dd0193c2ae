"""Record from the virtual cell, replay it as a camera and a robot; refuse newer formats."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from cellctl.cli import main
from drivers.base import DeviceUnavailable, MotionLimits, MotionRejected
from drivers.recording import Recording, RecordingError
from drivers.replay import ReplayCamera, ReplayRobot, ReplaySettings

LIMITS = MotionLimits((100.0, 800.0), (-400.0, 400.0), (50.0, 800.0), 0.25)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rec") / "run1"
    assert main(["record", "--out", str(out), "--frames", "3", "--interval-s", "0.2"]) == 0
    return out


def test_recording_layout(recording: Path) -> None:
    manifest = json.loads((recording / "manifest.json").read_text())
    assert manifest["format_version"] == 1
    assert manifest["cameras"] == {"cam0": {"frames": 3}}
    assert manifest["robots"] == {"robot0": {"states": 3}}
    rec = Recording(recording)
    assert [f.file.name for f in rec.frames] == ["000001.png", "000002.png", "000003.png"]


def test_replay_camera_returns_the_recorded_frames(recording: Path) -> None:
    import cv2

    with ReplayCamera("cam0", ReplaySettings(path=str(recording))) as cam:
        frames = [cam.grab() for _ in range(3)]
        with pytest.raises(DeviceUnavailable, match="recording has ended"):
            cam.grab()
    original = cv2.imread(str(recording / "cam0" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert original is not None
    assert np.array_equal(frames[1].pixels, original)
    assert frames[0].timestamp_s < frames[1].timestamp_s < frames[2].timestamp_s


def test_replay_at_recorded_timing(recording: Path) -> None:
    rec = Recording(recording)
    span = rec.frames[-1].timestamp_s - rec.frames[0].timestamp_s
    with ReplayCamera("cam0", ReplaySettings(path=str(recording), speed=1.0)) as cam:
        t0 = time.monotonic()
        for _ in range(3):
            cam.grab(timeout_s=5.0)
        elapsed = time.monotonic() - t0
    assert span * 0.9 <= elapsed <= span + 1.0


def test_replay_loop(recording: Path) -> None:
    with ReplayCamera("cam0", ReplaySettings(path=str(recording), loop=True)) as cam:
        ids = [cam.grab().frame_id for _ in range(5)]
    assert ids[3] == ids[0]


def test_replay_robot_states_and_refuses_motion(recording: Path) -> None:
    rec = Recording(recording)
    with ReplayRobot("robot0", ReplaySettings(path=str(recording)), LIMITS) as robot:
        states = [robot.state() for _ in range(3)]
        assert np.allclose(states[0].T_base_tool, rec.robot_states(None)[0].T_base_tool)
        assert states[0].age_s() < 1.0
        with pytest.raises(MotionRejected, match="replay"):
            robot.move_linear(states[0].T_base_tool, 0.1)


def test_newer_format_is_refused_and_nothing_changes(recording: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "newer"
    shutil.copytree(recording, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["format_version"] = 2
    (copy / "manifest.json").write_text(json.dumps(manifest))
    before = sorted(p.name for p in copy.rglob("*"))
    with pytest.raises(RecordingError, match="format_version 2 is newer than this cellctl reads"):
        Recording(copy)
    with pytest.raises(DeviceUnavailable, match="newer"):
        ReplayCamera("cam0", ReplaySettings(path=str(copy))).open()
    assert sorted(p.name for p in copy.rglob("*")) == before


def test_record_refuses_non_empty_folder(recording: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["record", "--out", str(recording), "--frames", "1"]) == 2
    assert "not empty" in capsys.readouterr().err
