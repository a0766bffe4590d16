"""The seam between the object service and a machine, wherever its GEO cycle runs.

The object service talks to a machine only through `MachinePort` and to whatever runs
its cycles only through `CycleRunner`. Two implementations of each exist: the machine in
this process (`Machine` with a `Scheduler`: stepped, free-running or real time on a
thread) and the machine in a child process (`RemoteMachine` with a `ProcessScheduler`).

Everything a caller asks of a machine is one of the frozen *operations* below. It is
queued and carried out at the next cycle boundary, in arrival order (the first step of a
GEO cycle). `submit` returns a `Pending`: a future that resolves once the cycle that
carried the operation out has published its snapshot, and that can be *withdrawn* as long
as no cycle has taken it yet. Withdrawal is what makes a timeout honest: an operation
reported as failed because it was not applied in time has been withdrawn, so it can
never take effect later.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from geo_server.seam import ChosenCycles

if TYPE_CHECKING:
    from geo_server.dictionary import Dictionary, ObjectDef
    from geo_server.events import Event
    from geo_server.machine.nc import Program
    from geo_server.model import Diagnostic, MachineConfig
    from geo_server.snapshot import Snapshot


# ---------------------------------------------------------------------- operations


@dataclass(frozen=True)
class WriteObjects:
    """Validated object writes `(object, axis, value)`, applied in one cycle, in order.
    The object is the definition the service resolved the address or name to, carried
    to the machine as it is (no second lookup); a name is looked up in the machine's
    dictionary (recorded inputs replayed, tests). The outcome is a tuple with one entry
    per item: None, or the exception that item raised (the other items are applied all
    the same)."""

    items: tuple[tuple[ObjectDef | str, int, Any], ...]


@dataclass(frozen=True)
class StartProgram:
    """Run a parsed NC program (or MDI lines) from the next cycle on."""

    program: Program
    mdi: bool = False
    #: the NC text it was parsed from (what a recording of the inputs replays)
    text: str = ""


@dataclass(frozen=True)
class Reset:
    """CNC reset: program stopped, axes stopped, manual-activation compensations
    deselected (000 §5.1)."""


@dataclass(frozen=True)
class Reload:
    """Swap in a validated configuration at this cycle boundary."""

    cfg: MachineConfig


@dataclass(frozen=True)
class Saved:
    """The lists hold the live values now: swap in `cfg`, the configuration as saved, at
    this cycle boundary (no step event: nothing the kernel uses changed)."""

    cfg: MachineConfig


@dataclass(frozen=True)
class Record:
    """Put a warning or error the server itself found (a rejected reload, a second
    server with this machine's name) into the machine's error list, so that
    `SIM::last_error_id` and `SIM::last_error` show it like every other error."""

    diagnostic: Diagnostic


@dataclass(frozen=True)
class VolcUpdate:
    """Replace volumetric compensation `ident` by a freshly loaded one (`#VOLCOMP
    UPDATE` or cnc_interpr_vol_comp_file_w, 004 p.23): the files were read by the
    caller, off the cycle; `comp` is a `geo_server.volcomp.config.VolComp`."""

    ident: int
    comp: Any


@dataclass(frozen=True)
class SensorFault:
    """Injected fault of the twin's sensor `sensor` (geo_server/faults.py): "stuck",
    "noisy" (σ = `sigma` °C more noise), "open", or "" to clear it."""

    sensor: int
    kind: str
    sigma: float = 0.0


Operation = WriteObjects | StartProgram | Reset | Reload | Saved | Record | VolcUpdate | SensorFault


# ---------------------------------------------------------------------- pending


class Pending(Future[Any]):
    """The outcome of a queued operation, which can be withdrawn until a cycle takes it.

    `withdraw()` (also what `cancel()` does, so an asyncio wrapper being cancelled can
    never leave an operation that still runs) returns True when the operation was
    removed before any cycle took it: it will never run, and the future is cancelled.
    False means a cycle has taken it (or it is done), or the owner cannot tell right now
    (the cycle process is stopped in the middle of taking operations): the future will
    tell the outcome, and the caller may try again later.
    """

    def __init__(self, withdraw: Callable[[Pending], bool] | None = None) -> None:
        super().__init__()
        self._withdraw = withdraw

    def cancel(self) -> bool:
        if self.done():
            return self.cancelled()
        if self._withdraw is None or not self._withdraw(self):
            return False
        return super().cancel()

    def withdraw(self) -> bool:
        return self.cancel()


def chained(inner: Pending, transform: Callable[[Any], Any]) -> Pending:
    """A `Pending` that follows `inner` with its result passed through `transform`
    (which may raise); withdrawing it withdraws `inner`."""
    outer = Pending(lambda _p: inner.withdraw())

    def copy(done: Future[Any]) -> None:
        if done.cancelled():
            outer.cancel()
            return
        if not outer.set_running_or_notify_cancel():
            return
        exc = done.exception()
        if exc is not None:
            outer.set_exception(exc)
            return
        try:
            outer.set_result(transform(done.result()))
        except BaseException as err:
            outer.set_exception(err)

    inner.add_done_callback(copy)
    return outer


def listen(listeners: list[Any], callback: Any) -> Callable[[], None]:
    """Add `callback` to `listeners`; returns the function that removes it again (once,
    harmlessly twice) — the `subscribe` contract of both machine kinds."""
    listeners.append(callback)

    def unsubscribe() -> None:
        if callback in listeners:
            listeners.remove(callback)

    return unsubscribe


def resolved(result: Any = None, error: BaseException | None = None) -> Pending:
    """A `Pending` that is already done (nothing was queued)."""
    p = Pending()
    if error is None:
        p.set_result(result)
    else:
        p.set_exception(error)
    return p


# ---------------------------------------------------------------------- protocols


#: An observer that needs the snapshots of chosen cycles (ADS notifications, OPC UA's
#: items): defined once, where OPC UA's own process can use it too (`seam.ChosenCycles`).
CycleDemand = ChosenCycles


class MachinePort(Protocol):
    """What the object service needs of a machine."""

    cfg: MachineConfig
    axes: tuple[int, ...]
    names: dict[str, int]
    dictionary: Dictionary
    cycle_s: float

    @property
    def snapshot(self) -> Snapshot:
        """The snapshot of the latest cycle (published by swapping a reference)."""

    @property
    def rest_snapshot(self) -> Snapshot | None:
        """The published snapshot while the machine shows its rest (`Machine.shows_rest`:
        every object that cannot vary at rest holds its value of every cycle from now
        until something is queued), else None (docs/design.md §13, *Repeated reads*)."""

    @property
    def heartbeat(self) -> float:
        """`time.monotonic()` when the cycle last showed it is alive: a cycle computed or
        skipped, or a snapshot published (the stall watch)."""

    @property
    def snapshot_time(self) -> float:
        """`time.monotonic()` when the current snapshot was published."""

    @property
    def events(self) -> Sequence[Event]:
        """The latest warnings and errors, oldest first."""

    def submit(self, op: Operation) -> Pending:
        """Queue `op` for the next cycle boundary."""

    def record(self, diagnostic: Diagnostic) -> Pending:
        """Put a warning or error the server found into the error list (done once the
        returned future is: at once in this process, at the next cycle boundary when the
        cycle runs in its own process)."""

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        """Call `callback(snapshot)` after every cycle (on the thread that publishes it);
        returns the function that unsubscribes."""

    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        """Call `callback(event)` for every new warning or error; returns the function
        that unsubscribes."""


class CycleRunner(Protocol):
    """What runs the cycles of a machine: stepped, free-running or real time."""

    mode: str

    @property
    def running(self) -> bool:
        """True while cycles run by themselves (free-running or real time)."""

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def step(self, n: int = 1) -> None:
        """Run `n` cycles now (stepped mode only)."""

    def sync(self, wait: float = ..., record: bool = True) -> bool:
        """Make the machine's snapshot the one of the cycle due now (the exact engine
        computes late; others: nothing to do); False when it could not within `wait`
        seconds (0: only if nobody else is computing). `record`: time it as what
        catching up added to a request."""

    def shows_due(self) -> bool:
        """Whether `sync` has nothing to compute or wait for now (a look without a
        lock: the published snapshot is the one due, or no exact engine runs)."""
        ...

    def submit(self, op: Operation) -> Pending:
        """Queue `op` for the cycle after the one due now (`MachinePort.submit` once the
        machine has caught up)."""

    def demand_every_cycle(self) -> Callable[[], None]:
        """Publish every cycle's snapshot until the returned function is called (an
        observer samples every cycle: ADS notifications)."""

    def status(self) -> dict[str, Any]: ...
