"""The composition root (docs/design.md §1.2): a server built from options in one place —
a machine, the engine that runs its cycles and the object service over both
(`build_machine`), and the interfaces of the registry that serve it (`Interfaces`, over
each interface's plug: docs/design.md §1.3b) for one machine
(`Interfaces.start_machine`), a fleet (`Interfaces.start_fleet`) or a test
(`loopback_interface`). Used by `geo-server run` (`cli`), each fleet (`fleet`) and
`GeoTestServer` (`geo_clients.testing`) alike. Nothing else constructs a `Machine`, a
scheduler and an `ObjectService` together (the recorder's replay builds its own stepped
machine); an interface's server is built by its plug when this asks
(tests/test_architecture.py). The transports are imported when built: a command that
serves nothing does not load Zenoh, aiohttp or asyncua (tests/test_interface_registry.py).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
from collections.abc import Awaitable, Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from geo_server.descriptors import MIN_CAP, AcceptLog, DescriptorError, plan
from geo_server.fleetfile import Member
from geo_server.interfaces import REGISTRY, InterfaceStartError, start_failure
from geo_server.machine.machine import Machine
from geo_server.machine.port import CycleRunner, MachinePort
from geo_server.machine.scheduler import Scheduler
from geo_server.model import MachineConfig
from geo_server.service import ObjectService, ServiceLimits
from geo_server.transports.interface import (
    FleetMachine,
    FleetStatus,
    Interface,
    Loopback,
    Server,
    load,
    plugs,
)


@dataclass(frozen=True)
class EngineOptions:
    """How a machine's cycles run (README *Running*, docs/design.md §5.4–§5.6, §13)."""

    cycle_ms: float = 1.0
    homed: bool = True
    #: virtual time runs this many times as fast as wall time (None: real time)
    time_scale: float | None = None
    #: "stepped" (a test steps it), "realtime" or "free"
    mode: str = "stepped"
    #: "exact" or "punctual"
    engine: str = "exact"
    #: the cycle thread ends after this many cycles (0: never)
    max_cycles: int = 0
    #: "thread" or "process" (the cycle in a child process; Linux and macOS)
    cycle_in: str = "thread"

    @classmethod
    def from_args(cls, args: argparse.Namespace, cycle_in: str = "thread") -> EngineOptions:
        """The options of `geo-server run`'s command line."""
        return cls(
            cycle_ms=args.cycle_ms,
            homed=args.homed,
            time_scale=args.time_scale,
            mode=args.mode,
            engine=args.engine,
            max_cycles=args.cycles,
            cycle_in=cycle_in,
        )


@dataclass(frozen=True)
class Built:
    """A machine with its engine and its object service (the only way in for every
    interface)."""

    machine: MachinePort
    scheduler: CycleRunner
    service: ObjectService


def build_machine(
    cfg: MachineConfig, options: EngineOptions, limits: ServiceLimits | None = None
) -> Built:
    """The machine of `cfg`, its engine and its object service, from `options`."""
    cycle_s = options.cycle_ms / 1000.0
    machine: Any
    scheduler: Any
    if options.cycle_in == "process":
        from geo_server.machine.process import ProcessScheduler, RemoteMachine

        machine = RemoteMachine(
            cfg, cycle_s=cycle_s, homed=options.homed, time_scale=options.time_scale
        )
        scheduler = ProcessScheduler(
            machine, mode=options.mode, max_cycles=options.max_cycles, engine=options.engine
        )
    else:
        machine = Machine(cfg, cycle_s=cycle_s, homed=options.homed, time_scale=options.time_scale)
        scheduler = Scheduler(
            machine, mode=options.mode, max_cycles=options.max_cycles, engine=options.engine
        )
    return Built(machine, scheduler, ObjectService(machine, scheduler, limits))


# ---------------------------------------------------------------------- interfaces


