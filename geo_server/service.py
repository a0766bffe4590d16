"""The object service: the one API every transport calls.

Reads
    `read(group, offset, length)` answers from the latest published snapshot with ADS
    bytes, or raises `AdsError` (0x702 group, 0x703 offset or axis, 0x705 length). A
    read never returns more bytes than the object has; `read_many` answers a batch from
    one snapshot (sum reads, block reads). While cycles run by themselves and the latest
    cycle has not advanced for `ServiceLimits.stall_after`, the GEO cycle is *stalled*: reads
    raise 0x707 (device not ready) instead of serving an ever older picture as current,
    and `status()` says `"stalled": true` (status itself is always answered).

Writes: the write lifecycle lives here, once, for every transport
    `prepare`/`prepare_name` validate at once (0x702…0x706). `write_applied` /
    `write_name_applied` / `apply_writes` queue the values for the next cycle boundary
    and return when the cycle that applied them has published its snapshot — so a read
    sent after the answer sees the value. In stepped mode nobody runs that cycle until
    the test steps: they return as soon as the values are queued. A write not applied
    within the timeout is *withdrawn* before the caller hears 0x719: a write reported as
    failed never takes effect later. One the cycle has already taken is always
    acknowledged, however late (it will take effect). While the cycle is stalled new
    writes are refused at once with 0x707 and are not queued.

Commands
    Objects marked `command` in the dictionary (`SIM::reload`, `SIM::save`) run that
    command instead of queueing a value; commands read or write list files, so
    `*_applied` run them in a worker thread, never on an event loop. One command runs at
    a time; another one waits at most `command_wait` and then gets 0x708 (busy).

Transports never reach into the kernel or the machine; they hold an `ObjectService`
and map its `AdsError`s to their own codes.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.faults import Fault, FaultError, Faults, parse_fault
from geo_server.listfile import ListFileError, compare_max_points, load_machine, rewrite_values
from geo_server.listfile.values import Reporter
from geo_server.machine.nc import NcError, parse_program
from geo_server.machine.port import (
    CycleRunner,
    MachinePort,
    Pending,
    Reload,
    Reset,
    SensorFault,
    StartProgram,
    VolcUpdate,
    WriteObjects,
    chained,
    resolved,
    varies_at_rest,
)
from geo_server.model import CompKind, Diagnostic, MachineConfig
from geo_server.paths import is_product_data
from geo_server.recorder import Recorder, RecordSpec, SelectionError, TraceFileError
from geo_server.recorder.paths import check_target, default_record_dir, machine_files, output_path
from geo_server.recorder.recorder import RecorderLimits
from geo_server.snapshot import Snapshot
from geo_server.twin.measure import LiveBench, MeasureError, StepBench, plan_from_json, run_test
from geo_server.volcomp.config import reload_compensation
from geo_server.volcomp.kernel import VOLC_ERROR

#: ADS "syntax error in file" — a reload rejected because a list has errors.
ADSERR_DEVICE_SYNTAX = AdsErrorCode.DEVICE_SYNTAX
#: the longest a status or a server's own error waits for another thread's catch-up
#: (seconds; a fleet's status asks every machine in turn)
STATUS_SYNC_WAIT = 0.02


@dataclass(frozen=True)
class ServiceLimits:
    """Time and size bounds of the object service (README, *Limits*)."""

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


@dataclass(frozen=True)
class PreparedWrite:
    """A validated write: the object, the axis (0 for machine objects) and the value."""

    obj: ObjectDef
    axis: int
    value: Any


@dataclass
class CommandResult:
    """Outcome of `reload` / `save`, as JSON for the transports."""

    ok: bool
    command: str
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    #: The ADS code of a failure: 0x70D list errors, 0x708 busy, 0x719 not applied in time.
    code: int = 0
    #: The manual's error ID of the first problem (e.g. 110591), 0 if none has one.
    error_id: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "command": self.command,
            "errors": self.errors,
            "warnings": self.warnings,
            "files": self.files,
        }

    @property
    def message(self) -> str:
        """One line saying what happened (the reason of a rejection first)."""
        if self.ok:
            return f"{self.command} done" + (f": {', '.join(self.files)}" if self.files else "")
        head = (
            "reload rejected, machine unchanged"
            if self.command == "reload"
            else f"{self.command} failed"
        )
        return f"{head}: {'; '.join(self.errors)}"

    def error(self) -> AdsError:
        return AdsError(self.code or ADSERR_DEVICE_SYNTAX, self.message, self.command)


def format_value(obj: ObjectDef, value: Any) -> str:
    """A value as a list-file token: integers plain, REAL64 shortest round-trip form."""
    if obj.type.name == "BOOLEAN":
        return "1" if value else "0"
    if obj.type.name == "REAL64":
        f = float(value)
        return str(int(f)) if f.is_integer() and abs(f) < 1e15 else repr(f)
    return str(round(value))


class ObjectService:
    """Reads, writes, batches, subscriptions and commands over one machine."""

    def __init__(
        self,
        machine: MachinePort,
        scheduler: CycleRunner | None = None,
        limits: ServiceLimits | None = None,
    ) -> None:
        if scheduler is None:
            from geo_server.machine.scheduler import Scheduler

            scheduler = Scheduler(machine, mode="stepped")  # type: ignore[arg-type]
        self.machine = machine
        self.scheduler = scheduler
        self.limits = limits or ServiceLimits()
        if hasattr(scheduler, "idle_wake"):  # an engine that sleeps at rest: a heartbeat
            scheduler.idle_wake = min(scheduler.idle_wake, self.limits.stall_after / 2)
        self.dictionary = machine.dictionary
        self._command_lock = threading.Lock()
        self._measure_lock = threading.Lock()
        self._measure_cancel = threading.Event()
        #: Items merged into `status()` (interfaces add what they observe).
        self.status_extra: dict[str, Any] = {}
        self._started_at = 0.0
        #: injected faults (docs/faults.md); the transports ask `faults.decide`
        self.faults = Faults()
        #: the recording a command started (docs/recorder.md §7) and where it goes
        self.recording: Recorder | None = None
        self._recording_lock = threading.Lock()
        #: where recordings asked for over an interface go (`run --record-dir`); None:
        #: `recordings/` beside the start-up list (recorder.paths.default_record_dir)
        self.record_dir: Path | None = None
        #: bounds of a recording (README *Limits*, docs/recorder.md §8)
        self.record_limits = RecorderLimits()

    # ------------------------------------------------------------------ state

    @property
    def axes(self) -> tuple[int, ...]:
        return self.machine.axes

    @property
    def cycle_s(self) -> float:
        return self.machine.cycle_s

    @property
    def running(self) -> bool:
        """True while cycles run by themselves (real time, free-running)."""
        return self.scheduler.running

    @property
    def snapshot(self) -> Snapshot:
        """The snapshot of the cycle due now (the exact engine catches up first), also
        while the cycle is stalled — then the last one there is (see `current`)."""
        return self.fresh()

    def stalled_for(self) -> float:
        """Seconds since the latest snapshot when the cycle is stalled, else 0. An old
        heartbeat is checked by a catch-up that does not wait (the exact engine sleeps
        at rest: a late wake is no stall; a hung engine holds its lock)."""
        if not self.running:
            return 0.0
        if not self._started_at:
            self._started_at = time.monotonic()
        age = time.monotonic() - max(self.machine.heartbeat, self._started_at)
        if age > self.limits.stall_after and self.scheduler.sync(wait=0, record=False):
            age = time.monotonic() - max(self.machine.heartbeat, self._started_at)
        return age if age > self.limits.stall_after else 0.0

    def fresh(self) -> Snapshot:
        """The snapshot of the cycle due now (docs/design.md §13): the exact engine
        catches up first; other engines publish on their own."""
        self.scheduler.sync()
        return self.machine.snapshot

    def current(self) -> Snapshot:
        """The snapshot of the cycle due now, or 0x707 while the GEO cycle is stalled or
        cannot catch up in time."""
        if not self.scheduler.sync():
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY,
                "the GEO cycle is busy catching up (the host stalled): no current values",
            )
        snap = self.machine.snapshot
        stalled = self.stalled_for()
        if stalled:
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY,
                f"the GEO cycle is stalled: no cycle for {stalled:.1f} s (last cycle {snap.cycle})",
            )
        return snap

    # ------------------------------------------------------------------ addressing

    def resolve(self, index_group: int, index_offset: int) -> tuple[ObjectDef, int, str | None]:
        return self.dictionary.resolve(index_group, index_offset, self.axes)

    @staticmethod
    def varies_at_rest(obj: ObjectDef) -> bool:
        """Whether `obj` can change while the machine is quiescent (`machine/port.py`
        `varies_at_rest`; docs/design.md §13): an on-change observer of any other object
        needs no snapshot of a quiescent cycle."""
        return varies_at_rest(obj.name)

    def lookup(self, name: str, axis: int) -> ObjectDef:
        """Object by name for `axis`; 0x703 when the axis does not exist."""
        obj = self.dictionary.by_name(name)
        if obj.scope == "axis" and axis not in self.axes:
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
    ) -> bytes:
        """ADS bytes of one object (or attribute) from one snapshot.

        `length` smaller than the object -> 0x705; larger -> the object's bytes only
        (ADS returns the bytes actually read, never more than requested).
        """
        obj, axis, attr = self.resolve(index_group, index_offset)
        if attr:
            data = obj.attribute(attr)
        else:
            check_readable(obj)
            data = (snapshot or self.current()).encode(obj, axis)
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

    def read_name(self, name: str, axis: int = 0, snapshot: Snapshot | None = None) -> Any:
        """Decoded value of an object by name (a write-only one shows what its snapshot
        column holds: the Modbus view; ADS and Zenoh refuse it with `check_readable`)."""
        obj = self.lookup(name, axis)
        return (snapshot or self.current()).value(obj, axis)

    def read_axis(self, axis: int, group: str = "geo") -> dict[str, Any]:
        """Every object of `group` for one axis, decoded, from one snapshot."""
        snap = self.current()
        return {
            o.name: snap.value(o, axis)
            for o in self.dictionary.group_objects(group)
            if axis in self.axes
        }

    # ------------------------------------------------------------------ writes: validation

    def prepare(self, index_group: int, index_offset: int, data: bytes) -> PreparedWrite:
        """Validate ADS bytes for a write (0x702/0x703/0x704/0x705/0x706)."""
        obj, axis, attr = self.resolve(index_group, index_offset)
        if attr is not None:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDACCESS, f"attribute of {obj.name} is read-only", obj.name
            )
        self._check_writable(obj)
        return PreparedWrite(obj, axis, obj.decode(data))

    def prepare_name(self, name: str, axis: int, value: Any) -> PreparedWrite:
        """Validate a decoded value (JSON, CLI) for a write."""
        obj = self.lookup(name, axis)
        self._check_writable(obj)
        return PreparedWrite(obj, axis, obj.coerce(value))

    def prepare_object(self, obj: ObjectDef, axis: int, value: Any) -> PreparedWrite:
        """Validate a value for an object the caller has already resolved."""
        self._check_writable(obj)
        return PreparedWrite(obj, axis, obj.coerce(value))

    @staticmethod
    def is_command(obj: ObjectDef) -> bool:
        """Does writing `obj` run a command (reload/save) rather than queue a value?"""
        return obj.command is not None

    def _check_writable(self, obj: ObjectDef) -> None:
        if not obj.writable:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, f"{obj.name} is read-only", obj.name)

    # ------------------------------------------------------------------ writes: queueing

    def write(self, index_group: int, index_offset: int, data: bytes) -> Pending:
        """Validate ADS bytes now and apply them at the next cycle boundary (a command
        object runs its command here, in the caller's thread). The future's result is
        None, or it raises the error applying the value raised."""
        return _single(self.submit_writes([self.prepare(index_group, index_offset, data)]))

    def write_name(self, name: str, axis: int, value: Any) -> Pending:
        """Validate a decoded value (JSON, CLI) and apply it at the next cycle boundary."""
        return _single(self.submit_writes([self.prepare_name(name, axis, value)]))

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
            result = self.run_command(commands[0].obj.command or "", commands[0].value)
            if not result.ok:
                raise result.error()
            return resolved(result)
        self._refuse_when_stalled()
        return self.scheduler.submit(
            WriteObjects(tuple((w.obj.name, w.axis, w.value) for w in writes))
        )

    async def write_applied(
        self, index_group: int, index_offset: int, data: bytes, *, timeout: float | None = None
    ) -> None:
        """Validate, queue and wait until applied (see the module docstring)."""
        errors = await self.apply_writes([self.prepare(index_group, index_offset, data)], timeout)
        if errors[0] is not None:
            raise errors[0]

    async def write_name_applied(
        self, name: str, axis: int, value: Any, *, timeout: float | None = None
    ) -> Any:
        """`write_applied` by name with a decoded value; returns the value as stored."""
        w = self.prepare_name(name, axis, value)
        errors = await self.apply_writes([w], timeout)
        if errors[0] is not None:
            raise errors[0]
        return w.value

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
        outcome = await self.settle(pending, timeout)
        if outcome is None:  # stepped: queued, applied at the next step
            return [None] * len(writes)
        return [e if isinstance(e, AdsError) else None for e in outcome]

    async def settle(self, pending: Pending, timeout: float | None = None) -> Any:
        """Wait for a queued operation (running cycles only; stepped: None at once).

        After `timeout` (default `write_timeout`) the operation is withdrawn and 0x719
        raised; if a cycle has taken it already, wait on for its outcome (withdrawal is
        retried in case the cycle process was merely stopped while taking operations).
        """
        if pending.done() or not self.running:
            return pending.result() if pending.done() else None
        limit = self.limits.write_timeout if timeout is None else timeout
        wrapped = asyncio.wrap_future(pending)
        done, _ = await asyncio.wait({wrapped}, timeout=limit)
        while not done:
            if pending.withdraw():
                raise _not_applied(limit)
            done, _ = await asyncio.wait({wrapped}, timeout=0.25)
        return wrapped.result()

    def settle_sync(self, pending: Pending, timeout: float) -> Any:
        """`settle` for a caller's thread (commands)."""
        if pending.done() or not self.running:
            return pending.result() if pending.done() else None
        deadline = time.monotonic() + timeout
        while True:
            try:
                return pending.result(timeout=max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                if pending.withdraw():
                    raise _not_applied(timeout) from None
                deadline = time.monotonic() + 0.25

    def _refuse_when_stalled(self) -> None:
        stalled = self.stalled_for()
        if stalled:
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY,
                f"the GEO cycle is stalled (no cycle for {stalled:.1f} s): nothing queued",
            )

    # ------------------------------------------------------------------ subscriptions

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        """Call `callback(snapshot)` after every published cycle, on the thread that
        publishes it. The exact engine publishes only the cycles someone looks at (and
        every cycle while `scheduler.demand_every_cycle()` is held, as `subscribe_changes`
        and the ADS notifications do); the other engines publish every cycle.

        Keep it short and hand work to your own thread or event loop. Returns a function
        that unsubscribes.
        """
        return self.machine.subscribe(callback)

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
        release = self.scheduler.demand_every_cycle()  # no change may go unseen

        def stop() -> None:
            unsubscribe()
            release()

        return stop

    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        """Call `callback(event)` for every new warning or error (machine or server).

        It runs on the reporting thread — the cycle's, with the cycle's lock held — so
        it must hand the event on and return: calling `status`, `report`, `fresh` or
        `current` from it would wait for the cycle it is called from."""
        return self.machine.subscribe_events(callback)

    # ------------------------------------------------------------------ status, events

    def status(self) -> dict[str, Any]:
        """Cycle count, cycle time, lateness, overruns, and whether the cycle is stalled.

        A status is an observation like a read (docs/design.md §13): the exact engine
        catches up first, so `cycle` is the cycle due now (`_catch_up`)."""
        self._catch_up()
        st = dict(self.scheduler.status())
        stalled = self.stalled_for()
        st["stalled"] = bool(stalled)
        st["stalled_for_s"] = round(stalled, 3)
        st["axis_names"] = {str(a): self.machine.cfg.axes[a].params.name for a in self.axes}
        st["faults"] = self.faults.status()
        if self.recording is not None:
            st["recording"] = {**self.recording.status(), "file": str(self.recording.out)}
        st.update(self.status_extra)
        return st

    # ------------------------------------------------------------------ faults

    def inject_fault(self, fault: str | Fault) -> dict[str, Any]:
        """Inject a fault (text as in docs/faults.md, or parsed) and return it as listed
        in `status()["faults"]`. Transport faults act on the next request; a cycle
        overrun from the next cycle on; a sensor fault at the next cycle boundary.
        Raises `FaultError` (a clear message) for a fault this machine cannot have."""
        f = parse_fault(fault) if isinstance(fault, str) else fault
        if f.target == "cycle":
            return self._inject_overrun(f)
        if f.target == "sensor":
            return self._inject_sensor(f)
        return self.faults.add(f).as_dict()

    def _inject_overrun(self, f: Fault) -> dict[str, Any]:
        set_overrun = getattr(self.scheduler, "set_overrun", None)
        if set_overrun is None:
            raise FaultError(
                f"fault {f.text!r}: cycle overruns need the GEO cycle in a thread "
                "(geo-server run --cycle-in thread)"
            )
        active = self.faults.of("cycle")
        if active:
            raise FaultError(
                f"fault {f.text!r}: overrun fault {active[0].ident} is active; clear it first"
            )
        cycles = max(1, round(f.value / (self.cycle_s * 1000)))
        added = self.faults.add(f)
        set_overrun(cycles, f.every, lambda: self.faults.hit(added))
        return added.as_dict()

    def _inject_sensor(self, f: Fault) -> dict[str, Any]:
        twin = getattr(self.machine, "twin", None)
        if twin is None:
            raise FaultError(
                f"fault {f.text!r}: sensor faults need the GEO cycle in a thread "
                "(geo-server run --cycle-in thread)"
            )
        try:
            k = twin.sensor_index(f.sensor)
        except LookupError as exc:
            raise FaultError(f"fault {f.text!r}: {exc}") from None
        if any(twin.sensor_index(g.sensor) == k for g in self.faults.of("sensor")):
            raise FaultError(f"fault {f.text!r}: that sensor has a fault already; clear it first")
        added = self.faults.add(f)
        self._settle_op(SensorFault(k, f.kind, f.value))
        return added.as_dict()

    # ------------------------------------------------------------------ recording

    def start_recording(
        self,
        spec: RecordSpec | dict[str, Any],
        out: str | Path = "geo-trace.csv",
        name: str = "",
        *,
        overwrite: bool = False,
        local: bool = False,
    ) -> dict[str, Any]:
        """Start recording `spec` (docs/recorder.md) into `out` (CSV or .parquet, the
        inputs beside it as `<stem>.inputs.jsonl`), streamed while it records and put in
        place by `stop_recording`. An `out` from an interface (not `local`, the command
        line's own) is a file name in the recordings folder, an existing file replaced
        only with `overwrite`, never a file of the machine (recorder.paths); anything
        else is refused with 0x70B, as are settings outside `record_limits`. One
        recording at a time: another one is refused with 0x708."""
        with self._recording_lock:
            if self.recording is not None:
                raise AdsError(
                    AdsErrorCode.DEVICE_BUSY, "a recording runs already: stop it first", "record"
                )
            try:
                if isinstance(spec, dict):
                    spec = RecordSpec.from_json(spec, self.record_limits)
                protected = machine_files(self.machine.cfg)
                if local:
                    target = Path(out)
                    check_target(target, overwrite=True, protected=protected)
                else:
                    folder = self.record_dir or default_record_dir(self.machine.cfg.startup_path)
                    folder.mkdir(parents=True, exist_ok=True)
                    target = output_path(
                        str(out),
                        folder,
                        overwrite=overwrite,
                        protected=protected,
                        max_text=self.record_limits.max_text,
                    )
                rec = Recorder(self, spec, name, out=target, limits=self.record_limits)
                self.recording = rec.start()
            except (SelectionError, ValueError) as exc:
                raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, str(exc), "record") from None
            except OSError as exc:  # the folder cannot be made or written
                raise AdsError(
                    AdsErrorCode.DEVICE_ERROR, f"record: cannot write {out}: {exc}", "record"
                ) from None
            return {**rec.status(), "file": str(target)}

    def stop_recording(self) -> dict[str, Any]:
        """Stop the recording, write the rows it still holds and put its trace and
        inputs in place (in the calling thread: call it off the event loop); what was
        written."""
        with self._recording_lock:
            rec, self.recording = self.recording, None
        if rec is None:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDSTATE, "no recording runs", "record")
        try:
            return rec.finish()
        except (OSError, TraceFileError) as exc:
            raise AdsError(AdsErrorCode.DEVICE_ERROR, str(exc), "record") from None

    def clear_faults(self, ident: int | None = None) -> list[dict[str, Any]]:
        """Clear fault `ident` (None: every fault) and undo what it did: overruns stop,
        a sensor reads its node again from its next sample. Returns the faults cleared;
        an `ident` that is not active raises `FaultError`."""
        gone = self.faults.remove(ident)
        if ident is not None and not gone:
            active = ", ".join(str(f["id"]) for f in self.faults.status()) or "none"
            raise FaultError(f"no active fault {ident} (active: {active})")
        for f in gone:
            if f.target == "cycle":
                self.scheduler.set_overrun(0, 0)  # type: ignore[attr-defined]
            elif f.target == "sensor":
                twin = self.machine.twin  # type: ignore[attr-defined]
                self._settle_op(SensorFault(twin.sensor_index(f.sensor), ""))
        return [f.as_dict() for f in gone]

    def _settle_op(self, op: SensorFault) -> None:
        """Queue a machine operation; with cycles running, wait until it is applied."""
        pending = self.scheduler.submit(op)
        if self.running:
            self.settle_sync(pending, self.limits.write_timeout)

    def errors(self) -> list[dict[str, Any]]:
        """The last 100 warnings and errors, oldest first."""
        return [e.as_dict() for e in list(self.machine.events)]

    def report(self, message: str, *, severity: str = "error", error_id: int = 0) -> Pending:
        """Record a warning or error the server itself found (a rejected reload, a second
        server with this machine's name) in the machine's error list: listed by
        `errors()`, shown by `SIM::last_error(_id)`, passed to the event listeners. Never
        refused; with the cycle in its own process it lands at the next cycle boundary
        (while that cycle is stalled: once it resumes). Its cycle is the one due now."""
        self._catch_up()
        return self.machine.record(Diagnostic(severity, message, error_id=error_id))

    def _catch_up(self) -> None:
        """Before a status or a server's own error: the exact engine computes up to the
        cycle due now (docs/design.md §13) — not while the cycle is stalled, when the
        answer must come at once and tells the last cycle there is."""
        if not self.stalled_for():  # (briefly: a status must answer, caught up or not)
            self.scheduler.sync(wait=STATUS_SYNC_WAIT, record=False)

    def _report_now(self, message: str, error_id: int = 0) -> None:
        """`report` and, when cycles run, wait (briefly) until it is in the list, so a
        client that asks for the errors right after the answer finds it."""
        pending = self.report(message, error_id=error_id)
        with contextlib.suppress(TimeoutError):
            pending.result(timeout=self.limits.write_timeout if self.running else 0)

    def step(self, n: int = 1) -> Snapshot:
        """Run `n` cycles (stepped mode)."""
        self.scheduler.step(n)
        return self.snapshot

    # ------------------------------------------------------------------ NC, reset

    def run_nc(self, text: str) -> Pending:
        """Parse NC lines now and start them as MDI lines at the next cycle boundary.

        Bad text -> 0x70D naming the line; text over `nc_max_bytes` or `nc_max_lines`
        -> 0x705 (a long program belongs in a file: `geo-server run --program`)."""
        size = len(text.encode("utf-8", errors="replace"))
        lines = text.count("\n") + 1
        lim = self.limits
        if size > lim.nc_max_bytes or lines > lim.nc_max_lines:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"NC text of {size} bytes / {lines} lines exceeds {lim.nc_max_bytes} bytes / "
                f"{lim.nc_max_lines} lines",
                "nc",
            )
        try:
            prog = parse_program(text, self.machine.names, mdi=True)
        except NcError as exc:
            raise AdsError(ADSERR_DEVICE_SYNTAX, str(exc), "nc") from None
        self._refuse_when_stalled()
        return self.scheduler.submit(StartProgram(prog, True, text))

    async def run_nc_applied(self, text: str, *, timeout: float | None = None) -> int:
        """`run_nc` parsed in a worker thread; returns the cycle that started it."""
        pending = await asyncio.to_thread(self.run_nc, text)
        await self.settle(pending, timeout)
        return self.snapshot.cycle

    def reset(self) -> Pending:
        """CNC reset at the next cycle boundary: program stopped, axes stopped."""
        self._refuse_when_stalled()
        return self.scheduler.submit(Reset())

    async def reset_applied(self, *, timeout: float | None = None) -> int:
        await self.settle(self.reset(), timeout)
        return self.snapshot.cycle

    # ------------------------------------------------------------------ commands

    def measure(self, spec: Any) -> dict[str, Any]:
        """An ISO 230-2 positioning test on the twin (docs/twin.md), for `cmd/measure`:
        `spec` is the JSON plan of `twin.measure.plan_from_json`; returns the evaluation
        as a dict. Blocks until done: call it from a worker thread. On a running machine
        it moves the axis through object writes and waits for the cycles (at most
        `limits.measure_deadline` in all; `cancel_measure` ends it); in stepped mode it
        steps the machine itself. A bad plan is 0x706; one measurement at a time, and a
        test that cannot go on (axis not homed, moved by someone else, an NC error) is
        0x708."""
        try:
            plan = plan_from_json(spec, self.machine.cfg)
        except MeasureError as exc:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDDATA, str(exc), "measure") from None
        if not self._measure_lock.acquire(blocking=False):
            raise AdsError(AdsErrorCode.DEVICE_BUSY, "a measurement is running", "measure")
        self._measure_cancel.clear()
        try:
            bench = (
                LiveBench(
                    self,
                    timeout_s=self.limits.command_wait + 60.0,
                    deadline_s=self.limits.measure_deadline,
                    cancel=self._measure_cancel,
                )
                if self.running
                else StepBench(self)
            )
            started = time.monotonic()
            ev = run_test(bench, plan)
        except MeasureError as exc:
            raise AdsError(AdsErrorCode.DEVICE_BUSY, str(exc), "measure") from None
        finally:
            self._measure_lock.release()
        return {
            "ok": True,
            "command": "measure",
            "axis": plan.axis,
            "runs": plan.runs,
            "off": list(plan.compensation_off),
            "host_s": round(time.monotonic() - started, 3),
            **ev.as_dict(),
        }

    def cancel_measure(self) -> None:
        """End a running `measure` at its next wait (the server is shutting down)."""
        self._measure_cancel.set()

    def run_command(self, name: str, value: Any = None) -> CommandResult:
        """Run `reload`, `save` or `volcomp_update` in the caller's thread (see
        `command`)."""
        if name == "reload":
            return self.reload()
        if name == "save":
            return self.save()
        if name == "volcomp_update":
            return self.volcomp_update(str(value))
        raise AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"unknown command {name!r}")

    async def command(self, name: str) -> CommandResult:
        """Run `reload` or `save` in a worker thread (never on the event loop)."""
        return await asyncio.to_thread(self.run_command, name)

    def reload(self, startup: Path | str | None = None) -> CommandResult:
        """Reload the lists: validate everything first, swap atomically or reject.

        Runs in the caller's thread up to the swap, which happens at a cycle boundary.
        A rejected reload leaves the machine unchanged and is recorded in `errors()`.
        """
        if not self._command_lock.acquire(timeout=self.limits.command_wait):
            return _busy("reload")
        try:
            result = self._reload(startup)
        finally:
            self._command_lock.release()
        if not result.ok:
            self._report_now(result.message, result.error_id)
        return result

    def _reload(self, startup: Path | str | None) -> CommandResult:
        path = Path(startup) if startup else self.machine.cfg.startup_path
        try:  # the folders the user allowed at start stay allowed
            new = load_machine(path, self.machine.cfg.allow_dirs)
        except ListFileError as exc:
            return CommandResult(False, "reload", errors=[str(exc)], code=ADSERR_DEVICE_SYNTAX)
        problems = _rejecting(new) + compare_max_points(self.machine.cfg, new)
        if set(new.axes) != set(self.machine.cfg.axes):
            problems.append(
                Diagnostic(
                    "error",
                    f"the axes changed ({sorted(self.machine.cfg.axes)} -> "
                    f"{sorted(new.axes)}); restart the server to change the machine layout",
                )
            )
        warnings = [str(d) for d in new.diagnostics if d not in problems]
        if problems:
            return CommandResult(
                False,
                "reload",
                [p.describe() for p in problems],
                warnings,
                code=ADSERR_DEVICE_SYNTAX,
                error_id=next((p.error_id for p in problems if p.error_id), 0),
            )
        try:
            self._refuse_when_stalled()
            self.settle_sync(self.scheduler.submit(Reload(new)), self.limits.swap_timeout)
        except AdsError as exc:
            return CommandResult(False, "reload", errors=[exc.message], code=exc.code)
        return CommandResult(True, "reload", warnings=warnings, files=new.list_files)

    def volcomp_update(self, file_name: str) -> CommandResult:
        """cnc_interpr_vol_comp_file_w (004 p.23): read the VOLC list `file_name` and its
        correction files for the compensation whose ID was written to
        cnc_interpr_vol_comp_index_w (VOLC::index), here, off the cycle; the cycle then
        swaps it in (switched off first, without movement). A list or file with errors
        leaves the compensation as it was: 0x70D with the diagnostics."""
        if not self._command_lock.acquire(timeout=self.limits.command_wait):
            return _busy("volcomp_update")
        try:
            result = self._volcomp_update(file_name)
        finally:
            self._command_lock.release()
        if not result.ok:
            self._report_now(result.message + ": " + "; ".join(result.errors), result.error_id)
        return result

    def _volcomp_update(self, file_name: str) -> CommandResult:
        ident = int(self.snapshot.value(self.dictionary.by_name("VOLC::index"), 0))
        diags: list[Diagnostic] = []
        new = reload_compensation(self.machine.cfg, ident, file_name, Reporter(diags))
        if new is None:
            return CommandResult(
                False,
                "volcomp_update",
                [f"vol_comp[{ident}] is not configured in the start-up list (004 p.12)"],
                code=AdsErrorCode.DEVICE_INVALIDDATA,
                error_id=VOLC_ERROR,
            )
        warnings = [d.describe() for d in diags if d.severity != "error"]
        if not new.available:
            return CommandResult(
                False,
                "volcomp_update",
                [d.describe() for d in diags if d.severity == "error"],
                warnings,
                code=ADSERR_DEVICE_SYNTAX,
                error_id=VOLC_ERROR,
            )
        try:
            self._refuse_when_stalled()
            self.settle_sync(
                self.scheduler.submit(VolcUpdate(ident, new)), self.limits.swap_timeout
            )
        except AdsError as exc:
            return CommandResult(False, "volcomp_update", errors=[exc.message], code=exc.code)
        return CommandResult(
            True, "volcomp_update", warnings=warnings, files=[new.path, *new.param_files]
        )

    def save(self) -> CommandResult:
        """Write the live TEMPC parameters back into the axis lists (atomic rewrite)."""
        if not self._command_lock.acquire(timeout=self.limits.command_wait):
            return _busy("save")
        try:
            result = self._save()
        finally:
            self._command_lock.release()
        if not result.ok:
            self._report_now(result.message, result.error_id)
        return result

    def _save(self) -> CommandResult:
        startup = self.machine.cfg.startup_path
        if is_product_data(startup):  # refused whatever changed: it is never saved
            return CommandResult(
                False, "save", errors=[_read_only_default(startup)], code=AdsErrorCode.DEVICE_ERROR
            )
        snap = self.snapshot
        files: list[str] = []
        errors: list[str] = []
        for axis in self.axes:
            params = self.machine.cfg.axes[axis].params
            changes = self._changed_parameters(snap, axis)
            if not changes:
                continue
            if not params.path:
                errors.append(f"axis {axis}: no axis parameter list to save into")
                continue
            if is_product_data(params.path):
                errors.append(_read_only_default(params.path))
                continue
            try:
                rewrite_values(params.path, changes)
            except (OSError, ListFileError) as exc:
                errors.append(f"{params.path}: {exc}")
                continue
            _note_saved(self.dictionary, params, changes)
            files.append(params.path)
        return CommandResult(
            not errors, "save", errors=errors, files=files, code=AdsErrorCode.DEVICE_ERROR
        )

    def _changed_parameters(self, snap: Snapshot, axis: int) -> dict[str, str]:
        params = self.machine.cfg.axes[axis].params
        changes: dict[str, str] = {}
        for obj in self.dictionary.saved_parameters():  # objects with a `list_key`
            if obj.type.name == "BOOLEAN" and params.temp_comp_manual_activation:
                continue  # a manual-activation selection is not a list setting (000 §3.2)
            live = snap.value(obj, axis)
            stored = getattr(params, obj.param_attr or "")
            if format_value(obj, live) != format_value(obj, stored):
                changes[obj.list_key or ""] = format_value(obj, live)
        return changes


