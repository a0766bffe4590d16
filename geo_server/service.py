"""The object service: the one API every transport calls (SPEC §2, §4, §5, §9).

- `read(group, offset, length)` answers from the latest published snapshot and returns
  ADS bytes or raises `AdsError` with the code of SPEC §9 (0x702 group, 0x703 offset or
  axis, 0x705 length). A read never returns more bytes than the object has.
- `read_many(...)` answers a batch from **one** snapshot (sum reads, block reads).
- `write(group, offset, data)` validates at once (0x702/0x703/0x704/0x705/0x706) and
  queues the value; it is applied at the next cycle boundary in arrival order. The
  returned future resolves when it has been applied.
- `write_async` / `write_name_async`: the same from an asyncio loop. The command objects
  (`SIM::reload`, `SIM::save`, see `is_command`) read and write list files; they run in
  a worker thread so the loop (ADS, Modbus, Zenoh) keeps answering meanwhile.
- by-name access with decoded values, change subscriptions, `status`, `errors`,
  and the commands `reload` and `save` of SPEC §4.

Transports never reach into the kernel or the machine; they hold an `ObjectService`.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geo_server.config import CompKind, Diagnostic, MachineConfig
from geo_server.dictionary import AdsError, AdsErrorCode, ObjectDef
from geo_server.listfile import ListFileError, compare_max_points, load_machine, rewrite_values
from geo_server.machine.machine import Event, Machine
from geo_server.machine.nc import NcError, parse_program
from geo_server.machine.scheduler import Scheduler
from geo_server.machine.snapshot import Snapshot
from geo_server.paths import is_packaged_data

#: ADS "syntax error in file" — a reload rejected because a list has errors.
ADSERR_DEVICE_SYNTAX = AdsErrorCode.DEVICE_SYNTAX

#: Writable TEMPC objects and the axis-list parameter `save` writes them to (000 §3.2).
SAVED_PARAMETERS = {
    "TEMPC::coefficient": "lr_param.temp_comp_coefficient",
    "TEMPC::offset_0": "lr_param.temp_comp_offset_0",
    "TEMPC::position_0": "lr_param.temp_comp_position_0",
    "TEMPC::activated": "lr_param.temp_comp",
}

#: Objects whose write runs a command (SPEC §2, 0x12F300 IDs 0x4/0x5) instead of queueing
#: a value: they parse or rewrite list files and may take long, so never on an event loop.
COMMAND_OBJECTS = frozenset({"SIM::reload", "SIM::save"})


@dataclass
class CommandResult:
    """Outcome of `reload` / `save`, as JSON for the transports."""

    ok: bool
    command: str
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "command": self.command,
            "errors": self.errors,
            "warnings": self.warnings,
            "files": self.files,
        }


def format_value(obj: ObjectDef, value: Any) -> str:
    """A value as a list-file token: integers plain, REAL64 shortest round-trip form."""
    if obj.type.name == "BOOLEAN":
        return "1" if value else "0"
    if obj.type.name == "REAL64":
        f = float(value)
        return str(int(f)) if f.is_integer() and abs(f) < 1e15 else repr(f)
    return str(round(value))


class ObjectService:
    """Reads, writes, batches, subscriptions and commands over one `Machine`."""

    def __init__(self, machine: Machine, scheduler: Scheduler | None = None) -> None:
        self.machine = machine
        self.scheduler = scheduler or Scheduler(machine, mode="stepped")
        self.dictionary = machine.dictionary
        self._command_lock = threading.Lock()

    # ------------------------------------------------------------------ addressing

    @property
    def axes(self) -> tuple[int, ...]:
        return self.machine.axes

    @property
    def snapshot(self) -> Snapshot:
        return self.machine.snapshot

    def resolve(self, index_group: int, index_offset: int) -> tuple[ObjectDef, int, str | None]:
        return self.dictionary.resolve(index_group, index_offset, self.axes)

    def lookup(self, name: str, axis: int) -> ObjectDef:
        """Object by name for `axis`; 0x703 when the axis does not exist."""
        obj = self.dictionary.by_name(name)
        if obj.scope == "axis" and axis not in self.axes:
            raise AdsError(
                AdsErrorCode.INVALID_INDEX_OFFSET, f"axis {axis} is not configured", obj.name
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
        data = obj.attribute(attr) if attr else (snapshot or self.snapshot).encode(obj, axis)
        if length is not None and length < len(data):
            raise AdsError(
                AdsErrorCode.INVALID_SIZE,
                f"{obj.name}: read of {length} bytes, the value has {len(data)}",
                obj.name,
            )
        return data

    def read_many(self, requests: Iterable[tuple[int, int, int | None]]) -> list[bytes | AdsError]:
        """Batch read from one snapshot; each entry is bytes or the AdsError it raised."""
        snap = self.snapshot
        out: list[bytes | AdsError] = []
        for ig, io, length in requests:
            try:
                out.append(self.read(ig, io, length, snap))
            except AdsError as exc:
                out.append(exc)
        return out

    def read_name(self, name: str, axis: int = 0, snapshot: Snapshot | None = None) -> Any:
        """Decoded value of an object by name."""
        obj = self.lookup(name, axis)
        return (snapshot or self.snapshot).value(obj, axis)

    def read_axis(self, axis: int, group: str = "geo") -> dict[str, Any]:
        """Every object of `group` for one axis, decoded, from one snapshot."""
        snap = self.snapshot
        return {
            o.name: snap.value(o, axis)
            for o in self.dictionary.group_objects(group)
            if axis in self.axes
        }

    # ------------------------------------------------------------------ writes

    def write(self, index_group: int, index_offset: int, data: bytes) -> Future:
        """Validate ADS bytes now and apply them at the next cycle boundary."""
        obj, axis, attr = self.resolve(index_group, index_offset)
        if attr is not None:
            raise AdsError(
                AdsErrorCode.INVALID_ACCESS, f"attribute of {obj.name} is read-only", obj.name
            )
        self._check_writable(obj)
        return self._queue(obj, axis, obj.decode(data))

    def write_name(self, name: str, axis: int, value: Any) -> Future:
        """Validate a decoded value (JSON, CLI) and apply it at the next cycle boundary."""
        obj = self.lookup(name, axis)
        self._check_writable(obj)
        return self._queue(obj, axis, obj.coerce(value))

    def is_command(self, obj: ObjectDef) -> bool:
        """Does writing `obj` run a command (reload/save) rather than queue a value?"""
        return obj.name in COMMAND_OBJECTS

    async def write_async(self, index_group: int, index_offset: int, data: bytes) -> Future:
        """`write` for callers on an asyncio loop: a command object runs in a worker thread.

        `write` of `SIM::reload`/`SIM::save` parses or rewrites the list files before it
        returns; on the loop that would stall every transport sharing it (ADS, Modbus,
        Zenoh) for the whole reload. Plain values are validated and queued in place
        (cheap, and it keeps their arrival order).
        """
        obj, _axis, attr = self.resolve(index_group, index_offset)
        if attr is None and self.is_command(obj):
            return await asyncio.get_running_loop().run_in_executor(
                None, self.write, index_group, index_offset, data
            )
        return self.write(index_group, index_offset, data)

    async def write_name_async(self, name: str, axis: int, value: Any) -> Future:
        """`write_name` for callers on an asyncio loop (see `write_async`)."""
        if self.is_command(self.dictionary.by_name(name)):
            return await asyncio.get_running_loop().run_in_executor(
                None, self.write_name, name, axis, value
            )
        return self.write_name(name, axis, value)

    def _check_writable(self, obj: ObjectDef) -> None:
        if not obj.writable:
            raise AdsError(AdsErrorCode.INVALID_ACCESS, f"{obj.name} is read-only", obj.name)

    def _queue(self, obj: ObjectDef, axis: int, value: Any) -> Future:
        # Commands run here, in the caller's thread: callers on an event loop use
        # `write_async` / `write_name_async`, which call this in a worker thread.
        if obj.name == "SIM::reload":
            return self._done(self.reload())
        if obj.name == "SIM::save":
            return self._done(self.save())
        return _detached(self.machine.call("apply_write", obj.name, axis, value))

    @staticmethod
    def _done(result: CommandResult) -> Future:
        fut: Future = Future()
        if result.ok:
            fut.set_result(result)
        else:
            fut.set_exception(AdsError(ADSERR_DEVICE_SYNTAX, "; ".join(result.errors)))
        return fut

    # ------------------------------------------------------------------ subscriptions

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        """Call `callback(snapshot)` after every cycle, on the cycle thread.

        Keep it short and hand work to your own thread or event loop. Returns a function
        that unsubscribes.
        """
        self.machine.listeners.append(callback)
        return lambda: self.machine.listeners.remove(callback)

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
                if last.get((obj.name, axis), _MISSING) != v:
                    last[(obj.name, axis)] = v
                    changed[(obj.name, axis)] = v
            if changed:
                callback(changed)

        return self.subscribe(on_cycle)

    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        self.machine.event_listeners.append(callback)
        return lambda: self.machine.event_listeners.remove(callback)

    # ------------------------------------------------------------------ status

    def status(self) -> dict[str, Any]:
        return self.scheduler.status()

    def errors(self) -> list[dict[str, Any]]:
        """The last 100 warnings and errors (SPEC §7 `errors`)."""
        return [e.as_dict() for e in list(self.machine.events)]

    def step(self, n: int = 1) -> Snapshot:
        """Run `n` cycles (stepped mode)."""
        self.scheduler.step(n)
        return self.snapshot

    # ------------------------------------------------------------------ NC

    def run_nc(self, text: str) -> Future:
        """Parse NC lines now (bad text -> AdsError 0x70D naming the line) and start them
        as MDI lines at the next cycle boundary."""
        try:
            prog = parse_program(text, self.machine.names, mdi=True)
        except NcError as exc:
            raise AdsError(ADSERR_DEVICE_SYNTAX, str(exc), "nc") from None
        return _detached(self.machine.call("start", prog, True))

    def reset(self) -> Future:
        """CNC reset at the next cycle boundary: program stopped, axes stopped."""
        return _detached(self.machine.call("reset"))

    # ------------------------------------------------------------------ commands

    def reload(self, startup: Path | str | None = None) -> CommandResult:
        """Reload the lists (SPEC §4): validate everything first, swap atomically or reject.

        Runs in the caller's thread up to the swap, which happens at a cycle boundary.
        """
        with self._command_lock:
            path = Path(startup) if startup else self.machine.cfg.startup_path
            try:
                new = load_machine(path)
            except ListFileError as exc:
                return CommandResult(False, "reload", errors=[str(exc)])
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
                return CommandResult(False, "reload", [str(p) for p in problems], warnings)
            fut = self.machine.call("reload", new)
            self._wait_applied(fut)
            return CommandResult(True, "reload", warnings=warnings, files=_list_files(new))

    def save(self) -> CommandResult:
        """Write the live TEMPC parameters back into the axis lists (SPEC §4)."""
        with self._command_lock:
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
                if is_packaged_data(params.path):
                    errors.append(
                        f"{params.path} belongs to the installed package; copy the machine "
                        "with `geo-server init DIR` and run DIR/hochlauf.lis to save"
                    )
                    continue
                try:
                    rewrite_values(params.path, changes)
                except OSError as exc:
                    errors.append(f"{params.path}: {exc}")
                    continue
                _note_saved(params, changes)
                files.append(params.path)
            return CommandResult(not errors, "save", errors=errors, files=files)

    def _changed_parameters(self, snap: Snapshot, axis: int) -> dict[str, str]:
        params = self.machine.cfg.axes[axis].params
        changes: dict[str, str] = {}
        for name, entry in SAVED_PARAMETERS.items():
            obj = self.dictionary.by_name(name)
            if name == "TEMPC::activated" and params.temp_comp_manual_activation:
                continue  # a manual-activation selection is not a list setting (000 §3.2)
            live = snap.value(obj, axis)
            stored = getattr(params, entry.split(".", 1)[1])
            if format_value(obj, live) != format_value(obj, stored):
                changes[entry] = format_value(obj, live)
        return changes

    def _wait_applied(self, fut: Future) -> None:
        """In stepped mode the swap waits for the next step; otherwise wait for it."""
        if self.scheduler.running:
            fut.result(timeout=5.0)


_MISSING = object()


def _detached(inner: Future) -> Future:
    """The caller's copy of a queued write's future: it follows `inner`, but cancelling
    it never reaches `inner`.

    Transports await writes with `asyncio.wait_for(asyncio.wrap_future(fut), …)`; a
    timeout or a dropped connection cancels the asyncio future, and `wrap_future` passes
    that on to the concurrent future. The machine still applies the queued write, but
    then `fut.set_result` on the cancelled future raised `InvalidStateError` on the
    cycle thread: the cycle failed (`Scheduler.cycle_errors`), the other writes of that
    cycle were never acknowledged and the listeners missed the cycle (found by
    tests/test_robust_fuzz.py: ADS clients that vanish while a write is pending).
    A cancelled copy just stays cancelled; the write itself is applied as queued.
    """
    outer: Future = Future()

    def copy(done: Future) -> None:
        if not outer.set_running_or_notify_cancel():
            return  # the caller gave up waiting: nobody to tell
        exc = done.exception()
        if exc is None:
            outer.set_result(done.result())
        else:
            outer.set_exception(exc)

    inner.add_done_callback(copy)
    return outer


def _rejecting(cfg: MachineConfig) -> list[Diagnostic]:
    """Diagnostics that make a reload fail: errors and deactivated compensations."""
    return [d for d in cfg.diagnostics if d.severity == "error" or d.deactivated is not None]


def _list_files(cfg: MachineConfig) -> list[str]:
    files = {a.params.path for a in cfg.axes.values() if a.params.path}
    files |= {a.comp.path for a in cfg.axes.values() if a.comp is not None}
    return sorted(files)


def _note_saved(params: Any, changes: dict[str, str]) -> None:
    """After a save, the lists hold the live values: remember them as the stored ones."""
    for entry, text in changes.items():
        attr = entry.split(".", 1)[1]
        current = getattr(params, attr)
        setattr(
            params,
            attr,
            type(current)(float(text)) if not isinstance(current, bool) else text == "1",
        )


__all__ = ["ADSERR_DEVICE_SYNTAX", "COMMAND_OBJECTS", "CommandResult", "CompKind", "ObjectService"]
