"""The OPC UA server's self-signed certificate (docs/security.md *OPC UA*).

Made on first start and kept: clients that trusted it once go on trusting it (the
folder: `geo_server.transports.opcua.plug.cert_folder`). The key is written for its owner only
(0600), both files atomically (a crash leaves no half file).
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import socket
from pathlib import Path

CERT_FILE = "server_cert.der"
KEY_FILE = "server_key.pem"
#: Ten years: a test tool's certificate should not expire under a CI pipeline.
DAYS = 3650


def ensure_certificate(folder: Path, app_uri: str, host: str) -> tuple[Path, Path]:
    """(certificate, key) in `folder`, made now when either is missing."""
    cert, key = folder / CERT_FILE, folder / KEY_FILE
    if cert.is_file() and key.is_file():
        return cert, key
    from asyncua.crypto import cert_gen
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    folder.mkdir(parents=True, exist_ok=True)
    private = cert_gen.generate_private_key()
    names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(app_uri)]
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        names.append(x509.DNSName(host))
    else:
        names.append(x509.IPAddress(ip))
        if ip.is_unspecified:  # every address (a container): the loopback ones are among them
            names += [x509.IPAddress(ipaddress.ip_address(a)) for a in ("127.0.0.1", "::1")]
    # clients compare the host of the endpoint URL they were given with these names
    for name in dict.fromkeys(("localhost", socket.gethostname())):
        if name and name != host:
            names.append(x509.DNSName(name))
    certificate = cert_gen.generate_self_signed_app_certificate(
        private,
        app_uri,
        {"organizationName": "geo-server"},
        names,
        extended=[ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
        days=DAYS,
    )
    _write(key, cert_gen.dump_private_key_as_pem(private), 0o600)
    _write(cert, certificate.public_bytes(encoding=Encoding.DER), 0o644)
    return cert, key


def _write(path: Path, data: bytes, mode: int) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


__all__ = ["CERT_FILE", "KEY_FILE", "ensure_certificate"]
