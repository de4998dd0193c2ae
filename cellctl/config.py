"""``cell.yaml``: the cell's devices, motion limits, tokens and store (pydantic models); its listeners
(``http:``, ``plc:``) are in :mod:`cellctl.config_listeners`.

Every device names its adapter with ``kind:`` and gives that adapter's own ``settings:``, which
are validated by the adapter's ``Settings`` model. Unknown keys, wrong types and out-of-range
values are refused at start-up with the file, the key path and what is expected.
"""

from __future__ import annotations

import math
import re
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, Field, PrivateAttr, ValidationError, field_validator, model_validator

from calibration.io import read_text, yaml_error_text
from cellctl.config_listeners import HttpConfig, PlcConfig
from cellctl.drift.config import DriftConfig
from cellctl.errors import CellctlError
from cellctl.errors_format import format_validation_errors
from cellctl.strict_types import ClosedModel
from drivers.base import MotionLimits
from drivers.registry import Category, UnknownAdapter, adapter_class
from drivers.yaml_text import load_yaml

CONFIG_FORMAT_VERSION = 1
Role = Literal["viewer", "operator", "engineer"]
ROLE_RANK: dict[str, int] = {"viewer": 0, "operator": 1, "engineer": 2}


class ConfigError(CellctlError, ValueError):
    """cell.yaml is malformed; the message names the file, the key path and what is expected."""


class TokenConfig(ClosedModel):
    name: str = Field(min_length=1)
    role: Role
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    """SHA-256 of the token (hex); the token itself is never stored."""


class AuthConfig(ClosedModel):
    tokens: list[TokenConfig] = []


class StoreConfig(ClosedModel):
    url: str | None = None  # e.g. postgresql+psycopg://user@127.0.0.1:5432/cellctl; default: SQLite at path
    path: str | None = None
    """SQLite file; default: ``$XDG_DATA_HOME/cellctl/<cell_id>.db`` (``~/.local/share``)."""
    backup_dir: str | None = None
    """Folder of ``cellctl store backup`` without ``--out`` (and of ``restore --latest``); default:
    ``<data dir>/backups``. Better on another disk than the store's."""


class Envelope(ClosedModel):
    """Workspace box of the tool position in the robot base frame, millimetres."""

    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]

    @model_validator(mode="after")
    def _ordered(self) -> Envelope:
        for name in ("x_mm", "y_mm", "z_mm"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"{name} must be [low, high] with low < high, got [{lo}, {hi}]")
        return self


class DeviceConfig(ClosedModel):
    kind: str
    settings: dict[str, Any] = {}


POSE_NAME = re.compile(r"[A-Za-z0-9_.-]{1,40}")


class CameraConfig(DeviceConfig):
    pass


class RobotConfig(DeviceConfig):
    envelope: Envelope
    max_linear_speed_m_s: float = Field(0.25, gt=0, le=5.0)
    max_joint_speed_rad_s: float = Field(1.0, gt=0, le=6.3)
    tool_down_cone_deg: float | None = Field(60.0, gt=0, le=180)
    """Largest angle of the tool's z axis from straight down (deg); null: orientation not checked."""
    max_move_duration_s: float = Field(60.0, gt=0, le=3600)
    """A move that would take longer at its speed is refused (s)."""
    poses: dict[str, list[float]] = {}
    """Named tool poses (home, capture poses): ``name: [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad]``, UR's
    form in the base frame (metres, rotation vector in radians); ``POST /robots/{id}/move
    {"named_pose": name}`` goes there. Each must lie in the envelope and the tool cone."""

    @model_validator(mode="after")
    def _poses_inside(self) -> RobotConfig:
        from calibration.geometry import ur_pose_to_transform
        from drivers.base import MotionRejected

        for name, pose in self.poses.items():
            if not POSE_NAME.fullmatch(name):
                raise ValueError(f"poses.{name}: a pose name is 1-40 letters, digits, '_', '-' or '.'")
            if len(pose) != 6:
                raise ValueError(f"poses.{name}: a pose is 6 numbers [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad] "
                                 f"(UR form: metres, rotation vector in radians), got {len(pose)}")
            if not all(math.isfinite(v) for v in pose):
                raise ValueError(f"poses.{name}: every number must be finite")
            if max(abs(v) for v in pose[:3]) > 100.0 or math.hypot(*pose[3:]) > 2 * math.pi + 1e-6:
                raise ValueError(f"poses.{name}: {list(pose)} is not a UR pose [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad] "
                                 "(metres, and a rotation vector of at most one turn in radians)")
            try:
                self.limits().check_pose(ur_pose_to_transform(pose))
            except MotionRejected as exc:
                raise ValueError(f"poses.{name}: {exc}") from None
        return self

    def limits(self) -> MotionLimits:
        e = self.envelope
        return MotionLimits(e.x_mm, e.y_mm, e.z_mm, self.max_linear_speed_m_s, self.max_joint_speed_rad_s,
                            tool_down_cone_deg=self.tool_down_cone_deg, max_move_duration_s=self.max_move_duration_s)


class IOConfig(DeviceConfig):
    pass


class ConveyorConfig(DeviceConfig):
    """A belt's encoder (docs/conveyor.md)."""


class CalibrationDefaults(ClosedModel):
    """Defaults of the calibration routines (each request may override them)."""

    camera: str = "cam0"
    robot: str = "robot0"
    target: str = "plate"
    setup: Literal["eye-in-hand", "eye-to-hand"] = "eye-in-hand"
    model: Literal["opencv5", "opencv8", "division"] = "opencv5"
    speed_m_s: float = Field(0.1, gt=0, le=2.0)
    verify_tolerance_px: float = Field(1.0, gt=0)
    verify_tolerance_mm: float = Field(0.5, gt=0)


