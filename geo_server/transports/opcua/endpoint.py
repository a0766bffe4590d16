"""An OPC UA endpoint's address (README *OPC UA*), without importing the server: the
parser checks it for every `geo-server run`."""

from __future__ import annotations

from urllib.parse import urlsplit

#: The IANA port of OPC UA over TCP.
DEFAULT_PORT = 4840


def parse_endpoint(url: str) -> tuple[str, int]:
    """(host, port) of `opc.tcp://HOST:PORT`; ValueError for anything else."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError:
        parts, port = None, None
    if parts is None or parts.scheme != "opc.tcp" or not parts.hostname:
        raise ValueError(f"an OPC UA endpoint is opc.tcp://HOST:PORT, not {url[:100]!r}")
    return parts.hostname, DEFAULT_PORT if port is None else port
