"""The ADS interface's plug (geo_server/transports/interface.py): its options of
`geo-server run`, its server for one machine, one port routing a fleet by AMS NetId
(README *ADS*)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from geo_server.dictionary import GEO_AMS_PORT
from geo_server.transports.interface import (
    FleetCounts,
    FleetMachine,
    FleetStatus,
    Interface,
    Loopback,
    Server,
    Startable,
    Starting,
    Wants,
)
from geo_server.transports.tcp import BACKLOG

if TYPE_CHECKING:
    from geo_server.service import ObjectService
    from geo_server.transports.ads.options import AdsOptions


class Ads(Interface):
    name = "ads"
    title = "ADS"
    port_option = "--ads-port PORT"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        a = parser.add_argument_group("ads")
        a.add_argument("--no-ads", action="store_true", help="do not start ADS/AMS over TCP")
        a.add_argument("--ads-host", default="127.0.0.1", help="listen address (default 127.0.0.1)")
        a.add_argument("--ads-port", type=int, default=48898, help="listen port (default 48898)")
        a.add_argument("--ads-netid", default="127.0.0.1.1.1", help="own AMS NetId")
        a.add_argument(
            "--ads-udp-port",
            type=int,
            default=48899,
            help="UDP port of ADS discovery and add-route (default 48899, 0: off)",
        )
        a.add_argument("--ads-read-only", action="store_true", help="reject ADS writes (0x704)")
        a.add_argument(
            "--ads-route-user",
            metavar="USER",
            help="user name an add-route request on the discovery port must carry (with "
            "--ads-route-password; without both, every add-route is refused with 0x704)",
        )
        a.add_argument(
            "--ads-route-password",
            metavar="PASSWORD",
            default=os.environ.get("GEO_SERVER_ADS_ROUTE_PASSWORD"),
            help="password an add-route request must carry (see --ads-route-user; or the "
            "environment's GEO_SERVER_ADS_ROUTE_PASSWORD)",
        )

    def wants(self, args: argparse.Namespace, machines: int | None) -> Wants:
        from geo_server.transports.ads.options import AdsOptions

        # one port, for a fleet too (its cap is the fleet's)
        most = AdsOptions.max_connections if machines is None else AdsOptions.max_connections_fleet
        return Wants(most, BACKLOG)

    def limits(self) -> type:
        from geo_server.transports.ads.options import AdsOptions

        return AdsOptions

    def build(
        self, args: argparse.Namespace, service: ObjectService, caps: Mapping[str, int]
    ) -> Startable:
        from geo_server.transports.ads.server import AdsServer

        more = self.cap(caps)
        ads = AdsServer(service, _options(args, args.ads_netid, listener=True, **more))

        def line() -> str:
            said = f"ads: tcp://{ads.address} AMS NetId {args.ads_netid} port {GEO_AMS_PORT}"
            if ads.udp_port is not None:
                return said + f", discovery udp://{args.ads_host}:{ads.udp_port}"
            return said + (f" (discovery off: {ads.udp_error})" if ads.udp_error else "")

        return Startable(ads, line)

    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[FleetMachine],
        starting: Starting,
        status: FleetStatus,
    ) -> None:
        """One port, routing by target AMS NetId; each machine's requests on its share."""
        from geo_server.transports.ads.server import AdsServer

        head, last = machines[0], machines[-1]
        options = _options(
            args, head.netid, listener=True, max_connections_fleet=starting.caps["ads"]
        )
        ads = AdsServer(head.service, options, share=head.share)
        for m in machines[1:]:
            ads.add_device(m.service, _options(args, m.netid), m.share)
        await starting.start(
            self.name,
            ads,
            lambda: (
                f"ads: tcp://{ads.address}, AMS NetIds {head.netid}…{last.netid} "
                "(routed by target NetId)"
            ),
        )

    def loopback(self, service: ObjectService, test: Loopback) -> Server:
        from geo_server.transports.ads.options import AdsOptions
        from geo_server.transports.ads.server import AdsServer

        return AdsServer(service, AdsOptions(port=0, netid=test.netid))

    def fleet_counts(self, status: Mapping[str, Any]) -> FleetCounts:
        from geo_server.transports.ads.options import NOTIFICATIONS_STATUS

        notes = status.get(NOTIFICATIONS_STATUS) or {}
        return FleetCounts(
            notifications=int(notes.get("registrations", 0)),
            samples_late=int(notes.get("samples_late", 0)) + int(notes.get("samples_refused", 0)),
        )


def _options(
    args: argparse.Namespace, netid: str, *, listener: bool = False, **more: Any
) -> AdsOptions:
    """One machine's ADS options from the command line; `listener`: the machine that owns
    the TCP and UDP ports (the only one of a single run, a fleet's first)."""
    from geo_server.transports.ads.options import AdsOptions

    if listener:
        more.update(
            port=args.ads_port,
            udp_port=args.ads_udp_port or None,
            route_user=args.ads_route_user,
            route_password=args.ads_route_password,
        )
    return AdsOptions(
        host=args.ads_host, netid=netid, read_only=args.read_only or args.ads_read_only, **more
    )


INTERFACE = Ads()
