"""What the programs in `clients/` share: opening a client over any transport.

`open_client("zenoh" | "modbus" | "ads", endpoint, ...)` returns an object with the
`geo_server.client.GeoClient` protocol (`read`, `write`, `read_raw`, `write_raw`,
`close`), so the PLC temperature adaptation and the test helpers switch transports with
one argument (docs/design.md §10). Endpoints are written as the transports name them:

- zenoh: a Zenoh endpoint, `tcp/127.0.0.1:7447` (default)
- modbus: `host:port`, `127.0.0.1:5020` (default)
- ads: `host:port`, `127.0.0.1:48898` (default); the AMS NetId is `--netid`
"""

from __future__ import annotations

import argparse
from typing import Any

from geo_server.client import (
    DEFAULT_ENDPOINTS,
    TRANSPORTS,
    GeoClient,
    open_client,
    split_host_port,
)


def add_transport_arguments(p: argparse.ArgumentParser) -> None:
    """`--via`, `--connect`, `--machine`, `--netid`, `--timeout` for a client program."""
    g = p.add_argument_group("server")
    g.add_argument("--via", choices=TRANSPORTS, default="zenoh", help="transport (default zenoh)")
    g.add_argument(
        "--connect",
        metavar="ENDPOINT",
        help="server endpoint (zenoh tcp/127.0.0.1:7447, modbus 127.0.0.1:5020, "
        "ads 127.0.0.1:48898)",
    )
    g.add_argument("--machine", default="local", help="machine name (Zenoh key prefix)")
    g.add_argument("--netid", default="127.0.0.1.1.1", help="AMS NetId of the server (ADS)")
    g.add_argument("--timeout", type=float, default=2.0, help="seconds per request (default 2)")


def client_from_args(args: argparse.Namespace) -> GeoClient:
    """Open the client that `add_transport_arguments` describes."""
    return open_client(
        args.via, args.connect, machine=args.machine, timeout=args.timeout, netid=args.netid
    )


def transport_name(client: Any) -> str:
    """A short name of a client's transport for logs (`zenoh`, `modbus`, `ads`, …)."""
    name = type(client).__name__.lower()
    for t in (*TRANSPORTS, "service"):
        if t in name:
            return t
    return name


__all__ = [
    "DEFAULT_ENDPOINTS",
    "TRANSPORTS",
    "add_transport_arguments",
    "client_from_args",
    "open_client",
    "split_host_port",
    "transport_name",
]
