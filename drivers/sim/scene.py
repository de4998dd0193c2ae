"""The virtual cell's scene file: camera, mount, robot, targets and parts (versioned YAML).

Poses in the file are written in the Universal Robots form ``[x, y, z, rx, ry, rz]`` (metres and
a rotation vector in radians), under keys that name the transform (``T_tool_cam``,
``T_base_target``...). Part outlines are millimetres in the part's own frame; a part lies on the
table at ``x_mm, y_mm`` (base frame) rotated by ``angle_deg`` about the base z axis.

The parser is strict: unknown keys and a newer ``format_version`` are refused with the key path.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from calibration.camera_model import CameraModel
from calibration.geometry import ur_pose_to_transform
from calibration.targets import PlanarTarget, target_from_dict
from drivers.errors import DriverInputError
from drivers.sim.conveyor import BeltSpec
from drivers.sim.production_spec import ProductionSpec
from drivers.yaml_text import load_yaml

SCENE_FORMAT_VERSION = 1
BUILTIN_SCENE = Path(__file__).with_name("scenes") / "virtual-cell.yaml"
BUILTIN_SCENES = {"production": Path(__file__).with_name("scenes") / "production.yaml",
                  "fixed-camera": Path(__file__).with_name("scenes") / "virtual-cell-fixed-camera.yaml",
                  "conveyor": Path(__file__).with_name("scenes") / "conveyor.yaml"}
"""Scenes a sim device's ``scene`` setting may name instead of giving a path."""


def resolve_scene(path: str | Path | None) -> Path | None:
    """A scene setting as a path: a built-in scene's name (``production``) or the path itself."""
    if path is None or str(path) == "":
        return None
    return BUILTIN_SCENES.get(str(path), Path(path))


class SceneError(DriverInputError):
    """A scene file is malformed or of a newer format."""


