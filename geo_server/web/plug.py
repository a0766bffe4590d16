"""The web HMI's plug (geo_server/transports/interface.py): its options of `geo-server
run`, its server for one machine, the fleet's page (docs/web.md)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

from geo_server.transports.interface import (
    FleetMachine,
    FleetStatus,
    Interface,
    Startable,
    Starting,
    Wants,
)
from geo_server.transports.tcp import BACKLOG

if TYPE_CHECKING:
    from geo_server.service import ObjectService


class Http(Interface):
    name = "http"
    title = "HTTP"
    port_option = "--http HOST:PORT"
    starts_with_the_status = True  # a fleet's page shows its status: once the cycles run

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument(
            "--http",
            metavar="HOST:PORT",
            help="serve the web HMI there (off by default; e.g. 127.0.0.1:8080; docs/web.md; "
            "a fleet: its list at /, a machine at /m/NAME/). Edits need the token of the URL "
            "printed at start; no TLS: keep it on loopback or behind a proxy",
        )
        h = parser.add_argument_group("web HMI (docs/web.md §4)")
        h.add_argument(
            "--http-allowed-hosts",
            action="append",
            metavar="HOST[:PORT],…",
            help="Host names the HMI answers to besides its address (e.g. hmi.example:8080; "
            "repeatable); a request for any other Host is refused (DNS rebinding)",
        )
        h.add_argument(
            "--http-token",
            metavar="TOKEN",
            default=os.environ.get("GEO_SERVER_HTTP_TOKEN"),
            help="the secret edits, reload and save need (default: GEO_SERVER_HTTP_TOKEN, else "
            "a new random one each run, printed in the page's URL)",
        )
        h.add_argument(
            "--http-user", metavar="USER", help="HTTP Basic authentication on everything"
        )
        h.add_argument(
            "--http-password",
            metavar="PASSWORD",
            default=os.environ.get("GEO_SERVER_HTTP_PASSWORD"),
            help="its password (with --http-user; or the environment's "
            "GEO_SERVER_HTTP_PASSWORD, which other users cannot see in the process list)",
        )
        h.add_argument(
            "--http-read-only", action="store_true", help="the HMI shows, refuses every edit"
        )

    def check(self, args: argparse.Namespace) -> str | None:
        if not args.http:
            return None
        from geo_server.web.server import http_options

        try:
            http_options(args)
        except ValueError as exc:
            return str(exc)
        return None

    def enabled(self, args: argparse.Namespace) -> bool:
        return bool(args.http)

    def wants(self, args: argparse.Namespace, machines: int | None) -> Wants:
        from geo_server.web.server import HmiOptions

        return Wants(HmiOptions.max_connections, BACKLOG)  # one port, for a fleet too

    def limits(self) -> type:
        from geo_server.web.server import HmiOptions

        return HmiOptions

    def build(
        self, args: argparse.Namespace, service: ObjectService, caps: Mapping[str, int]
    ) -> Startable:
        from geo_server.web.server import HmiServer, access_note, http_options

        more = self.cap(caps)
        hmi = HmiServer(service, http_options(args, machine=args.machine, **more))
        return Startable(hmi, lambda: f"http: web HMI on {hmi.url} ({access_note(hmi.options)})")

    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[FleetMachine],
        starting: Starting,
        status: FleetStatus,
    ) -> None:
        """The fleet's page (its `status`) at `/`, each machine's at `/m/<name>/`."""
        from geo_server.web.server import FleetHmi, access_note, http_options

        options = http_options(args, max_connections=starting.caps["http"])
        hmi = FleetHmi({m.name: m.service for m in machines}, status.latest, options)
        await starting.start(
            self.name,
            hmi,
            lambda: (
                f"http: web HMI on {hmi.url} (the fleet; a machine at /m/<name>/; "
                f"{access_note(hmi.options)})"
            ),
        )


INTERFACE = Http()