def check_readable(obj: ObjectDef) -> None:
    """0x704 for a write-only object (a read by address or by Zenoh key)."""
    if not obj.readable:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, f"{obj.name} is write-only", obj.name)


def _not_applied(limit: float) -> AdsError:
    """0x719: a queued operation withdrawn after `limit` seconds without its cycle."""
    return AdsError(
        AdsErrorCode.DEVICE_TIMEOUT,
        f"not applied within {limit:g} s (the GEO cycle is late or stalled); "
        "withdrawn, it will not take effect",
    )


def _single(pending: Pending) -> Pending:
    """The outcome of a one-item `WriteObjects` as None or its error raised (a command's
    CommandResult is passed on as it is)."""

    def first(outcome: Any) -> Any:
        if isinstance(outcome, tuple):
            if outcome[0] is not None:
                raise outcome[0]
            return None
        return outcome

    return chained(pending, first)


def _read_only_default(path: str | Path) -> str:
    """Why `save` does not write into `path`, a file of the shipped default machine
    (docs/design.md §4.5)."""
    return (
        f"{path} belongs to the default machine shipped with geo-server, which is read-only "
        "wherever it is installed; copy it with `geo-server init DIR` and run "
        "`geo-server run DIR/hochlauf.lis` to save"
    )


def _busy(command: str) -> CommandResult:
    return CommandResult(
        False,
        command,
        errors=["another reload or save is still running; try again"],
        code=AdsErrorCode.DEVICE_BUSY,
    )


def _rejecting(cfg: MachineConfig) -> list[Diagnostic]:
    """Diagnostics that make a reload fail: errors and deactivated compensations."""
    return [d for d in cfg.diagnostics if d.severity == "error" or d.deactivated is not None]


def _note_saved(dictionary: Dictionary, params: Any, changes: dict[str, str]) -> None:
    """After a save, the lists hold the live values: remember them as the stored ones."""
    attrs = {o.list_key: o.param_attr or "" for o in dictionary.saved_parameters()}
    for entry, text in changes.items():
        attr = attrs[entry]
        current = getattr(params, attr)
        setattr(
            params,
            attr,
            type(current)(float(text)) if not isinstance(current, bool) else text == "1",
        )


__all__ = [
    "ADSERR_DEVICE_SYNTAX",
    "CommandResult",
    "CompKind",
    "ObjectService",
    "PreparedWrite",
    "ServiceLimits",
    "check_readable",
]
