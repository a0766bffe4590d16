"""The composition root (docs/design.md §1.2): a machine, the engine that runs its
cycles and the object service over both, built from options in one place — for
`geo-server run` (`cli`), each machine of a fleet (`fleet`) and `GeoTestServer`
(`geo_clients.testing`). Nothing else constructs a `Machine`, a scheduler and an
`ObjectService` together (the recorder's replay builds its own stepped machine).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

from geo_server.machine.machine import Machine
from geo_server.machine.port import CycleRunner, MachinePort
from geo_server.machine.scheduler import Scheduler
from geo_server.model import MachineConfig
from geo_server.service import ObjectService, ServiceLimits


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
