"""The OPC UA options of `geo-server run` (README *OPC UA*), without importing the
server: the parser is built for every command."""

from __future__ import annotations

import argparse
import os
from typing import Any
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


def check_args(args: argparse.Namespace) -> str | None:
    """What is wrong with the OPC UA options of `geo-server run`, or None."""
    if args.no_opcua:
        return None
    if (args.opcua_user is None) != (args.opcua_password is None):
        return "--opcua-user and --opcua-password go together"
    try:
        parse_endpoint(args.opcua_endpoint)
    except ValueError as exc:
        return str(exc)
    return None


def add_arguments(parser: Any) -> None:
    """The OPC UA options of `geo-server run`."""
    o = parser.add_argument_group("opcua (README *OPC UA*)")
    o.add_argument("--no-opcua", action="store_true", help="do not start the OPC UA server")
    o.add_argument(
        "--opcua-endpoint",
        default="opc.tcp://127.0.0.1:4840",
        metavar="URL",
        help="endpoint (default opc.tcp://127.0.0.1:4840)",
    )
    o.add_argument(
        "--opcua-read-only", action="store_true", help="reject OPC UA writes and methods"
    )
    o.add_argument("--opcua-user", metavar="USER", help="sessions need this user (no anonymous)")
    o.add_argument(
        "--opcua-password",
        metavar="PASSWORD",
        default=os.environ.get("GEO_SERVER_OPCUA_PASSWORD"),
        help="its password (with --opcua-user; or the environment's GEO_SERVER_OPCUA_PASSWORD)",
    )
    o.add_argument(
        "--opcua-encrypt-only",
        action="store_true",
        help="offer only Basic256Sha256 SignAndEncrypt (no unencrypted endpoint)",
    )
    o.add_argument(
        "--opcua-no-companions",
        action="store_true",
        help="leave out the CNC (OPC 40502) and Machine Tool (OPC 40501) models: "
        "OPC UA is ready about 3 s sooner",
    )
    o.add_argument(
        "--opcua-cert-dir",
        metavar="DIR",
        help="folder of the server certificate, made there on first start (default: opcua/ "
        "beside the start-up list; for the default machine ~/.config/geo-server/opcua)",
    )
