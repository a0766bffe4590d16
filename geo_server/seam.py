"""The object service as the layers below it see it (docs/design.md §1.3, §5.7).

`geo_server.service.ObjectService` sits above the machine, the twin, the recorder and
the commands it hands itself to (a measurement's bench, a recording): they cannot
import it, and typed it `Any`, which let any attribute through (a renamed one hid a
regression). Each types what it uses of the service as a Protocol built from these
parts, in the manner of pymodbus' datastore context; mypy checks that the service is
each of them where it hands itself over (`service.py`: `MeasureService`,
`RecordingService`, and `_conforms`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.errors import AdsError
from geo_server.events import Event
from geo_server.model import MachineConfig
from geo_server.snapshot import Snapshot


@dataclass(frozen=True)
class PreparedWrite:
    """A validated write: the object, the axis (0 for machine objects) and the value."""

    obj: ObjectDef
    axis: int
    value: Any


class MachineFacts(Protocol):
    """What the service says of its machine (`service.MachineInfo`)."""

    @property
    def axes(self) -> tuple[int, ...]: ...
    @property
    def cycle_s(self) -> float: ...
    @property
    def config(self) -> MachineConfig: ...
    @property
    def dictionary(self) -> Dictionary: ...
    @property
    def mode(self) -> str: ...


@dataclass(frozen=True)
class Facts:
    """A machine's facts as a value (`MachineFacts`), for a process that cannot ask the
    service (OPC UA's own, `transports.opcua.apart`): sent once, as they were then."""

    axes: tuple[int, ...]
    cycle_s: float
    config: MachineConfig
    dictionary: Dictionary
    mode: str

    @classmethod
    def of(cls, info: MachineFacts) -> Facts:
        return cls(info.axes, info.cycle_s, info.config, info.dictionary, info.mode)


class Outcome(Protocol):
    """A queued operation's outcome (`machine.port.Pending`)."""

    def done(self) -> bool: ...
    def result(self, timeout: float | None = None) -> Any: ...


class Stepping(Protocol):
    """Runs a stepped machine's cycles (`service.Stepper`)."""

    def step(self, n: int = 1) -> None: ...


class NcRunning(Protocol):
    """Starts NC text (`commands.nc.NcService`)."""

    def run(self, text: str) -> Outcome: ...


class Measured(Protocol):
    """What a measurement's bench uses (`twin.measure.StepBench`, `LiveBench`)."""

    @property
    def info(self) -> MachineFacts: ...
    @property
    def nc(self) -> NcRunning: ...
    def current(self, *, stale_ok: bool = False) -> Snapshot: ...
    def lookup(self, name: str, axis: int) -> ObjectDef: ...
    def prepare_name(self, name: str | ObjectDef, axis: int, value: Any) -> PreparedWrite: ...
    def submit_writes(self, writes: Sequence[PreparedWrite]) -> Outcome: ...
    def errors(self) -> list[dict[str, Any]]: ...
    def stepper(self) -> Stepping: ...


#: the most snapshots a catch-up holds back before it hands them to the listeners
#: (`Machine.held_back`): a listener's own count of what waits for it (ADS's
#: `sample_backlog`, which its `wants` refuses cycles past) lags the cycles published by
#: at most this many
HELD_MAX = 16


class ChosenCycles(Protocol):
    """An observer that needs the snapshots of chosen cycles (ADS notifications, OPC
    UA's items; `machine.port.CycleDemand` is this): the exact engine publishes a cycle
    it computes or skips when `wants` says so, and wakes for the next one `next_wanted`
    names. Both are called on the engine's thread (or a request's catch-up) with the
    engine lock held, so they must be quick and lock-free. The snapshots of a catch-up
    reach the listeners together, after it or every `HELD_MAX` of them."""

    def wants(self, cycle: int, quiescent: bool) -> bool:
        """Publish the snapshot of `cycle` (`quiescent`: the machine is at rest)."""

    def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
        """The first cycle after `cycle` whose snapshot is wanted (None: none)."""


class CommandsApplied(Protocol):
    """Runs a list command and waits for it (`commands.lists.CommandService`): its
    `CommandResult`."""

    async def run_applied(self, name: str, value: Any = None) -> Any: ...


class NcApplied(Protocol):
    """Starts NC text or a reset and waits for the cycle that did (`commands.nc.NcService`)."""

    async def run_applied(self, text: str, *, timeout: float | None = None) -> int: ...
    async def reset_applied(self, *, timeout: float | None = None) -> int: ...


class FaultsInjecting(Protocol):
    """Injects and clears faults (`commands.faults.FaultService`)."""

    def inject(self, fault: str) -> dict[str, Any]: ...
    def clear(self, ident: int | None = None) -> list[dict[str, Any]]: ...


class OpcUaService(Protocol):
    """What OPC UA uses of a machine's service (`geo_server.transports.opcua`):
    `ObjectService` itself, or, in OPC UA's own process, its stand-in there
    (`transports.opcua.apart.RemoteService`, docs/design.md §9.1)."""

    @property
    def info(self) -> MachineFacts: ...
    @property
    def nc(self) -> NcApplied: ...
    @property
    def commands(self) -> CommandsApplied: ...
    @property
    def faults(self) -> FaultsInjecting: ...
    @property
    def status_extra(self) -> dict[str, Any]: ...
    def current(
        self, *, stale_ok: bool = False, wait: float | None = None, at_rest_ok: bool = False
    ) -> Snapshot: ...
    def current_if_due(self) -> Snapshot | None: ...
    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]: ...
    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]: ...
    def demand_cycles(self, demand: ChosenCycles | None = None) -> Callable[[], None]: ...
    def prepare_name(self, name: str | ObjectDef, axis: int, value: Any) -> PreparedWrite: ...
    async def apply_writes(
        self, writes: Sequence[PreparedWrite], timeout: float | None = None
    ) -> list[AdsError | None]: ...
