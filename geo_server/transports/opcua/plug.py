"""The OPC UA interface's plug (geo_server/transports/interface.py): its options of
`geo-server run`, where its certificate is kept, its server for one machine or a fleet,
and what is said when its background start ends (README *OPC UA*, docs/security.md
*OPC UA*)."""

from __future__ import annotations

import argparse
import asyncio
import importlib
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from geo_server.interfaces import start_failure
from geo_server.paths import default_startup_list, is_product_data
from geo_server.transports.interface import (
    FleetCounts,
    FleetMachine,
    FleetStatus,
    Interface,
    Startable,
    Starting,
    Wants,
)
from geo_server.transports.opcua.endpoint import parse_endpoint
from geo_server.transports.opcua.status import ITEMS_STATUS, SHARE_STATUS
from geo_server.transports.tcp import BACKLOG

if TYPE_CHECKING:
    from geo_server.service import ObjectService
    from geo_server.transports.opcua.apart import OpcUaProcess
    from geo_server.transports.opcua.server import OpcUaOptions
    from geo_server.transports.share import LoopShare

_SERVER_MODULE = "geo_server.transports.opcua.apart"


class OpcUa(Interface):
    name = "opcua"
    title = "OPC UA"
    port_option = "--opcua-endpoint opc.tcp://127.0.0.1:PORT (or --no-opcua)"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
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
        o.add_argument(
            "--opcua-user", metavar="USER", help="sessions need this user (no anonymous)"
        )
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

    def check(self, args: argparse.Namespace) -> str | None:
        if args.no_opcua:
            return None
        if (args.opcua_user is None) != (args.opcua_password is None):
            return "--opcua-user and --opcua-password go together"
        try:
            parse_endpoint(args.opcua_endpoint)
        except ValueError as exc:
            return str(exc)
        return None

    def wants(self, args: argparse.Namespace, machines: int | None) -> Wants:
        from geo_server.transports.opcua.server import OpcUaOptions

        return Wants(OpcUaOptions.max_connections, BACKLOG)  # one server, for a fleet too

    def limits(self) -> type:
        from geo_server.transports.opcua.server import OpcUaOptions

        return OpcUaOptions

    async def prepare(self) -> None:
        """Its modules take a while to import: not on the loop the others answer on."""
        await asyncio.to_thread(importlib.import_module, _SERVER_MODULE)

    def build(
        self, args: argparse.Namespace, service: ObjectService, caps: Mapping[str, int]
    ) -> Startable:
        return _server(args, {args.machine: service}, args.startup, caps, f"Objects/{args.machine}")

    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[FleetMachine],
        starting: Starting,
        status: FleetStatus,
    ) -> None:
        """One server, each machine under its own name, its requests on its share."""
        services = {m.name: m.service for m in machines}
        shares = {m.name: m.share for m in machines if m.share is not None}
        where = args.fleet or args.startup  # the certificate beside the fleet file
        said = f"{len(services)} machines: Objects/<name>"
        built = _server(args, services, where, starting.caps, said, shares)
        await starting.start(self.name, built.server, built.line)

    def fleet_counts(self, status: Mapping[str, Any]) -> FleetCounts:
        items = status.get(ITEMS_STATUS) or {}
        share = status.get(SHARE_STATUS) or {}
        return FleetCounts(
            samples_late=int(items.get("samples_late", 0)), holds=int(share.get("holds", 0))
        )


def _server(
    args: argparse.Namespace,
    services: Mapping[str, ObjectService],
    where: str | None,
    caps: Mapping[str, int],
    said: str,
    shares: Mapping[str, LoopShare] | None = None,
) -> Startable:
    """One OPC UA server, in a process of its own (`apart.py`), each machine of
    `services` under its own name, its certificate beside `where` (the start-up list or
    the fleet file); it starts in the background, and says so with `said` when ready
    (`announce`). In a fleet, each machine's requests draw on its share of the loop
    (`shares`)."""
    from geo_server.transports.opcua.apart import OpcUaProcess

    options = options_from_args(args, Path(where) if where else None, caps)
    ua = OpcUaProcess(dict(services), options, shares)
    announce(ua, said)
    return Startable(ua, lambda: f"opcua: {ua.endpoint} starting (README *OPC UA*)")


def user_folder() -> Path:
    """The user's geo-server folder (for the shipped default machine's certificate)."""
    if sys.platform == "win32":
        base = Path(os.environ.get("APPDATA") or Path.home() / "AppData" / "Roaming")
    else:
        base = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")
    return base / "geo-server"


def cert_folder(startup: Path) -> Path:
    """`opcua/` beside the start-up list, or in `user_folder` for the shipped machine."""
    if is_product_data(startup):
        return user_folder() / "opcua"
    return Path(startup).resolve().parent / "opcua"


def announce(iface: OpcUaProcess, where: str) -> None:
    """`geo-server run`: say when the background start is done, or why it failed."""

    def said(exc: BaseException | None) -> None:
        if exc is None:
            print(f"opcua: ready on {iface.endpoint} ({where})", flush=True)
            return
        text = start_failure(OpcUa.name, exc, OpcUa.port_option)
        print(f"error: {text} (the other interfaces keep serving)", file=sys.stderr, flush=True)

    iface.on_started = said


def options_from_args(
    args: argparse.Namespace, startup: Path | None, caps: Mapping[str, int]
) -> OpcUaOptions:
    """The options of `geo-server run` (one machine or a fleet; `startup`: the start-up
    list or fleet file the certificate is kept beside, `cert_folder`)."""
    from geo_server.transports.opcua.server import OpcUaOptions

    folder = args.opcua_cert_dir
    opts = OpcUaOptions(
        endpoint=args.opcua_endpoint,
        read_only=args.read_only or args.opcua_read_only,
        user=args.opcua_user,
        password=args.opcua_password,
        cert_dir=Path(folder) if folder else cert_folder(startup or default_startup_list()),
        encrypt_only=args.opcua_encrypt_only,
        companion_models=not args.opcua_no_companions,
        background=True,
    )
    if "opcua" in caps:
        opts.shrink_to(caps["opcua"])
    return opts


INTERFACE = OpcUa()
