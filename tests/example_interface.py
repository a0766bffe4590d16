"""The worked example of docs/design.md §1.3: a whole interface in one module.

"line" serves reads as lines of text on TCP: `SIM::cycle_count` or
`TEMPC::coefficient 1` (a name and an axis) is answered with the value, or with
`error: …`. Registering it is one line, `"line": Registered("example_interface")`, and
`geo-server run` then has `--line-port` and `--no-line`, plans its connections, starts
and closes it (tests/test_interface_registry.py does exactly that)."""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Mapping, Sequence

from geo_server import access
from geo_server.errors import GeoError
from geo_server.service import ObjectService
from geo_server.transports.interface import (
    FleetMachine,
    FleetStatus,
    Interface,
    Startable,
    Starting,
    Wants,
)
from geo_server.transports.tcp import BACKLOG, Gate, Listener

#: a request line, at most (a longer one closes the connection)
MAX_LINE = 256


class LineOptions:
    """Where it listens; `max_connections` is its cap (fitted by the composition root)."""

    max_connections: int = 8

    def __init__(self, port: int, max_connections: int = max_connections) -> None:
        self.port = port
        self.max_connections = max_connections


class LineServer:
    """The server: a `Listener` (the cap) and a protocol that reads lines."""

    def __init__(self, service: ObjectService, options: LineOptions) -> None:
        self._service = service
        self.listener = Listener("127.0.0.1", options.port, options.max_connections)

    async def start(self) -> None:
        await self.listener.listen(lambda: Gate(self.listener, self._protocol, "line"))

    async def close(self) -> None:
        await self.listener.close()

    def _protocol(self) -> asyncio.Protocol:
        return _Lines(self._service)


class _Lines(asyncio.Protocol):
    def __init__(self, service: ObjectService) -> None:
        self._service = service
        self._buffer = b""
        self._transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport

    def data_received(self, data: bytes) -> None:
        assert self._transport is not None
        self._buffer += data
        while b"\n" in self._buffer:
            line, self._buffer = self._buffer.split(b"\n", 1)
            self._transport.write(self._answer(line.decode("utf-8", "replace")).encode() + b"\n")
        if len(self._buffer) > MAX_LINE:
            self._transport.abort()

    def _answer(self, line: str) -> str:
        name, _, axis = line.strip().partition(" ")
        try:
            return str(access.read_name(self._service, name, int(axis or 0)))
        except (GeoError, ValueError) as exc:
            return f"error: {exc}"


class Line(Interface):
    name = "line"
    title = "line"
    port_option = "--line-port PORT"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        g = parser.add_argument_group("line (tests/example_interface.py)")
        g.add_argument("--no-line", action="store_true", help="do not serve lines")
        g.add_argument("--line-port", type=int, default=5099, help="listen port")

    def wants(self, args: argparse.Namespace, machines: int | None) -> Wants:
        return Wants(LineOptions.max_connections, BACKLOG)

    def limits(self) -> type:
        return LineOptions

    def build(
        self, args: argparse.Namespace, service: ObjectService, caps: Mapping[str, int]
    ) -> Startable:
        server = LineServer(service, LineOptions(args.line_port, caps["line"]))
        return Startable(server, lambda: f"line: tcp://{server.listener.endpoint}")

    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[FleetMachine],
        starting: Starting,
        status: FleetStatus,
    ) -> None:
        for i, m in enumerate(machines):  # a port per machine
            options = LineOptions(args.line_port + i, starting.caps["line"])
            await starting.start(self.name, LineServer(m.service, options), None)


INTERFACE = Line()