class ProductionConfig(ClosedModel):
    """Production runs (docs/production.md): where the frames of failed cycles are kept, and how many."""

    failure_frames_dir: str | None = None
    """Folder of the kept frames of failed cycles; default: ``<data dir>/production/<cell_id>/failures``."""
    failure_frames_max_count: int = Field(500, ge=0, le=1_000_000)
    """Kept failure frames over all runs; beyond it the oldest are deleted (0: keep none)."""
    failure_frames_max_mb: float = Field(1000.0, ge=0, le=1_000_000)
    """Their total size on disk, MB (10^6 bytes); beyond it the oldest are deleted."""


class CellConfig(ClosedModel):
    format_version: int = CONFIG_FORMAT_VERSION
    cell_id: str = Field("cell", pattern=r"^[A-Za-z0-9_.-]+$")
    http: HttpConfig = HttpConfig()
    auth: AuthConfig = AuthConfig()
    store: StoreConfig = StoreConfig()
    cameras: dict[str, CameraConfig] = {}
    robots: dict[str, RobotConfig] = {}
    io: dict[str, IOConfig] = {}
    conveyors: dict[str, ConveyorConfig] = {}
    """Belts whose encoder the cell reads (conveyor tracking, docs/conveyor.md)."""
    targets: dict[str, dict[str, Any]] = {}
    """Named calibration targets (the YAML of docs/targets.md)."""
    calibration: CalibrationDefaults = CalibrationDefaults()
    plc: PlcConfig = PlcConfig()
    """PLC-native front ends (Modbus TCP, OPC UA); both off unless enabled."""
    production: ProductionConfig = ProductionConfig()
    drift: DriftConfig | None = None
    """Drift checks against fixed fiducials (docs/drift.md); none when absent."""
    _source: Path | None = PrivateAttr(None)
    """The file this config was read from (None: built in); the service re-reads its tokens on change."""

    @property
    def source(self) -> Path | None:
        return self._source

    @field_validator("targets")
    @classmethod
    def _targets(cls, v: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
        from calibration.targets import target_from_dict

        for name, desc in v.items():
            target_from_dict(desc, f"targets.{name}")
        return v

    @model_validator(mode="after")
    def _drift_target(self) -> CellConfig:
        target = None if self.drift is None else self.drift.fiducials.target
        if target is not None and target not in self.targets:
            raise ValueError(f"drift.fiducials.target {target!r} is not a target of this cell (targets: "
                             f"{', '.join(sorted(self.targets)) or 'none'}); name one of them")
        return self

    @field_validator("format_version")
    @classmethod
    def _version(cls, v: int) -> int:
        if v > CONFIG_FORMAT_VERSION:
            raise ValueError(f"format_version {v} is newer than this cellctl supports ({CONFIG_FORMAT_VERSION}); "
                             "upgrade cellctl")
        return v

    def validated_settings(self, category: Category, device_id: str) -> BaseModel:
        """The device's settings parsed by its adapter's ``Settings`` model."""
        table: dict[str, dict[str, DeviceConfig]] = {
            "camera": dict(self.cameras), "robot": dict(self.robots), "io": dict(self.io),
            "conveyor": dict(self.conveyors)}
        dev = table[category][device_id]
        settings_model: type[BaseModel] = adapter_class(category, dev.kind).Settings  # type: ignore[attr-defined]
        return settings_model.model_validate(dev.settings)


_SECTIONS: dict[str, Category] = {"cameras": "camera", "robots": "robot", "io": "io", "conveyors": "conveyor"}


def parse_config(data: Any, source: str = "cell.yaml") -> CellConfig:
    """Validate a cell configuration mapping, including each adapter's settings."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the top level must be a mapping of sections "
                          "(cameras, robots, io, http, auth, store)")
    try:
        cfg = CellConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {format_validation_errors(exc, model=CellConfig)}") from None
    for section, category in _SECTIONS.items():
        for device_id in getattr(cfg, section):
            path = f"{section}.{device_id}"
            try:
                cfg.validated_settings(category, device_id)
            except UnknownAdapter as exc:
                raise ConfigError(f"{source}: {path}.kind: {exc}") from None
            except ImportError as exc:
                raise ConfigError(f"{source}: {path}.kind: the adapter cannot be loaded ({exc})") from None
            except ValidationError as exc:
                settings = adapter_class(category, getattr(cfg, section)[device_id].kind).Settings  # type: ignore[attr-defined]
                text = format_validation_errors(exc, prefix=path + ".settings", model=settings)
                raise ConfigError(f"{source}: {text}") from None
    return cfg


def load_config(path: str | Path | None) -> CellConfig:
    """Read ``cell.yaml``; ``None`` gives the built-in virtual cell."""
    if path is None:
        return parse_config(load_yaml(default_config_text()), "built-in virtual cell")
    p = Path(path)
    text = read_text(p, "the config file", ConfigError)
    try:
        data = load_yaml(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({yaml_error_text(exc)})") from None
    cfg = parse_config(data, str(p))
    cfg._source = p.resolve()
    return cfg


def default_config_text() -> str:
    """The built-in virtual cell's ``cell.yaml`` (what ``cellctl config default`` prints)."""
    return resources.files("cellctl").joinpath("data/virtual-cell.yaml").read_text()


SIM_KINDS = frozenset({"sim", "sim_gripper"})


def sim_settings(config: CellConfig) -> dict[str, Any] | None:
    """The settings (scene, seed) of the cell's first simulated device, None when it has none (the
    virtual cell's truth: ``GET /sim/truth`` and ``cellctl sim truth``)."""
    for dev in [*config.cameras.values(), *config.robots.values(), *config.io.values()]:
        if dev.kind in SIM_KINDS:
            return dict(dev.settings)
    return None
