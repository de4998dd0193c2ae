"""The service's listeners in ``cell.yaml``: ``http:`` (the REST service) and ``plc:`` (the PLC front
ends: Modbus TCP, OPC UA, EtherNet/IP, the robot socket), each a host and port with its limits.

A listener beyond loopback is open to its network: HTTPS needs ``tls_cert`` and ``tls_key`` together;
OPC UA's ``basic256sha256`` needs its certificate, key and trusted clients (:data:`TRUST_HINT`); a PLC
server that authenticates no client beyond loopback needs the integrator's zone decision
(``plc.insecure_plc_network``, :meth:`PlcConfig.zone_problem`). Part of :class:`cellctl.config.CellConfig`.
"""

from __future__ import annotations

import ipaddress
from typing import Literal

from pydantic import Field, model_validator

from cellctl.strict_types import ClosedModel


class HttpConfig(ClosedModel):
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


class ModbusServerConfig(ClosedModel):
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


class EthernetIpServerConfig(ClosedModel):
    """The EtherNet/IP (CIP explicit messaging) tag server for Rockwell PLCs (docs/plc-ethernet-ip.md).
    EtherNet/IP has no authentication: bind it to the PLC's network only."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(44818, ge=1, le=65535)
    idle_timeout_s: float = Field(60.0, gt=0, le=86400)
    """A connection that sends nothing for this long is closed."""
    max_clients: int = Field(16, ge=1, le=1000)
    """Connections at once; more are closed at once."""


class RobotSocketConfig(ClosedModel):
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


class OpcUaServerConfig(ClosedModel):
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


class PlcConfig(ClosedModel):
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
