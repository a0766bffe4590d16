"""The Modbus TCP interface's plug (geo_server/transports/interface.py): its options of
`geo-server run`, its server for one machine, a port per machine of a fleet (README
*Modbus TCP*)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping, Sequence
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
from geo_server.transports.tcp import BACKLOG

if TYPE_CHECKING:
    from geo_server.service import ObjectService
    from geo_server.transports.modbus.server import ModbusOptions

#: Connections each machine's Modbus port queues before they are accepted: a fleet has a
#: port per machine, and every queued connection may become a descriptor at once.
FLEET_BACKLOG = 16


class Modbus(Interface):
    name = "modbus"
    title = "Modbus"
    port_option = "--modbus-port PORT"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        m = parser.add_argument_group("modbus")
        m.add_argument("--no-modbus", action="store_true", help="do not start Modbus TCP")
        m.add_argument(
            "--modbus-host", default="127.0.0.1", help="listen address (default 127.0.0.1)"
        )
        m.add_argument("--modbus-port", type=int, default=5020, help="listen port (default 5020)")
        m.add_argument("--modbus-read-only", action="store_true", help="reject Modbus writes")

    def add_commands(self, commands: argparse._SubParsersAction[Any]) -> None:
        mm = commands.add_parser("modbus-map", help="print the Modbus register map")
        mm.add_argument("--format", choices=("md", "csv"), default="md")
        mm.set_defaults(func=_modbus_map)

    def wants(self, args: argparse.Namespace, machines: int | None) -> Wants:
        from geo_server.transports.modbus.server import ModbusOptions

        n = machines or 1
        queue = BACKLOG if machines is None else FLEET_BACKLOG
        return Wants(ModbusOptions.max_connections * n, queue * n, per_machine=True)

    def limits(self) -> type:
        from geo_server.transports.modbus.server import ModbusOptions

        return ModbusOptions

    def build(
        self, args: argparse.Namespace, service: ObjectService, caps: Mapping[str, int]
    ) -> Startable:
        from geo_server.transports.modbus.server import ModbusInterface

        more = self.cap(caps)
        mb = ModbusInterface(service, _options(args, args.modbus_port, **more))
        return Startable(
            mb, lambda: f"modbus: tcp://{mb.endpoint} (unit id = axis number, unit 0 = machine)"
        )

    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[FleetMachine],
        starting: Starting,
        status: FleetStatus,
    ) -> None:
        """A port per machine (its `modbus_port`), its requests on its share of the loop."""
        from geo_server.transports.modbus.server import ModbusInterface

        for m in machines:
            options = _options(
                args, m.modbus_port, max_connections=starting.caps["modbus"], backlog=FLEET_BACKLOG
            )
            await starting.start(self.name, ModbusInterface(m.service, options, m.share), None)
        first, last = machines[0].modbus_port, machines[-1].modbus_port
        print(f"modbus: tcp://{args.modbus_host}:{first}…{last}, one port per machine", flush=True)

    def loopback(self, service: ObjectService, test: Loopback) -> Server:
        from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

        return ModbusInterface(service, ModbusOptions(port=0))


def _options(args: argparse.Namespace, port: int, **more: Any) -> ModbusOptions:
    """One machine's Modbus options from `geo-server run`'s command line (one machine or
    a fleet's member, on its own port)."""
    from geo_server.transports.modbus.server import ModbusOptions

    return ModbusOptions(
        host=args.modbus_host,
        port=port,
        read_only=args.read_only or args.modbus_read_only,
        **more,
    )


def _modbus_map(args: argparse.Namespace) -> int:
    """`geo-server modbus-map`: the register map, from the dictionary."""
    from geo_server.transports.modbus.regmap import modbus_map

    sys.stdout.write(modbus_map(args.format))
    return 0


INTERFACE = Modbus()
