"""The Zenoh interface's plug (geo_server/transports/interface.py): its options of
`geo-server run`, its server for one machine, a fleet's session (README *Zenoh*,
docs/design.md §7)."""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from geo_server.transports.interface import (
    FleetMachine,
    FleetStatus,
    Interface,
    Loopback,
    Server,
    Startable,
    Starting,
    Wants,
)

if TYPE_CHECKING:
    from geo_server.service import ObjectService
    from geo_server.transports.zenoh.options import ZenohOptions

#: The key of a fleet's status: every machine's cycle, overruns, faults (docs/fleet.md).
FLEET_STATUS_KEY = "cnc/fleet/status"


class Zenoh(Interface):
    name = "zenoh"
    title = "Zenoh"
    port_option = "--zenoh-listen tcp/127.0.0.1:PORT"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        z = parser.add_argument_group("zenoh")
        z.add_argument("--no-zenoh", action="store_true", help="do not start the Zenoh interface")
        z.add_argument(
            "--zenoh-listen",
            action="append",
            metavar="ENDPOINT",
            help="listen endpoint (default tcp/127.0.0.1:7447; repeatable)",
        )
        z.add_argument(
            "--zenoh-connect",
            action="append",
            metavar="ENDPOINT",
            help="router or peer to connect to (repeatable)",
        )
        z.add_argument("--zenoh-mode", choices=("peer", "client"), default="peer")
        z.add_argument(
            "--zenoh-config",
            metavar="FILE",
            help="Zenoh JSON5 config file (TLS, access control, …)",
        )
        z.add_argument("--zenoh-scouting", action="store_true", help="enable multicast scouting")
        z.add_argument("--zenoh-read-only", action="store_true", help="reject Zenoh writes")

    def wants(self, args: argparse.Namespace, machines: int | None) -> Wants:
        from geo_server.transports.zenoh.options import ZenohOptions

        # its sessions and the handshakes under way, one session for a fleet too
        return Wants(ZenohOptions.max_sessions + ZenohOptions.accept_pending)

    def limits(self) -> type:
        from geo_server.transports.zenoh.options import ZenohOptions

        return ZenohOptions

    def build(
        self, args: argparse.Namespace, service: ObjectService, caps: Mapping[str, int]
    ) -> Startable:
        from geo_server.transports.zenoh.server import ZenohInterface

        options = _options(args, caps, machine=args.machine)
        return Startable(
            ZenohInterface(service, options),
            lambda: (
                f"zenoh: machine {args.machine!r} on {', '.join(options.listen)} "
                f"(keys cnc/{args.machine}/**)"
            ),
        )

    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[FleetMachine],
        starting: Starting,
        status: FleetStatus,
    ) -> None:
        """One session with a machine's keys per machine, and the fleet's status at
        `FLEET_STATUS_KEY` (put when said, answered when asked)."""
        import zenoh

        from geo_server.transports.zenoh.server import ZenohInterface

        base = _options(args, starting.caps)
        loop = asyncio.get_running_loop()
        session = await loop.run_in_executor(None, zenoh.open, base.zenoh_config())

        async def close_session() -> None:
            await loop.run_in_executor(None, session.close)

        starting.closes("the Zenoh session", close_session)
        ifaces = []
        for i, m in enumerate(machines):
            # No status loop per machine (the fleet publishes every machine's status,
            # computed off the loop); the rival probes and the looks for subscribers
            # spread over their periods, the looks ten a second for the whole fleet: a
            # hundred catch-ups, probes or looks at once kept the loop every machine
            # shares busy for milliseconds to tens of milliseconds (docs/design.md §13.1).
            # The periodic probes are twenty a second for the whole fleet at most (each
            # starts a thread for its replies; Zenoh's reports of a new queryable or
            # token still start one at once).
            options = replace(
                base,
                machine=m.name,
                status_period=0.0,
                watch_recheck=max(base.watch_recheck, len(machines) / 10),
                rival_check_period=max(base.rival_check_period, len(machines) / 20),
                spread=i / len(machines),
            )
            iface = ZenohInterface(m.service, options, session=session)
            starting.closes(type(iface).__name__, iface.close)
            ifaces.append(iface)
            status.publishers[m.name] = iface.publish_status
        # together: each looks for a rival's token (up to 1 s)
        await asyncio.gather(*(iface.start() for iface in ifaces))

        def answer(q: Any) -> None:  # (a Zenoh thread: the latest status said, if any)
            said = status.latest_json()
            if said is not None:
                q.reply(FLEET_STATUS_KEY, said)

        queryable = session.declare_queryable(FLEET_STATUS_KEY, answer)

        async def undeclare() -> None:
            await loop.run_in_executor(None, queryable.undeclare)

        starting.closes("the fleet status queryable", undeclare)
        status.said.append(lambda said: session.put(FLEET_STATUS_KEY, said))
        print(
            f"zenoh: {len(ifaces)} machines on {', '.join(base.listen)} (keys cnc/<name>/**, "
            f"{FLEET_STATUS_KEY})",
            flush=True,
        )

    def loopback(self, service: ObjectService, test: Loopback) -> Server:
        """In peer mode with multicast scouting off and an explicit listen endpoint: it
        needs its port number up front (Modbus and ADS bind port 0 and report theirs)."""
        from geo_server.ports import free_port
        from geo_server.transports.zenoh.options import ZenohOptions
        from geo_server.transports.zenoh.server import ZenohInterface

        port = free_port()  # (free a moment ago, never one handed out before)
        options = ZenohOptions(
            machine=test.machine,
            listen=[f"tcp/127.0.0.1:{port}"],
            publish_period=test.publish_period,
            status_period=test.status_period,
        )
        return ZenohInterface(service, options)


def _options(args: argparse.Namespace, caps: Mapping[str, int], **more: Any) -> ZenohOptions:
    from geo_server.transports.zenoh.options import ZenohOptions

    options = ZenohOptions(
        mode=args.zenoh_mode,
        listen=args.zenoh_listen or ["tcp/127.0.0.1:7447"],
        connect=args.zenoh_connect or [],
        config_file=args.zenoh_config,
        multicast_scouting=args.zenoh_scouting,
        read_only=args.read_only or args.zenoh_read_only,
        **more,
    )
    if "zenoh" in caps:  # sessions and handshakes shrunk alike (`connection_caps`)
        options.shrink_to(caps["zenoh"])
    return options


INTERFACE = Zenoh()
