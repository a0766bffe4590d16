"""The object service: the one narrow API every interface calls.

`ObjectService` has sixteen public methods — addresses (`resolve`, `lookup`), the
snapshot due now (`current`), reads (`read`, `read_many`), the write lifecycle
(`prepare`, `prepare_name`, `submit_writes`, `apply_writes`), subscriptions
(`subscribe`, `subscribe_changes`, `subscribe_events`, `demand_cycles`) and the state
(`status`, `errors`, `report`) — and a few attributes that are services of their own:
`info` (`MachineInfo`: axes, cycle time, configuration, mode, dictionary), `faults`,
`nc`, `commands`, `recordings`, `measurements` (`geo_server/commands/`). Reads and
writes by name for tests, the command line and the clients are functions over these
methods (`geo_server.access`).

Reads
    `read(group, offset, length)` answers from the latest published snapshot with ADS
    bytes, or raises `AdsError` (0x702 group, 0x703 offset or axis, 0x705 length). A
    read never returns more bytes than the object has; `read_many` answers a batch from
    one snapshot (sum reads, block reads). While cycles run by themselves and the latest
    cycle has not advanced for `ServiceLimits.stall_after`, the GEO cycle is *stalled*: reads
    raise 0x707 (device not ready) instead of serving an ever older picture as current,
    and `status()` says `"stalled": true` (status itself is always answered).

Writes: the write lifecycle lives here, once, for every transport
    `prepare`/`prepare_name` validate at once (0x702…0x706). `submit_writes` queues the
    values for the next cycle boundary; `apply_writes` also returns when the cycle that
    applied them has published its snapshot — so a read sent after the answer sees the
    value. In stepped mode nobody runs that cycle until the test steps: it returns as
    soon as the values are queued. A write not applied within the timeout is
    *withdrawn* before the caller hears 0x719: a write reported as failed never takes
    effect later. One the cycle has already taken is always acknowledged, however late
    (it will take effect). While the cycle is stalled new writes are refused at once
    with 0x707 and are not queued.

Commands
    Objects marked `command` in the dictionary (`SIM::reload`, `SIM::save`, `VOLC::file`)
    run that command instead of queueing a value (`commands.run`); commands read or
    write list files, so `apply_writes` runs them in a worker thread, never on an event
    loop. One command runs at a time; another one waits at most `command_wait` and then
    gets 0x708 (busy). Each command is a service of its own (`geo_server/commands/`)
    over the same ports and rules (`commands.ports.Ports`).

Addresses
    `resolve(group, offset, port=…)`: an ADS request's AMS port is an argument (a task
    serves only its own groups, 0x702); None (any port) for name-based interfaces.

Interfaces never reach into the kernel or the machine (tests/test_architecture.py checks
imports, attribute access, and that they call only the names above); they hold an
`ObjectService` and map its `AdsError`s to their own codes. What an engine can do beyond
the ports (overruns, chosen cycles, the twin's sensors, input taps) is decided once here,
by type, never by `getattr`.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from geo_server.commands.faults import FaultService
from geo_server.commands.lists import CommandService
from geo_server.commands.measure import MeasureService
from geo_server.commands.nc import NcService
from geo_server.commands.ports import ADSERR_DEVICE_SYNTAX, CommandResult, Ports
from geo_server.commands.record import RecordingService
from geo_server.commands.save import format_value
from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.machine.machine import Machine
from geo_server.machine.port import (
    CycleDemand,
    CycleRunner,
    MachinePort,
    Pending,
    WriteObjects,
    resolved,
)
from geo_server.machine.scheduler import Scheduler
from geo_server.model import CompKind, Diagnostic, MachineConfig
from geo_server.seam import Measured, OpcUaService, PreparedWrite
from geo_server.snapshot import Snapshot

#: the longest a status or a server's own error waits for another thread's catch-up
#: (seconds; a fleet's status asks every machine in turn)
STATUS_SYNC_WAIT = 0.02
#: Refused writes and NC text reported in the error list per second at most (a client
#: sending bad values in a loop must not flood the list and its publications); the rest
#: are counted (`status()["refusals_unreported"]`).
REFUSALS_PER_SECOND = 10
#: The refusals that are reported: a value out of range or not valid (0x706) and NC
#: text that does not parse (0x70D); each answer carries its reason as well.
REPORTED_REFUSALS = frozenset({AdsErrorCode.DEVICE_INVALIDDATA, ADSERR_DEVICE_SYNTAX})


@dataclass(frozen=True)
class ServiceLimits:
    """Time and size bounds of the object service (docs/limits.md)."""

    #: Seconds a write may wait for the cycle that applies it; then it is withdrawn (0x719).
    write_timeout: float = 2.0
    #: Seconds a reload waits for the cycle that swaps the tables; then it is withdrawn.
    swap_timeout: float = 5.0
    #: Seconds a command waits for another command to finish; then 0x708 (busy).
    command_wait: float = 1.0
    #: Seconds without a new snapshot, while cycles run by themselves, after which the
    #: GEO cycle counts as stalled.
    stall_after: float = 0.5
    #: Largest NC text accepted in one request (bytes, UTF-8).
    nc_max_bytes: int = 16 * 1024
    #: Most lines of NC text accepted in one request.
    nc_max_lines: int = 500
    #: Seconds a measurement (`cmd/measure`) may hold a running machine in all.
    measure_deadline: float = 3600.0


class MachineInfo:
    """What an interface may know of the machine it serves (`ObjectService.info`): its
    axes, cycle time, configuration (the current one after a reload), how its cycles
    run, and the object dictionary. Read live: a reload replaces the configuration."""

    def __init__(self, machine: MachinePort, scheduler: CycleRunner) -> None:
        self._machine = machine
        self._scheduler = scheduler

    @property
    def axes(self) -> tuple[int, ...]:
        """The logical axis numbers, in slot order."""
        return self._machine.axes

    @property
    def cycle_s(self) -> float:
        """The GEO cycle time in seconds."""
        return self._machine.cycle_s

    @property
    def config(self) -> MachineConfig:
        """The machine's configuration as loaded from its lists (the current one after
        a reload or a save): axes, parameters, tables, file paths. Read-only (sealed: a
        write raises AttributeError); a reload or a save swaps in a new one, so a
        configuration held stays as it was."""
        return self._machine.cfg

    @property
    def dictionary(self) -> Dictionary:
        """The object dictionary (objects/objects.toml, docs/design.md §2)."""
        return self._machine.dictionary

    @property
    def mode(self) -> str:
        """How the cycles run: "stepped", "free" or "realtime" (docs/design.md §5.4)."""
        return self._scheduler.mode

    @property
    def running(self) -> bool:
        """True while cycles run by themselves (real time, free-running)."""
        return self._scheduler.running

    def axis_names(self) -> dict[int, str]:
        """Axis number -> axis name, in slot order (symbol names)."""
        m = self._machine
        return {m.axes[slot]: name for name, slot in sorted(m.names.items(), key=_by_slot)}

    def lookup_address(
        self, index_group: int, element: int, channel: int, axis: int
    ) -> tuple[int, int]:
        """The address lookup (group + 0x600, docs/design.md §2): (group, offset) of an
        element for (channel, axis), (0, 0) for none."""
        m = self._machine
        return m.dictionary.lookup_address(index_group, element, channel, axis, m.axes)


class Stepper:
    """Runs the cycles of a machine in stepped mode, now (docs/design.md §5.4): what a
    test, a measurement or a replay that owns a stepped machine is handed
    (`ObjectService.stepper`), never an interface."""

    def __init__(self, scheduler: CycleRunner) -> None:
        self._scheduler = scheduler

    def step(self, n: int = 1) -> None:
        """Run `n` cycles."""
        self._scheduler.step(n)


class ObjectService:
    """Reads, writes, batches and subscriptions over one machine (the narrow service);
    its commands, faults, recordings and measurements are services of their own."""

    def __init__(
        self,
        machine: MachinePort,
        scheduler: CycleRunner | None = None,
        limits: ServiceLimits | None = None,
    ) -> None:
        if scheduler is None:
            if not isinstance(machine, Machine):
                raise TypeError("a machine in another process comes with its scheduler")
            scheduler = Scheduler(machine, mode="stepped")
        self._machine = machine
        self._scheduler = scheduler
        self._limits = limits or ServiceLimits()
        #: axes, cycle time, configuration, mode, dictionary
        self.info = MachineInfo(machine, scheduler)
        self._refusal_window = (0.0, 0)  # (second, reported in it)
        self._refusals_unreported = 0
        #: refusals are noted by the thread that refused (the loop, an NC worker)
        self._refusal_lock = threading.Lock()
        # What the engine can do beyond the ports, decided once by its type: the engine
        # in this process (overruns, chosen cycles, an idle wake) and the machine in
        # this process (the twin's sensors, input taps); the cycle process has neither.
        self._engine = scheduler if isinstance(scheduler, Scheduler) else None
        local = machine if isinstance(machine, Machine) else None
        self._dictionary = machine.dictionary
        self._resolved: dict[tuple[int, int, int | None], tuple[ObjectDef, int, str | None]] = {}
        #: Items merged into `status()` (interfaces add what they observe).
        self.status_extra: dict[str, Any] = {}
        self._started_at = 0.0
        #: a heartbeat younger than this is no stall, and reads at rest need no catch-up
        #: (`rests_on`; the limits are frozen)
        self._rest_fresh = self._limits.stall_after / 2
        # The commands, each a service of its own over the same ports and rules
        # (geo_server/commands, docs/design.md §5.7), built once here.
        self._ports = Ports(
            machine,
            scheduler,
            self._limits,
            refuse_when_stalled=self._refuse_when_stalled,
            settle_sync=self._settle_sync,
            settle=self._settle,
            report_now=self._report_now,
            snapshot=self._fresh,
            note_refusal=self._note_refusal,
        )
        #: reload, save, volcomp_update (the list files), one at a time
        self.commands = CommandService(self._ports)
        #: injected faults (docs/faults.md); the transports ask `faults.decide`
        self.faults = FaultService(
            self._ports,
            self._engine.set_overrun if self._engine is not None else None,
            (lambda: local.twin) if local is not None else None,
        )
        #: NC text and reset
        self.nc = NcService(self._ports)
        #: ISO 230-2 measurements on the twin (docs/twin.md)
        self.measurements = MeasureService(self._ports, self)
        #: recordings asked for over an interface (docs/recorder.md §7)
        self.recordings = RecordingService(self._ports, self)

    def stepper(self) -> Stepper:
        """The stepper of this machine's cycles; RuntimeError while they run by
        themselves (real time or free running, not paused: nobody else may run one)."""
        if self._scheduler.running:
            raise RuntimeError(f"the cycles run {self._scheduler.mode}: no stepper")
        return Stepper(self._scheduler)

    # ------------------------------------------------------------------ snapshots

    def current(
        self,
        *,
        stale_ok: bool = False,
        wait: float | None = None,
        at_rest_ok: bool = False,
    ) -> Snapshot:
        """The snapshot of the cycle due now (docs/design.md §13: the exact engine
        catches up first; other engines publish on their own), or 0x707 while the GEO
        cycle is stalled or cannot catch up in time. `stale_ok`: the last snapshot there
        is instead of 0x707 (a cycle number to report, an observer's own sample). `wait`:
        the longest to wait for a catch-up another thread runs (default `SYNC_WAIT`; 0:
        not at all, 0x707 when the engine is busy). `at_rest_ok`: the caller reads only
        objects that cannot vary at rest (`varies_at_rest`), so while the machine shows
        its rest (`rests_on`) the published snapshot already holds their values of the
        cycle due, and nothing is caught up (§13, *Reads at rest*)."""
        if at_rest_ok:
            rest = self._machine.rest_snapshot
            if rest is not None and rests_on(self, rest):
                return rest
        sched = self._scheduler
        synced = sched.sync() if wait is None else sched.sync(wait)
        if not synced and not stale_ok:
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY,
                "the GEO cycle is busy catching up (the host stalled): no current values",
            )
        snap = self._machine.snapshot
        return snap if stale_ok else self._unless_stalled(snap)

    def current_if_due(self) -> Snapshot | None:
        """`current()` when it needs no catch-up (nothing is computed, the engine's lock
        is not taken: the published snapshot is the one due, or the engine computes on
        its own), else None: the caller then asks `current` on a thread that may hold
        the lock (OPC UA's niced thread does not, docs/design.md §9.1). 0x707 as
        `current` while the cycle is stalled."""
        if not self._scheduler.shows_due():
            return None
        return self._unless_stalled(self._machine.snapshot)

    def _unless_stalled(self, snap: Snapshot) -> Snapshot:
        stalled = self._stalled_for()
        if stalled:
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY,
                f"the GEO cycle is stalled: no cycle for {stalled:.1f} s (last cycle {snap.cycle})",
            )
        return snap

    def _fresh(self) -> Snapshot:
        return self.current(stale_ok=True)

    def _heartbeat_age(self) -> float:
        """Seconds since the cycle last advanced (or since the service first looked)."""
        now = time.monotonic()
        if not self._started_at:
            self._started_at = now
        return now - max(self._machine.heartbeat, self._started_at)

    def _stalled_for(self) -> float:
        """Seconds since the latest snapshot when the cycle is stalled, else 0. An old
        heartbeat is checked by a catch-up that does not wait (the exact engine sleeps
        at rest: a late wake is no stall; a hung engine holds its lock)."""
        age = self._heartbeat_age()
        if age <= self._limits.stall_after or not self._scheduler.running:
            return 0.0  # (the cheap test first: a thread's liveness costs more)
        if self._scheduler.sync(wait=0, record=False):
            age = self._heartbeat_age()
        return age if age > self._limits.stall_after else 0.0

    # ------------------------------------------------------------------ addressing

    def resolve(
        self, index_group: int, index_offset: int, *, port: int | None = None
    ) -> tuple[ObjectDef, int, str | None]:
        """The object, axis and attribute at an address; `port`: the AMS port the request
        was sent to (a task serves only its own groups: 0x702), None: any. Addresses that
        resolve are remembered (there are only as many as objects × axes × ports; one
        that does not raises each time)."""
        key = (index_group, index_offset, port)
        got = self._resolved.get(key)
        if got is None:
            got = self._dictionary.resolve(index_group, index_offset, self._machine.axes, port)
            self._resolved[key] = got
        return got

    def lookup(self, name: str, axis: int) -> ObjectDef:
        """Object by name for `axis`; 0x703 when the axis does not exist."""
        obj = self._dictionary.by_name(name)
        if obj.scope == "axis" and axis not in self._machine.axes:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET, f"axis {axis} is not configured", obj.name
            )
        return obj

    # ------------------------------------------------------------------ reads

    def read(
        self,
        index_group: int,
        index_offset: int,
        length: int | None = None,
        snapshot: Snapshot | None = None,
        *,
        port: int | None = None,
        wait: float | None = None,
    ) -> bytes:
        """ADS bytes of one object (or attribute) from one snapshot (None: the one due
        now, `current` with `wait`, none caught up at rest when the object cannot vary
        at rest).

        `length` smaller than the object -> 0x705; larger -> the object's bytes only
        (ADS returns the bytes actually read, never more than requested). `port` as
        in `resolve`.
        """
        obj, axis, attr = self.resolve(index_group, index_offset, port=port)
        if attr:
            data = obj.attribute(attr)
        else:
            check_readable(obj)
            snap = snapshot or snapshot_for(self, obj, wait)
            data = snap.encode(obj, axis)
        if length is not None and length < len(data):
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"{obj.name}: read of {length} bytes, the value has {len(data)}",
                obj.name,
            )
        return data

    def read_many(
        self,
        requests: Iterable[tuple[int, int, int | None]],
        snapshot: Snapshot | None = None,
    ) -> list[bytes | AdsError]:
        """Batch read from one snapshot; each entry is bytes or the AdsError it raised."""
        snap = snapshot or self.current()
        out: list[bytes | AdsError] = []
        for ig, io, length in requests:
            try:
                out.append(self.read(ig, io, length, snap))
            except AdsError as exc:
                out.append(exc)
        return out

    # ------------------------------------------------------------------ writes: validation

    def prepare(
        self, index_group: int, index_offset: int, data: bytes, *, port: int | None = None
    ) -> PreparedWrite:
        """Validate ADS bytes for a write (0x702/0x703/0x704/0x705/0x706); `port` as in
        `resolve`."""
        obj, axis, attr = self.resolve(index_group, index_offset, port=port)
        if attr is not None:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDACCESS, f"attribute of {obj.name} is read-only", obj.name
            )
        _check_writable(obj)
        return PreparedWrite(obj, axis, self._noted(obj.decode, data))

    def prepare_name(self, name: str | ObjectDef, axis: int, value: Any) -> PreparedWrite:
        """Validate a decoded value (JSON, CLI) for a write; `name` may be an object the
        caller has resolved already (its axis is not checked again)."""
        obj = self.lookup(name, axis) if isinstance(name, str) else name
        _check_writable(obj)
        return PreparedWrite(obj, axis, self._noted(obj.coerce, value))

    def _noted(self, convert: Callable[[Any], Any], value: Any) -> Any:
        """`convert(value)`; a refused value (0x706) is also put in the error list and
        `SIM::last_error` (`_note_refusal`), not only answered."""
        try:
            return convert(value)
        except AdsError as exc:
            self._note_refusal(exc, "write")
            raise

    def _note_refusal(self, exc: AdsError, what: str) -> None:
        """Put a refused write or NC text (`REPORTED_REFUSALS`) in the error list, where
        `SIM::last_error` and every interface's error list show it: at most
        `REFUSALS_PER_SECOND`, the rest counted. Recorded at the next cycle boundary,
        without waiting for it (the caller is answering a request)."""
        if exc.code not in REPORTED_REFUSALS:
            return
        second = float(int(time.monotonic()))
        with self._refusal_lock:
            start, count = self._refusal_window
            if start != second:
                start, count = second, 0
            if count >= REFUSALS_PER_SECOND:
                self._refusals_unreported += 1
                return
            self._refusal_window = (start, count + 1)
        text = f"{what} refused: {exc.message} (ADS 0x{exc.code:X})"
        self._machine.record(Diagnostic("error", text, entry=exc.name))

    # ------------------------------------------------------------------ writes: queueing

    def submit_writes(self, writes: Sequence[PreparedWrite]) -> Pending:
        """Queue validated writes as one operation (all applied in the same cycle).

        The outcome is a tuple with None or the AdsError of each item. A command object
        must be written on its own; it runs now and its outcome is the CommandResult.
        """
        commands = [w for w in writes if w.obj.command]
        if commands:
            if len(writes) != 1:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDACCESS,
                    f"{commands[0].obj.name} must be written on its own",
                    commands[0].obj.name,
                )
            result = self.commands.run(commands[0].obj.command or "", commands[0].value)
            if not result.ok:
                raise result.error()
            return resolved(result)
        self._refuse_when_stalled()
        return self._scheduler.submit(WriteObjects(tuple((w.obj, w.axis, w.value) for w in writes)))

    async def apply_writes(
        self, writes: Sequence[PreparedWrite], timeout: float | None = None
    ) -> list[AdsError | None]:
        """Queue validated writes as one operation and wait until the cycle applied them.

        Returns one entry per write: None (applied) or the AdsError it raised when it
        was applied (e.g. 0x708 for a move while the axis is busy). Raises AdsError for
        the whole batch: 0x707 (stalled, nothing queued), 0x719 (not applied in time,
        withdrawn), or the error of a command.
        """
        if any(w.obj.command for w in writes):  # run in a worker thread, done on return
            await asyncio.to_thread(self.submit_writes, writes)
            return [None] * len(writes)
        pending = self.submit_writes(writes)
        outcome = await self._settle(pending, timeout)
        if outcome is None:  # stepped: queued, applied at the next step
            return [None] * len(writes)
        return [e if isinstance(e, AdsError) else None for e in outcome]

    async def _settle(self, pending: Pending, timeout: float | None = None) -> Any:
        """Wait for a queued operation (cycles that run by themselves; stepped: None at
        once). Also before they started: `geo-server run` starts its interfaces first,
        and a write answered then, before its cycle ran, was not seen by a read sent
        after the answer.

        After `timeout` (default `write_timeout`) the operation is withdrawn and 0x719
        raised; if a cycle has taken it already, wait on for its outcome (withdrawal is
        retried in case the cycle process was merely stopped while taking operations).
        """
        if pending.done() or self._stepped():
            return pending.result() if pending.done() else None
        limit = self._limits.write_timeout if timeout is None else timeout
        wrapped = asyncio.wrap_future(pending)
        done, _ = await asyncio.wait({wrapped}, timeout=limit)
        while not done:
            if pending.withdraw():
                raise _not_applied(limit)
            done, _ = await asyncio.wait({wrapped}, timeout=0.25)
        return wrapped.result()

    def _settle_sync(self, pending: Pending, timeout: float) -> Any:
        """`_settle` for a caller's thread (commands, a measurement)."""
        if pending.done() or self._stepped():
            return pending.result() if pending.done() else None
        deadline = time.monotonic() + timeout
        while True:
            try:
                return pending.result(timeout=max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                if pending.withdraw():
                    raise _not_applied(timeout) from None
                deadline = time.monotonic() + 0.25

    def _stepped(self) -> bool:
        """Nobody runs the cycles but the owner's steps: a queued operation waits for
        them, not for the caller."""
        return self._scheduler.mode == "stepped" and not self._scheduler.running

    def _refuse_when_stalled(self) -> None:
        stalled = self._stalled_for()
        if stalled:
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY,
                f"the GEO cycle is stalled (no cycle for {stalled:.1f} s): nothing queued",
            )

    # ------------------------------------------------------------------ subscriptions

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        """Call `callback(snapshot)` after every published cycle, in cycle order, on the
        thread that publishes it. The exact engine publishes only the cycles someone
        looks at (and every cycle while `demand_cycles()` is held, as `subscribe_changes`
        and a recording do), and hands a catch-up's snapshots out together after its
        last cycle (or every `seam.HELD_MAX`); the other engines publish every cycle as
        it ends.

        Keep it short and hand work to your own thread or event loop. Returns a function
        that unsubscribes.
        """
        return self._machine.subscribe(callback)

    def subscribe_changes(
        self,
        objects: Iterable[tuple[str, int]],
        callback: Callable[[dict[tuple[str, int], Any]], None],
    ) -> Callable[[], None]:
        """Call `callback({(name, axis): value})` after a cycle in which any of them changed."""
        keys = [(self.lookup(n, a), a) for n, a in objects]
        last: dict[tuple[str, int], Any] = {}

        def on_cycle(snap: Snapshot) -> None:
            changed = {}
            for obj, axis in keys:
                v = snap.value(obj, axis)
                if (obj.name, axis) not in last or last[(obj.name, axis)] != v:
                    last[(obj.name, axis)] = v
                    changed[(obj.name, axis)] = v
            if changed:
                callback(changed)

        unsubscribe = self.subscribe(on_cycle)
        release = self._scheduler.demand_every_cycle()  # no change may go unseen

        def stop() -> None:
            unsubscribe()
            release()

        return stop

    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        """Call `callback(event)` for every new warning or error (machine or server).

        It runs on the reporting thread — the cycle's, with the cycle's lock held — so
        it must hand the event on and return: calling `status`, `report` or `current`
        from it would wait for the cycle it is called from."""
        return self._machine.subscribe_events(callback)

    def demand_cycles(self, demand: CycleDemand | None = None) -> Callable[[], None]:
        """Publish the cycles `demand` wants until the returned function is called (ADS
        notifications; docs/design.md §13); None: every cycle's snapshot, also at rest
        (an observer that samples every cycle: a recording). An engine that cannot
        choose (the cycle process) publishes every cycle's snapshot meanwhile."""
        if demand is not None and self._engine is not None:
            return self._engine.demand_cycles(demand)
        return self._scheduler.demand_every_cycle()

    # ------------------------------------------------------------------ status, events

    def status(self) -> dict[str, Any]:
        """Cycle count, cycle time, lateness, overruns, and whether the cycle is stalled.

        A status is an observation like a read (docs/design.md §13): the exact engine
        catches up first, so `cycle` is the cycle due now (`_catch_up`)."""
        self._catch_up()
        st = dict(self._scheduler.status())
        stalled = self._stalled_for()
        st["stalled"] = bool(stalled)
        st["stalled_for_s"] = round(stalled, 3)
        axes = self._machine.cfg.axes
        st["axis_names"] = {str(a): axes[a].params.name for a in self._machine.axes}
        st["faults"] = self.faults.status()
        st["refusals_unreported"] = self._refusals_unreported
        recording = self.recordings.status()
        if recording is not None:
            st["recording"] = recording
        # a copy of each: an interface's counters (a dict) go on counting on their own
        # thread while this status is serialized and read (docs/design.md §7.1)
        extra = dict(self.status_extra)  # (one C call: atomic against the loop adding)
        st.update({k: dict(v) if isinstance(v, dict) else v for k, v in extra.items()})
        return st

    def errors(self) -> list[dict[str, Any]]:
        """The last 100 warnings and errors, oldest first."""
        return [e.as_dict() for e in list(self._machine.events)]

    def report(self, message: str, *, severity: str = "error", error_id: int = 0) -> Pending:
        """Record a warning or error the server itself found (a rejected reload, a second
        server with this machine's name) in the machine's error list: listed by
        `errors()`, shown by `SIM::last_error(_id)`, passed to the event listeners. Never
        refused; with the cycle in its own process it lands at the next cycle boundary
        (while that cycle is stalled: once it resumes). Its cycle is the one due now."""
        self._catch_up()
        return self._machine.record(Diagnostic(severity, message, error_id=error_id))

    def _catch_up(self) -> None:
        """Before a status or a server's own error: the exact engine computes up to the
        cycle due now (docs/design.md §13) — not while the cycle is stalled, when the
        answer must come at once and tells the last cycle there is."""
        if not self._stalled_for():  # (briefly: a status must answer, caught up or not)
            self._scheduler.sync(wait=STATUS_SYNC_WAIT, record=False)

    def _report_now(self, message: str, error_id: int = 0) -> None:
        """`report` and, when cycles run, wait (briefly) until it is in the list, so a
        client that asks for the errors right after the answer finds it."""
        pending = self.report(message, error_id=error_id)
        with contextlib.suppress(TimeoutError):
            pending.result(timeout=self._limits.write_timeout if self._scheduler.running else 0)


def _conforms(service: ObjectService) -> Measured:
    """(mypy) The service is what the layers below it type it as (`geo_server.seam`)."""
    return service


def _conforms_opcua(service: ObjectService) -> OpcUaService:
    """(mypy) The service is what OPC UA types it as, in its process or its own."""
    return service


def is_command(obj: ObjectDef) -> bool:
    """Does writing `obj` run a command (reload/save/volcomp_update) rather than queue a
    value?"""
    return obj.command is not None


def varies_at_rest(obj: ObjectDef) -> bool:
    """Whether `obj` can change while the machine is quiescent (`varies_at_rest` in
    objects.toml; docs/design.md §13): an on-change observer of any other object needs
    no snapshot of a quiescent cycle."""
    return obj.varies_at_rest


def snapshot_for(service: ObjectService, obj: ObjectDef, wait: float | None = None) -> Snapshot:
    """The snapshot a read of `obj` alone is answered from: the one due now, none caught
    up at rest when `obj` cannot vary at rest (`ObjectService.current`; docs/design.md
    §13, *Reads at rest*)."""
    return service.current(wait=wait, at_rest_ok=not varies_at_rest(obj))


def rests_on(service: ObjectService, snap: Snapshot | None) -> bool:
    """Whether `snap` is the snapshot a read of objects that cannot vary at rest is
    answered from now, without a catch-up (docs/design.md §13, *Reads at rest*), so an
    answer kept from it is still the answer (*Repeated reads*): the machine's
    `rest_snapshot` (the published one while it shows its rest; kept by the cycle, so
    this is one look on every request), while the heartbeat is younger than half of
    `stall_after`. A read at rest catches up anyway when it is older (the engine wakes
    only every second at rest): then the stall watch finds it fresh, instead of checking
    it with a catch-up that does not wait and would call a wake of the engine under way
    a stall (0x707). (A heartbeat this young is no stall.) One function, no calls: a
    request runs it with cold caches after a pause."""
    m = service._machine
    return (
        snap is not None
        and snap is m.rest_snapshot
        and time.monotonic() - m.heartbeat <= service._rest_fresh
    )


def check_readable(obj: ObjectDef) -> None:
    """0x704 for a write-only object (a read by address or by Zenoh key)."""
    if not obj.readable:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, f"{obj.name} is write-only", obj.name)


def _check_writable(obj: ObjectDef) -> None:
    if not obj.writable:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, f"{obj.name} is read-only", obj.name)


def _by_slot(item: tuple[str, int]) -> int:
    return item[1]


def _not_applied(limit: float) -> AdsError:
    """0x719: a queued operation withdrawn after `limit` seconds without its cycle."""
    return AdsError(
        AdsErrorCode.DEVICE_TIMEOUT,
        f"not applied within {limit:g} s (the GEO cycle is late or stalled); "
        "withdrawn, it will not take effect",
    )


__all__ = [
    "ADSERR_DEVICE_SYNTAX",
    "CommandResult",
    "CompKind",
    "MachineInfo",
    "ObjectService",
    "PreparedWrite",
    "ServiceLimits",
    "Stepper",
    "check_readable",
    "format_value",
    "is_command",
    "rests_on",
    "snapshot_for",
    "varies_at_rest",
]
