"""``cell.yaml``: the cell's devices, motion limits, HTTP binding and tokens (pydantic models).

Every device names its adapter with ``kind:`` and gives that adapter's own ``settings:``, which
are validated by the adapter's ``Settings`` model. Unknown keys, wrong types and out-of-range
values are refused at start-up with the file, the key path and what is expected.
"""

from __future__ import annotations

import ipaddress
import math
import re
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from calibration.io import read_text, yaml_error_text
from cellctl.drift.config import DriftConfig
from cellctl.errors import CellctlError
from cellctl.errors_format import format_validation_errors
from drivers.base import MotionLimits
from drivers.registry import Category, UnknownAdapter, adapter_class
from drivers.yaml_text import load_yaml

CONFIG_FORMAT_VERSION = 1
Role = Literal["viewer", "operator", "engineer"]
ROLE_RANK: dict[str, int] = {"viewer": 0, "operator": 1, "engineer": 2}


class ConfigError(CellctlError, ValueError):
    """cell.yaml is malformed; the message names the file, the key path and what is expected."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class HttpConfig(_Strict):
    host: str = "127.0.0.1"
    port: int = Field(8080, ge=1, le=65535)
    tls_cert: str | None = None
    """PEM certificate (chain) for HTTPS, e.g. /etc/cellctl/tls/cert.pem; None: plain HTTP."""
    tls_key: str | None = None
    """PEM private key of ``tls_cert``, e.g. /etc/cellctl/tls/key.pem (readable by the service user only)."""
    max_body_mb: float = Field(8.0, gt=0, le=1024)
    """Largest request body (MB, 10^6 bytes); a larger one is refused with 413 before it is parsed or authorised."""
    max_event_streams: int = Field(16, ge=1, le=1000)
    """Open event streams (``/jobs/{id}/events``) over all callers; more are refused with 429."""
    max_event_streams_per_token: int = Field(4, ge=1, le=1000)
    """Open event streams per token; more are refused with 429."""
    body_timeout_s: float = Field(5.0, gt=0, le=600)
    """A request body must arrive whole within this many seconds of its headers; a slower one is refused with 408."""
    header_timeout_s: float = Field(10.0, gt=0, le=600)
    """A request's headers must arrive whole within this many seconds of the connection (or of the previous
    answer on a kept-alive connection); a slower connection is closed (``cellctl.api.connections``)."""
    max_connections: int = Field(4096, ge=16, le=1_000_000)
    """Open HTTP connections at most; the service lowers it further to keep descriptors in reserve
    (``cellctl.api.connections.FD_RESERVE`` below the open-files limit). Over it, the oldest connection
    that is not being served is closed to admit the new one, so Stop always gets in."""
    max_connections_per_address: int = Field(256, ge=1, le=1_000_000)
    """Open HTTP connections per client address at most (over it: that address's oldest idle one is closed)."""

    @model_validator(mode="after")
    def _tls_pair(self) -> HttpConfig:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together: give both (HTTPS) or neither (plain HTTP)")
        return self

    def is_loopback(self) -> bool:
        return is_loopback_host(self.host)


def is_loopback_host(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (127.0.0.0/8, ::1); a host name or 0.0.0.0 is not."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class TokenConfig(_Strict):
    name: str = Field(min_length=1)
    role: Role
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    """SHA-256 of the token (hex); the token itself is never stored."""


class AuthConfig(_Strict):
    tokens: list[TokenConfig] = []


class StoreConfig(_Strict):
    url: str | None = None  # e.g. postgresql+psycopg://user@127.0.0.1:5432/cellctl; default: SQLite at path
    path: str | None = None
    """SQLite file; default: ``$XDG_DATA_HOME/cellctl/<cell_id>.db`` (``~/.local/share``)."""
    backup_dir: str | None = None
    """Folder of ``cellctl store backup`` without ``--out`` (and of ``restore --latest``); default:
    ``<data dir>/backups``. Better on another disk than the store's."""


class Envelope(_Strict):
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


class DeviceConfig(_Strict):
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


class CalibrationDefaults(_Strict):
    """Defaults of the calibration routines (each request may override them)."""

    camera: str = "cam0"
    robot: str = "robot0"
    target: str = "plate"
    setup: Literal["eye-in-hand", "eye-to-hand"] = "eye-in-hand"
    model: Literal["opencv5", "opencv8", "division"] = "opencv5"
    speed_m_s: float = Field(0.1, gt=0, le=2.0)
    verify_tolerance_px: float = Field(1.0, gt=0)
    verify_tolerance_mm: float = Field(0.5, gt=0)


class ModbusServerConfig(_Strict):
    """The Modbus TCP server for PLCs (register map: docs/plc-modbus.md). Modbus has no security:
    bind it to the PLC's network only."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(5020, ge=1, le=65535)
    unit_id: int = Field(1, ge=0, le=255)
    """Modbus unit (device) id the server answers to; 0 answers every unit id."""
    idle_timeout_s: float = Field(60.0, gt=0, le=86400)
    """A connection that sends nothing for this long is closed (a PLC polls far more often)."""
    max_connections_per_address: int = Field(16, ge=1, le=10000)
    """Connections at once from one client address; more are closed at once (a PLC needs one or two)."""
    max_connections: int = Field(64, ge=1, le=100000)
    """Connections at once in all; more are closed at once, so no client can use up the service's descriptors."""


class EthernetIpServerConfig(_Strict):
    """The EtherNet/IP (CIP explicit messaging) tag server for Rockwell PLCs (docs/plc-ethernet-ip.md).
    EtherNet/IP has no authentication: bind it to the PLC's network only."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(44818, ge=1, le=65535)
    idle_timeout_s: float = Field(60.0, gt=0, le=86400)
    """A connection that sends nothing for this long is closed."""
    max_clients: int = Field(16, ge=1, le=1000)
    """Connections at once; more are closed at once."""


class RobotSocketConfig(_Strict):
    """The robot socket: one ASCII line in, one out, for a robot program's TCP client (docs/robot-socket.md)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(5021, ge=1, le=65535)
    pose_format: Literal["ur", "abb", "fanuc", "kuka", "yaskawa"] = "ur"
    """The orientation's form in a PICK answer: the robot controller's own convention."""
    idle_timeout_s: float = Field(60.0, gt=0, le=86400)
    """A client that sends nothing for this long is closed."""
    max_clients: int = Field(4, ge=1, le=1000)
    """Clients at once; more are answered ERR and closed."""


TRUST_HINT = ("security basic256sha256 needs trusted_client_certs: a directory holding the certificate of "
              "each PLC/client allowed to connect (DER or PEM, e.g. /etc/cellctl/opcua/trusted/plc.der); copy the "
              "client's application certificate there and set plc.opcua.trusted_client_certs to that directory "
              "(docs/plc-opcua.md, 'Trusting a client')")


class OpcUaServerConfig(_Strict):
    """The OPC UA server for PLCs (address space: docs/plc-opcua.md)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(4840, ge=1, le=65535)
    security: Literal["none", "basic256sha256"] = "none"
    """none: the lab; basic256sha256: Basic256Sha256 SignAndEncrypt with ``cert``/``key`` (production)."""
    cert: str | None = None
    """Server application certificate (PEM or DER), e.g. /etc/cellctl/opcua/cert.pem."""
    key: str | None = None
    """Its private key (PEM), readable by the service user only."""
    trusted_client_certs: str | None = None
    """Directory of trusted client certificates (DER/PEM); required with basic256sha256 (only the
    clients whose certificate is there may connect)."""

    @model_validator(mode="after")
    def _certs(self) -> OpcUaServerConfig:
        if self.security == "basic256sha256" and (self.cert is None or self.key is None):
            raise ValueError("security basic256sha256 needs the server certificate and key: set cert and key")
        if self.security == "basic256sha256" and self.trusted_client_certs is None:
            # Without a trust list any self-signed client certificate would be accepted (and could call Pick).
            raise ValueError(TRUST_HINT)
        return self


class PlcConfig(_Strict):
    modbus: ModbusServerConfig = ModbusServerConfig()
    opcua: OpcUaServerConfig = OpcUaServerConfig()
    ethernet_ip: EthernetIpServerConfig = EthernetIpServerConfig()
    robot_socket: RobotSocketConfig = RobotSocketConfig()
    allow_motion: bool = False
    """Let a PLC start a pick that moves the robot (Modbus command 3, OPC UA ``PickAndMove``): an
    engineer-level act, off by default; the motion owner and the Stop latch apply as for REST."""
    insecure_plc_network: bool = False
    """The integrator's IEC 62443 zone decision: the PLC network is a zone of its own, and its conduit
    admits only the PLC. Needed to serve OPC UA with ``security: none``, or Modbus or EtherNet/IP with
    ``allow_motion``, on an address other than loopback (none authenticates the client); refused otherwise."""

    @model_validator(mode="after")
    def _zones(self) -> PlcConfig:
        problem = self.zone_problem()
        if problem:
            raise ValueError(problem)
        return self

    def zone_problem(self) -> str | None:
        """Why this PLC setup exposes an unauthenticated server beyond loopback without the zone decision."""
        if self.insecure_plc_network:
            return None
        zone = ("if the PLC network is a separate IEC 62443 zone whose conduit admits only the PLC, the integrator "
                "records that decision with plc.insecure_plc_network: true")
        if self.opcua.enabled and self.opcua.security == "none" and not is_loopback_host(self.opcua.host):
            return (f"plc.opcua.security none on {self.opcua.host} (not loopback): any client on that network "
                    "could call Pick without a certificate; use security basic256sha256 (docs/plc-opcua.md), "
                    f"or {zone}")
        if self.modbus.enabled and self.allow_motion and not is_loopback_host(self.modbus.host):
            return (f"plc.allow_motion with plc.modbus on {self.modbus.host} (not loopback): Modbus has no "
                    "authentication, so any client on that network could make the robot move; turn "
                    f"allow_motion off, or {zone} (docs/plc-modbus.md)")
        if self.ethernet_ip.enabled and self.allow_motion and not is_loopback_host(self.ethernet_ip.host):
            return (f"plc.allow_motion with plc.ethernet_ip on {self.ethernet_ip.host} (not loopback): EtherNet/IP "
                    "has no authentication, so any client on that network could make the robot move; turn "
                    f"allow_motion off, or {zone} (docs/plc-ethernet-ip.md)")
        return None


class ProductionConfig(_Strict):
    """Production runs (docs/production.md): where the frames of failed cycles are kept, and how many."""

    failure_frames_dir: str | None = None
    """Folder of the kept frames of failed cycles; default: ``<data dir>/production/<cell_id>/failures``."""
    failure_frames_max_count: int = Field(500, ge=0, le=1_000_000)
    """Kept failure frames over all runs; beyond it the oldest are deleted (0: keep none)."""
    failure_frames_max_mb: float = Field(1000.0, ge=0, le=1_000_000)
    """Their total size on disk, MB (10^6 bytes); beyond it the oldest are deleted."""


class CellConfig(_Strict):
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
