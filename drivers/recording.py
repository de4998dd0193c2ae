"""Recording folder format: frames (PNG) and robot states with timestamps, versioned.

Layout of a recording ``DIR``::

    DIR/manifest.json        {"format_version": 1, "created_s", "cameras": {id: {"frames": n}},
                              "robots": {id: {"states": n}}}
    DIR/frames.csv           camera_id,frame_id,timestamp_s,file
    DIR/robot_states.csv     robot_id,timestamp_s,x,y,z,rx,ry,rz,j0..j5   (UR pose form: m, rad)
    DIR/<camera_id>/NNNNNN.png

The loader refuses a ``format_version`` newer than it knows, with a message saying so.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.geometry import transform_to_ur_pose, ur_pose_to_transform
from drivers.base import Frame, RobotState
from drivers.errors import DriverInputError

RECORDING_FORMAT_VERSION = 1


class RecordingError(DriverInputError):
    """A recording folder is missing, malformed, or of a newer format."""


@dataclass(frozen=True)
class FrameEntry:
    camera_id: str
    frame_id: int
    timestamp_s: float
    file: Path


class RecordingWriter:
    """Writes a recording folder incrementally; ``close()`` writes the manifest last."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if self.root.exists() and any(self.root.iterdir()):
            raise RecordingError(f"{self.root}: the output folder exists and is not empty; choose a new folder")
        self.root.mkdir(parents=True, exist_ok=True)
        self._frames = (self.root / "frames.csv").open("w", newline="")
        self._frames_csv = csv.writer(self._frames)
        self._frames_csv.writerow(["camera_id", "frame_id", "timestamp_s", "file"])
        self._states = (self.root / "robot_states.csv").open("w", newline="")
        self._states_csv = csv.writer(self._states)
        self._states_csv.writerow(["robot_id", "timestamp_s", "x", "y", "z", "rx", "ry", "rz",
                                   "j0", "j1", "j2", "j3", "j4", "j5"])
        self._counts: dict[str, dict[str, int]] = {"cameras": {}, "robots": {}}
        self._created = time.time()

    def add_frame(self, camera_id: str, frame: Frame) -> None:
        n = self._counts["cameras"].get(camera_id, 0) + 1
        rel = Path(camera_id) / f"{n:06d}.png"
        (self.root / camera_id).mkdir(exist_ok=True)
        if not cv2.imwrite(str(self.root / rel), frame.pixels):
            raise RecordingError(f"{self.root / rel}: could not write the frame")
        self._frames_csv.writerow([camera_id, frame.frame_id, repr(frame.timestamp_s), rel.as_posix()])
        self._counts["cameras"][camera_id] = n

    def add_state(self, robot_id: str, state: RobotState) -> None:
        pose = transform_to_ur_pose(state.T_base_tool)
        joints = list(np.asarray(state.joints_rad, dtype=np.float64).reshape(-1)[:6])
        joints += [0.0] * (6 - len(joints))
        self._states_csv.writerow([robot_id, repr(state.timestamp_s), *[repr(float(v)) for v in pose],
                                   *[repr(float(v)) for v in joints]])
        self._counts["robots"][robot_id] = self._counts["robots"].get(robot_id, 0) + 1

    def close(self) -> dict[str, Any]:
        self._frames.close()
        self._states.close()
        manifest = {
            "format_version": RECORDING_FORMAT_VERSION,
            "created_s": self._created,
            "cameras": {k: {"frames": v} for k, v in self._counts["cameras"].items()},
            "robots": {k: {"states": v} for k, v in self._counts["robots"].items()},
        }
        (self.root / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
        return manifest


class Recording:
    """A recording folder, read and validated."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        mpath = self.root / "manifest.json"
        try:
            manifest = json.loads(mpath.read_text())
        except FileNotFoundError:
            raise RecordingError(f"{self.root}: no manifest.json; not a cellctl recording "
                                 "(make one with `cellctl record`)") from None
        except (OSError, json.JSONDecodeError) as exc:
            raise RecordingError(f"{mpath}: unreadable manifest ({exc})") from None
        version = manifest.get("format_version") if isinstance(manifest, dict) else None
        if not isinstance(version, int):
            raise RecordingError(f"{mpath}: format_version missing or not an integer")
        if version > RECORDING_FORMAT_VERSION:
            raise RecordingError(f"{mpath}: recording format_version {version} is newer than this cellctl "
                                 f"reads ({RECORDING_FORMAT_VERSION}); upgrade cellctl to replay it")
        self.manifest: dict[str, Any] = manifest
        self.frames = self._read_frames()
        self.states = self._read_states()

    def _read_frames(self) -> list[FrameEntry]:
        out = []
        try:
            with (self.root / "frames.csv").open(newline="") as f:
                for row in csv.DictReader(f):
                    out.append(FrameEntry(row["camera_id"], int(row["frame_id"]), float(row["timestamp_s"]),
                                          self.root / row["file"]))
        except (OSError, KeyError, ValueError) as exc:
            raise RecordingError(f"{self.root / 'frames.csv'}: malformed ({exc})") from None
        return out

    def _read_states(self) -> list[tuple[str, float, NDArray[np.float64], NDArray[np.float64]]]:
        out = []
        try:
            with (self.root / "robot_states.csv").open(newline="") as f:
                for row in csv.DictReader(f):
                    pose = np.array([float(row[k]) for k in ("x", "y", "z", "rx", "ry", "rz")])
                    joints = np.array([float(row[f"j{i}"]) for i in range(6)])
                    out.append((row["robot_id"], float(row["timestamp_s"]), pose, joints))
        except (OSError, KeyError, ValueError) as exc:
            raise RecordingError(f"{self.root / 'robot_states.csv'}: malformed ({exc})") from None
        return out

    def camera_frames(self, camera_id: str | None) -> list[FrameEntry]:
        ids = sorted({f.camera_id for f in self.frames})
        cid = camera_id if camera_id is not None else (ids[0] if ids else None)
        frames = [f for f in self.frames if f.camera_id == cid]
        if not frames:
            raise RecordingError(f"{self.root}: no frames of camera {cid!r}; recorded cameras: {ids}")
        return frames

    def robot_states(self, robot_id: str | None) -> list[RobotState]:
        ids = sorted({s[0] for s in self.states})
        rid = robot_id if robot_id is not None else (ids[0] if ids else None)
        states = [RobotState(ur_pose_to_transform(p), j, t) for r, t, p, j in self.states if r == rid]
        if not states:
            raise RecordingError(f"{self.root}: no states of robot {rid!r}; recorded robots: {ids}")
        return states
