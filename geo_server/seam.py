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

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from geo_server.dictionary import Dictionary, ObjectDef
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