def connection_caps(args: argparse.Namespace, machines: int | None = None) -> dict[str, int]:
    """Each interface's connection cap, fitted under the open-files limit (raised to the
    hard limit first; geo_server/descriptors.py), from what each plug `wants`;
    `machines`: a fleet's size (None: one machine). A cap per machine (Modbus's: a port
    each) is that machine's, and keeps at least `MIN_CAP` connections each."""
    n = machines or 1
    wanted: dict[str, int] = {}
    floors: dict[str, int] = {}
    per_machine = set()
    fixed = 0
    for plug in plugs():
        if not plug.enabled(args):
            continue
        wants = plug.wants(args, machines)
        wanted[plug.name] = wants.connections
        fixed += wants.fixed
        if wants.per_machine:
            floors[plug.name] = MIN_CAP * n
            per_machine.add(plug.name)
    caps, said = plan(wanted, fixed, floors=floors)
    if said:
        print(said, file=sys.stderr, flush=True)
    return {name: cap // n if name in per_machine else cap for name, cap in caps.items()}


@contextlib.contextmanager
def _starting(plug: Interface) -> Iterator[None]:
    """Any failure to start interface `plug` (a taken port, a bad address, Zenoh's
    config) as an `InterfaceStartError` saying why (`start_failure`)."""
    try:
        yield
    except InterfaceStartError:
        raise
    except Exception as exc:
        raise InterfaceStartError(start_failure(plug.name, exc, plug.port_option)) from exc


class Interfaces:
    """A server's interfaces (`geo_server.interfaces.REGISTRY`), started in order and
    closed in the reverse order: what each plug is lent while it starts (`Starting`).

    `plan` fits their connection caps under the open-files limit; `start_machine`
    starts those of one machine, `start_fleet` (and `start_fleet_late`) those of a fleet,
    each printing its start-up line. Whatever starts is registered before its start, so
    a half-started interface is closed too (`close`)."""

    def __init__(self, caps: dict[str, int]) -> None:
        #: connection caps by interface (`connection_caps`)
        self.caps = caps
        self._closers: list[tuple[str, Callable[[], Awaitable[Any]]]] = []
        self._fleet: list[FleetMachine] = []

    @classmethod
    def plan(cls, args: argparse.Namespace, machines: int | None = None) -> Interfaces:
        """On the running loop, before anything starts: accept failures for want of
        descriptors said once per period (`AcceptLog`), not once per retry; the caps
        fitted under the open-files limit (`connection_caps`), an `InterfaceStartError`
        when they cannot be."""
        AcceptLog().install(asyncio.get_running_loop())
        try:
            return cls(connection_caps(args, machines))
        except DescriptorError as exc:
            raise InterfaceStartError(str(exc)) from None

    def closes(self, what: str, close: Callable[[], Awaitable[Any]]) -> None:
        """Have `close` (of `what`) called by `close`, before what was registered earlier."""
        self._closers.append((what, close))

    async def start(self, name: str, server: Server, line: Callable[[], str] | None) -> None:
        """Start `server`, of interface `name`, and print its start-up `line`."""
        self.closes(type(server).__name__, server.close)
        with _starting(load(name)):
            await server.start()
        if line is not None:
            print(line(), flush=True)

    async def close(self) -> None:
        """Close everything in the reverse order of start; one failing to close must not
        keep the others (and their ports) open."""
        while self._closers:
            what, close = self._closers.pop()
            try:
                await close()
            except Exception as exc:  # report and go on closing the others
                print(f"warning: closing {what}: {exc}", file=sys.stderr)

    async def start_machine(self, args: argparse.Namespace, service: ObjectService) -> None:
        """`geo-server run`'s interfaces of one machine, those not turned off, each up
        before the next starts, in the registry's order."""
        for plug in plugs():
            if plug.enabled(args):
                await plug.prepare()
                built = plug.build(args, service, self.caps)
                await self.start(plug.name, built.server, built.line)

    async def start_fleet(
        self,
        args: argparse.Namespace,
        machines: Sequence[tuple[Member, ObjectService]],
        status: FleetStatus,
    ) -> None:
        """A fleet's interfaces (fleet.py), those not turned off and not waiting for its
        first `status` (`start_fleet_late`). Each machine's requests draw on one share
        of the event loop (`transports.share`, docs/design.md §13.1)."""
        from geo_server.transports.share import LoopShare, fleet_rate

        rate = fleet_rate(len(machines))
        self._fleet = [
            FleetMachine(
                m.name,
                m.netid,
                m.modbus_port,
                service,
                LoopShare(rate) if len(machines) > 1 else None,
            )
            for m, service in machines
        ]
        await self._start_fleet(args, status, late=False)

    async def start_fleet_late(self, args: argparse.Namespace, status: FleetStatus) -> None:
        """The fleet's interfaces that show its status (`starts_with_the_status`), once
        its cycles run and the first status is known."""
        await self._start_fleet(args, status, late=True)

    async def _start_fleet(self, args: argparse.Namespace, status: FleetStatus, late: bool) -> None:
        for plug in plugs():
            if plug.enabled(args) and plug.starts_with_the_status == late:
                await plug.prepare()
                with _starting(plug):
                    await plug.start_fleet(args, self._fleet, self, status)


def loopback_interface(
    via: str,
    service: ObjectService,
    *,
    machine: str,
    netid: str,
    publish_period: float,
    status_period: float,
) -> Server:
    """`GeoTestServer`'s interface `via` (docs/design.md §10), not started, on a free port
    of 127.0.0.1 (`Interface.loopback`)."""
    test = Loopback(machine, netid, publish_period, status_period)
    server = load(via).loopback(service, test) if via in REGISTRY else None
    if server is None:
        able = [n for n in REGISTRY if type(load(n)).loopback is not Interface.loopback]
        raise ValueError(f"no loopback interface {via!r} ({', '.join(able)})")
    return server
