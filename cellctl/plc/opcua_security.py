"""The OPC UA server's secure channel (``plc.opcua.security``): which client certificates it trusts.

``none`` — the lab, one endpoint without security; ``basic256sha256`` — one Basic256Sha256
SignAndEncrypt endpoint with the server certificate and key from the config, and only clients whose
certificate is in ``trusted_client_certs`` may connect. The server refuses to start without that
directory or with one that holds no certificate: without a trust list asyncua accepts any
self-signed client. Every refusal is one line saying how to fix it (docs/plc-opcua.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from asyncua import Server, ua

from cellctl.config_listeners import TRUST_HINT, OpcUaServerConfig

CERT_SUFFIXES = (".der", ".pem", ".crt", ".cer")
"""The file suffixes taken for client certificates in the trusted directory."""


def trusted_dir_problem(folder: str | None) -> str | None:
    """Why ``folder`` cannot serve as the trust list of client certificates (None: it can)."""
    if folder is None:
        return f"plc.opcua: {TRUST_HINT}"
    trusted = Path(folder)
    if not trusted.is_dir():
        return f"plc.opcua.trusted_client_certs {trusted} is not a directory; {TRUST_HINT}"
    if not any(f.suffix.lower() in CERT_SUFFIXES for f in trusted.iterdir() if f.is_file()):
        return (f"plc.opcua.trusted_client_certs {trusted} holds no certificate, so no client could connect; "
                f"{TRUST_HINT}")
    return None


def security_problem(config: OpcUaServerConfig) -> str | None:
    """What keeps the configured OPC UA security from starting (files missing, nobody trusted); None: fine."""
    if config.security == "none":
        return None
    for what, path in (("certificate", config.cert), ("key", config.key)):
        if path is None or not Path(path).is_file():
            return f"plc.opcua: the server {what} {path} is missing; create it (docs/plc-opcua.md)"
    return trusted_dir_problem(config.trusted_client_certs)


async def trusted_clients_validator(folder: str | None) -> Any:
    """A validator that lets only the client certificates in ``folder`` connect (asyncua's TrustStore)."""
    from asyncua.crypto.truststore import TrustStore
    from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

    problem = trusted_dir_problem(folder)
    if problem or folder is None:
        raise OSError(problem)
    trusted = Path(folder)
    store = TrustStore([trusted], [])
    try:
        await store.load()
    except ValueError as exc:
        raise OSError(f"plc.opcua.trusted_client_certs {trusted}: a file there is not a certificate "
                      f"({exc}); keep only client certificates (.der/.pem) there") from None
    opts = (CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.TRUSTED
            | CertificateValidatorOptions.PEER_CLIENT)
    return CertificateValidator(opts, store)


async def secure(server: Server, config: OpcUaServerConfig) -> None:
    """Basic256Sha256 SignAndEncrypt, and only clients whose certificate is in the trusted directory.

    Refuses to start (``OSError`` with how to fix it) without a trusted directory or with one
    that holds no certificate: without a trust list asyncua accepts any self-signed client.
    """
    problem = security_problem(config)
    if problem or config.cert is None or config.key is None:
        raise OSError(problem or "plc.opcua: security basic256sha256 needs the server certificate and key")
    await server.load_certificate(config.cert)
    await server.load_private_key(config.key)
    server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
    server.set_certificate_validator(await trusted_clients_validator(config.trusted_client_certs))