URPose = Annotated[list[float], Field(min_length=6, max_length=6)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ImagingSpec(_Strict):
    """How the virtual camera turns what it sees into grey levels (DN, 0..255), defects included.

    Every defect is off by default. They apply in the order light meets them
    (``drivers.sim.imaging.sensor``, where the formulas are):

    - ``light_gradient``: brightness ramp from the image's left to its right edge;
    - ``vignetting``: fraction of the light lost at the image corners (cos^4 law of the distance
      from the image centre): 0.3 leaves the corners 70 % of the centre's brightness;
    - blur: ``blur_sigma_px`` (Gaussian) and defocus in quadrature: with ``focus_distance_m``
      (camera z of the plane in focus) set, a pixel seeing depth ``z`` is blurred by
      ``defocus_sigma_px_per_diopter * |1/z - 1/focus_distance_m|`` px (a thin lens's blur circle);
    - ``motion_blur_px``: uniform motion of that length (px) along ``motion_blur_angle_deg``
      (image frame: 0 is +u, 90 is +v, down);
    - noise: ``noise_sigma`` (Gaussian, DN), shot noise of ``grey / gain_dn_per_e`` electrons
      (Poisson; ``gain_dn_per_e`` 0 is off) and ``read_noise_dn`` (Gaussian): variance
      ``gain * grey + read^2``;
    - ``gamma``: encoding ``255 (grey / 255)^(1 / gamma)`` (1: linear);
    - ``jpeg_quality``: JPEG compression at that quality (1..100; none when absent).

    Random draws follow the scene's ``seed`` (or the camera's ``seed`` setting): one seed, one
    sequence of frames.
    """

    black_level: float = Field(25.0, ge=0, le=255)
    white_level: float = Field(225.0, ge=0, le=255)
    background: float = Field(0.45, ge=0, le=1)
    blur_sigma_px: float = Field(0.0, ge=0, le=10)
    noise_sigma: float = Field(0.0, ge=0, le=50)
    """Gaussian noise, grey levels (1-sigma)."""
    light_gradient: float = Field(0.0, ge=-1, le=1)
    supersample: int = Field(6, ge=1, le=16)
    vignetting: float = Field(0.0, ge=0, lt=1)
    """Fraction of the light lost at the image corners."""
    focus_distance_m: float | None = Field(None, gt=0, le=100)
    """Camera z (m) of the plane in focus; absent: no defocus."""
    defocus_sigma_px_per_diopter: float = Field(0.0, ge=0, le=50)
    """Defocus blur sigma (px) per diopter (1/m) of distance from the focus plane."""
    motion_blur_px: float = Field(0.0, ge=0, le=100)
    motion_blur_angle_deg: float = Field(0.0, ge=-360, le=360)
    gain_dn_per_e: float = Field(0.0, ge=0, le=10)
    """Grey levels per electron (shot noise); 0: no shot noise."""
    read_noise_dn: float = Field(0.0, ge=0, le=50)
    """Read noise, grey levels (1-sigma)."""
    gamma: float = Field(1.0, ge=0.2, le=5)
    jpeg_quality: int | None = Field(None, ge=1, le=100)


class CameraSpec(_Strict):
    model: Literal["opencv5", "opencv8", "division"]
    width: int = Field(gt=0, le=8192)
    height: int = Field(gt=0, le=8192)
    K: list[list[float]]
    dist: list[float]
    mount: Literal["tool", "base"]
    T_tool_cam: URPose | None = None
    T_base_cam: URPose | None = None
    imaging: ImagingSpec = ImagingSpec()

    @model_validator(mode="after")
    def _mount_pose(self) -> CameraSpec:
        if self.mount == "tool" and self.T_tool_cam is None:
            raise ValueError("mount: tool needs T_tool_cam")
        if self.mount == "base" and self.T_base_cam is None:
            raise ValueError("mount: base needs T_base_cam")
        return self

    def camera_model(self) -> CameraModel:
        return CameraModel(self.model, self.width, self.height, np.asarray(self.K), np.asarray(self.dist))


class KinematicErrorSpec(_Strict):
    """The physical arm differs from its controller's nominal model (seeded, deterministic)."""

    seed: int = Field(0, ge=0)
    link_sigma_mm: float = Field(0.5, ge=0, le=20)
    """1-sigma error of each DH length (d, a), mm."""
    joint_offset_sigma_deg: float = Field(0.05, ge=0, le=5)
    """1-sigma error of each joint's zero offset, degrees."""


class RobotFaultSpec(_Strict):
    """Faults the virtual robot plays, like a real controller (counted in moves since connect)."""

    protective_stop_after_moves: int | None = Field(None, ge=0)
    """The N+1-th move ends halfway in a protective stop (the move raises; unlock to continue)."""
    drop_after_moves: int | None = Field(None, ge=0)
    """After N moves the controller drops off the network (state and moves raise DeviceUnavailable)."""
    speed_slider: float = Field(1.0, gt=0, le=1)
    """The operator's speed slider (a real controller's pendant, 0..1): every move takes 1/slider times as long
    as the robot's own timing (``SimRobot.linear_move_s``) says; a planner's estimate is then optimistic."""


class RobotSpec(_Strict):
    home: URPose
    """Initial ``T_base_tool`` (UR form)."""
    repeatability_mm: float = Field(0.02, ge=0, le=10)
    """1-sigma position error of the reported pose against the true one, per axis."""
    repeatability_deg: float = Field(0.005, ge=0, le=5)
    """1-sigma rotation error of the reported pose (about a random axis)."""
    motion_time_scale: float = Field(1.0, ge=0, le=10)
    """Simulated moves take distance/speed times this: 1 is real time (the default), 0 instantaneous
    (for tests and benches that need speed; a sim robot's ``motion_time_scale`` setting overrides it)."""
    tool_turn_speed_deg_s: float = Field(90.0, gt=0, le=1000)
    """How fast the tool turns (deg/s): a move takes the longer of its distance at the commanded
    speed and its rotation at this rate, so a pure turn takes time too (and a Stop meets it
    under way), as on a real arm with its orientation speed limit."""
    kinematic_error: KinematicErrorSpec | None = None
    """Pose-dependent error of the arm (perturbed UR5e link lengths and joint offsets); off when absent."""
    faults: RobotFaultSpec = Field(default_factory=lambda: RobotFaultSpec())


class TargetSpec(_Strict):
    name: str
    target: dict[str, Any]
    attached_to: Literal["base", "tool", "belt"] = "base"
    pose: URPose
    """``T_base_target`` (attached to base) or ``T_tool_target`` (attached to tool); on the belt: its
    ``T_base_target`` at the belt's start (it rides the belt, a loop: it comes round again)."""

    @field_validator("target")
    @classmethod
    def _target(cls, v: dict[str, Any]) -> dict[str, Any]:
        t = target_from_dict(v, "target")
        if not hasattr(t, "reflectance"):
            raise ValueError("the virtual cell renders planar targets only")
        return v

    def parsed(self) -> PlanarTarget:
        t = target_from_dict(self.target, self.name)
        if not isinstance(t, PlanarTarget):
            raise SceneError(f"target {self.name}: the virtual cell renders planar targets only")
        return t


class PartSpec(_Strict):
    name: str
    outline_mm: list[list[float]] = Field(min_length=3)
    holes_mm: list[list[list[float]]] = []
    reflectance: float = Field(0.9, ge=0, le=1)
    x_mm: float
    y_mm: float
    angle_deg: float = 0.0

    @field_validator("outline_mm")
    @classmethod
    def _pairs(cls, v: list[list[float]]) -> list[list[float]]:
        if any(len(p) != 2 for p in v):
            raise ValueError("outline_mm must be a list of [x, y] pairs")
        return v


class ToolFeatureSpec(_Strict):
    """A feature the tool carries, seen by a fixed camera: a bright disk in a dark ring.

    The gripper's centre mark of a jog-to-mark cell (a lit LED or a retro-reflective dot on a dark
    gripper body): a disk of ``diameter_mm`` at ``offset_mm`` from the flange, in the flange (tool)
    frame, lying in the tool's x/y plane, drawn at ``grey_dn`` (the sensor saturates on it by
    default) inside a ring of ``ring_diameter_mm`` at ``ring_grey_dn``. The sim camera draws it over
    the rendered frame, projected through the camera model from the tool's true pose
    (``drivers/camera/sim.py``); the tool itself is not drawn.
    """

    offset_mm: tuple[float, float, float]
    """The disk's centre in the flange frame, mm (x, y, z; z along the tool axis)."""
    diameter_mm: float = Field(8.0, gt=0, le=200)
    ring_diameter_mm: float = Field(16.0, ge=0, le=400)
    """Outer diameter of the dark ring around the disk, mm (0: no ring)."""
    grey_dn: float = Field(255.0, ge=0, le=255)
    ring_grey_dn: float = Field(20.0, ge=0, le=255)


class FiducialSpec(_Strict):
    """A mark fixed on the table for drift checks: a bright disk of ``diameter_mm`` centred at
    (``x_mm``, ``y_mm``, ``z_mm``) in the robot base frame, lying level (cellctl's ``drift.fiducials``)."""

    x_mm: float
    y_mm: float
    z_mm: float = 0.0
    diameter_mm: float = Field(4.0, gt=0, le=100)
    reflectance: float = Field(0.95, ge=0, le=1)


class TableSpec(_Strict):
    z_m: float = 0.0
    reflectance: float = Field(0.35, ge=0, le=1)
    size_m: tuple[float, float] = (2.0, 2.0)


class SceneSpec(_Strict):
    format_version: int
    name: str = "virtual cell"
    seed: int = 0
    camera: CameraSpec
    robot: RobotSpec
    table: TableSpec = TableSpec()
    targets: list[TargetSpec] = []
    parts: list[PartSpec] = []
    tool_feature: ToolFeatureSpec | None = None
    """A feature on the tool for a fixed camera to see (the tool centre); none when absent."""
    fiducials: list[FiducialSpec] = []
    """Marks fixed on the table (drift checks); none when absent."""
    production: ProductionSpec | None = None
    """Parts as objects a sim gripper picks and places (``drivers.sim.production``); none when absent."""
    conveyor: BeltSpec | None = None
    """A belt carrying the production parts along base +x (``drivers.sim.conveyor``); none when absent."""

    def T_tool_cam(self) -> np.ndarray | None:
        c = self.camera
        return ur_pose_to_transform(c.T_tool_cam) if c.T_tool_cam is not None else None

    def T_base_cam_fixed(self) -> np.ndarray | None:
        c = self.camera
        return ur_pose_to_transform(c.T_base_cam) if c.T_base_cam is not None else None


def scene_from_dict(data: Any, source: str = "scene") -> SceneSpec:
    """Validate a scene mapping; errors name the source, the key path and what is expected."""
    if not isinstance(data, dict):
        raise SceneError(f"{source}: a scene file must be a mapping")
    version = data.get("format_version")
    if not isinstance(version, int):
        raise SceneError(f"{source}: format_version must be an integer (this cellctl reads {SCENE_FORMAT_VERSION})")
    if version > SCENE_FORMAT_VERSION:
        raise SceneError(f"{source}: scene format_version {version} is newer than this cellctl supports "
                         f"({SCENE_FORMAT_VERSION}); upgrade cellctl")
    try:
        return SceneSpec.model_validate(data)
    except ValidationError as exc:
        raise SceneError(f"{source}: {format_validation_error(exc)}") from None


def load_scene(path: str | Path | None = None) -> SceneSpec:
    """Read a scene file (default: the built-in virtual cell)."""
    resolved = resolve_scene(path)
    p = resolved if resolved is not None else BUILTIN_SCENE
    try:
        data = load_yaml(p.read_text())
    except OSError as exc:
        raise SceneError(f"{p}: cannot read scene file ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        raise SceneError(f"{p}: not valid YAML ({exc})") from exc
    return scene_from_dict(data, str(p))


def format_validation_error(exc: ValidationError) -> str:
    """pydantic errors as ``key.path: message`` lines joined by '; '."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "(top level)"
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        parts.append(f"{loc}: {msg}")
    return "; ".join(parts)
