"""The contract every interface keeps (docs/design.md §1.3), in the manner of python-can's
`BusABC` and its backend table: the table is `geo_server.interfaces.REGISTRY`, one line
per interface naming the module that holds its `Interface` (its *plug*, `INTERFACE`).

A plug says what `geo-server run` needs to know of its interface — its name, its
command-line options and what is wrong with them, whether it is on, the connections it
wants, how to build its server for one machine and how to start it for a fleet — and
nothing more: `compose`, `cli`, `fleet` and `faults` iterate the registry and never name
an interface (tests/test_interface_registry.py); `docs` takes each interface's options
class from it (and names constants of some for the Limits page). A plug imports its
server only when it builds one: the parser is made for every command, and a command that
serves nothing loads no Zenoh, aiohttp or asyncua.
"""

from __future__ import annotations

import argparse
import importlib
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple, Protocol

from geo_server.interfaces import REGISTRY

if TYPE_CHECKING:  # (the parser is built for every command: nothing heavy at import)
    from geo_server.service import ObjectService
    from geo_server.transports.share import LoopShare


class Server(Protocol):
    """What the composition root does with an interface's server: start it, close it."""

    async def start(self) -> None: ...

    async def close(self) -> None: ...


class Startable(NamedTuple):
    """An interface's server for one machine, not started, and the line it says once up."""

    server: Server
    line: Callable[[], str] | None


class FleetCounts(NamedTuple):
    """What an interface's entries of a machine's status (`ObjectService.status_extra`)
    add to the machine's row of a fleet's status (geo_server/fleet.py)."""

    #: notification registrations
    notifications: int = 0
    #: samples taken later than their cycle, refused or dropped (`starved`)
    samples_late: int = 0
    #: requests held for a share of the processor (`throttled`)
    holds: int = 0


class Wants(NamedTuple):
    """What an interface asks of the process's descriptors (geo_server/descriptors.py)."""

    #: connections it would admit (the cap `Starting.caps` gets, shrunk to fit)
    connections: int
    #: descriptors held besides them (listening sockets' accept queues)
    fixed: int = 0
    #: its cap is per machine of a fleet (`connections` counts them all; each machine
    #: keeps at least `descriptors.MIN_CAP`, or the server does not start)
    per_machine: bool = False


class Starting(Protocol):
    """What the composition root lends an interface while it starts
    (`compose.Interfaces`)."""

    @property
    def caps(self) -> Mapping[str, int]:
        """Connection caps by interface name, fitted under the open-files limit."""

    def closes(self, what: str, close: Callable[[], Awaitable[Any]]) -> None:
        """Have `close` called when the server stops (before what started earlier)."""

    async def start(self, name: str, server: Server, line: Callable[[], str] | None) -> None:
        """Start `server`, registered to be closed first, and print its `line`."""


class Loopback(NamedTuple):
    """What `GeoTestServer` asks of an interface (docs/design.md §10)."""

    machine: str
    netid: str
    publish_period: float
    status_period: float


@dataclass(frozen=True)
class FleetMachine:
    """One machine of a fleet as its interfaces see it (fleet files: docs/fleet.md)."""

    name: str
    netid: str
    modbus_port: int
    service: ObjectService
    #: its share of the event loop (None: a fleet of one)
    share: LoopShare | None


@dataclass
class FleetStatus:
    """The fleet's status as its interfaces may serve it (geo_server/fleet.py)."""

    #: the latest status (empty before the first)
    latest: Callable[[], dict[str, Any]]
    #: ... as JSON (None before the first)
    latest_json: Callable[[], bytes | None]
    #: called with each new status as JSON, on the event loop
    said: list[Callable[[bytes], None]] = field(default_factory=list)
    #: a machine's name -> publish that machine's own status (from any thread)
    publishers: dict[str, Callable[[dict[str, Any]], None]] = field(default_factory=dict)


class Interface(ABC):
    """One interface of geo-server: its plug, registered in
    `geo_server.interfaces.REGISTRY` under `name`."""

    #: its name: the registry's key, a fault's target, its connection cap's key
    name: ClassVar[str]
    #: its name in tables and messages ("OPC UA")
    title: ClassVar[str]
    #: what to change when its port is taken (`geo_server.interfaces.start_failure`)
    port_option: ClassVar[str]
    #: a fleet starts it once the cycles run and the first status is known
    starts_with_the_status: ClassVar[bool] = False

    @abstractmethod
    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Its options of `geo-server run`."""

    def add_commands(self, commands: argparse._SubParsersAction[Any]) -> None:
        """Commands of its own beside `run` (`geo-server modbus-map`)."""
        return None

    def check(self, args: argparse.Namespace) -> str | None:
        """What is wrong with its options (None: nothing), said before anything starts."""
        return None

    def enabled(self, args: argparse.Namespace) -> bool:
        """Is it to be started? (By default: unless `--no-NAME` was given.)"""
        return not vars(args)[f"no_{self.name}"]

    def cap(self, caps: Mapping[str, int]) -> dict[str, int]:
        """Its options' `max_connections` from the planned `caps`, if planned (a server
        built without a plan keeps its options' default)."""
        return {"max_connections": caps[self.name]} if self.name in caps else {}

    @abstractmethod
    def wants(self, args: argparse.Namespace, machines: int | None) -> Wants:
        """Its descriptors for one machine (`machines` None) or a fleet of `machines`."""

    @abstractmethod
    def limits(self) -> type:
        """Its options class: its fields with a `limit` description make the README's
        Limits table (geo_server/docs.py)."""

    async def prepare(self) -> None:
        """Work before it is built, off the loop the others answer on (an import)."""
        return None

    @abstractmethod
    def build(
        self, args: argparse.Namespace, service: ObjectService, caps: Mapping[str, int]
    ) -> Startable:
        """Its server of one machine (`geo-server run`), not started."""

    @abstractmethod
    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[FleetMachine],
        starting: Starting,
        status: FleetStatus,
    ) -> None:
        """Start what serves a fleet's `machines` (`starting.start`), say so."""

    def fleet_counts(self, status: Mapping[str, Any]) -> FleetCounts:
        """What its entries of a machine's `status` add to the machine's row of the
        fleet's status (none by default)."""
        return FleetCounts()

    def loopback(self, service: ObjectService, test: Loopback) -> Server | None:
        """`GeoTestServer`'s server of this interface (None: it has none), not started, on
        a free port of 127.0.0.1."""
        return None


def load(name: str) -> Interface:
    """The plug of interface `name` (a KeyError for one not registered)."""
    module = importlib.import_module(REGISTRY[name].plug)
    plug: Interface = module.INTERFACE
    return plug


def plugs() -> list[Interface]:
    """Every interface's plug, in the registry's order (the order they start)."""
    return [load(name) for name in REGISTRY]
