"""Recording chosen objects every N cycles, with a trigger (docs/recorder.md §1–3, §8).

The recorder subscribes to the object service: its callback runs on the thread that
publishes each cycle, and it holds `demand_cycles()` (every cycle) so the exact engine
publishes every cycle while it records. Per sample it copies the selected values
straight from the snapshot's arrays into a preallocated ring (`np.take` with precomputed
flat indices): no dict lookups, no allocation, no I/O on the cycle's thread.

A recording *to a file* (`out`) streams: a writer thread of its own takes the rows from
the ring chunk by chunk (`CHUNK_BYTES`), types them and appends them to a temporary file
beside the target (CSV lines, Parquet row groups); `finish` writes the rest and replaces
the target atomically. The ring holds the `pre` samples before a trigger and the rows not
yet written — at most `RecorderLimits.buffer_bytes`, whatever the recording's length.
The machine's inputs are held as JSON lines, at most `input_buffer_bytes` of them.
A recording *in memory* (no `out`: the Python API, `stop()` → `Trace`) keeps every row.
"""

from __future__ import annotations

import json
import sys
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from geo_server import __version__
from geo_server.listfile.writer import AtomicFile
from geo_server.machine.port import Operation
from geo_server.recorder.inputs import inputs_path, op_to_json
from geo_server.recorder.selection import Trigger, parse_trigger, resolve_columns
from geo_server.recorder.trace import Trace, TraceWriter
from geo_server.seam import MachineFacts
from geo_server.snapshot import Snapshot

#: Rows kept without a trigger when the spec sets no limit (ten minutes of 1 ms cycles).
DEFAULT_SAMPLES = 600_000
#: Samples taken from the ring and written at once, in bytes of the ring (8 per value);
#: formatting a CSV chunk holds about eight times this in Python strings meanwhile.
CHUNK_BYTES = 256 * 1024
#: Chunk bounds in rows: at least 16 (a very wide recording), at most 4096 (a narrow
#: one reaches its file at least every 4096 samples).
CHUNK_ROWS = (16, 4096)
#: Chunks the ring holds beyond the `pre` samples: how far the writer may fall behind
#: the cycle before a real-time machine drops samples (a stepped or free-running one
#: waits for it instead).
ROOM_CHUNKS = 16
#: Seconds the writer sleeps at most between looks at the ring (rows reach the file at
#: least this often even when a chunk is not full).
WRITER_WAKE = 0.5


@dataclass(frozen=True)
class RecorderLimits:
    """Bounds of a recording (docs/limits.md, docs/recorder.md §8). A setting outside
    them is refused with 0x70B (invalid parameter), the message naming it and its range."""

    #: Rows of a recording without a trigger (`samples`) and after one (`post`).
    max_samples: int = 10_000_000
    #: Samples kept before the trigger (`pre`); the ring must also fit `buffer_bytes`.
    max_pre: int = 100_000
    #: Cycles between two samples (`every`).
    max_every: int = 1_000_000
    #: Selectors of one recording (`objects`).
    max_selectors: int = 256
    #: Characters of one selector, of the trigger and of the file name.
    max_text: int = 256
    #: The ring of a recording to a file (8 bytes per value and row, two more per row
    #: for cycle and time): the `pre` samples and the rows not yet written.
    buffer_bytes: int = 32 << 20
    #: The machine's inputs held in memory as JSON lines: while the trigger is awaited
    #: (then the oldest go), and those not yet written.
    input_buffer_bytes: int = 4 << 20


#: The limits in force (the defaults; `RecorderLimits` documents them).
LIMITS = RecorderLimits()


def _held_bytes(line: str) -> int:
    """What an input line held in memory takes: the text, its object and its slot."""
    return sys.getsizeof(line) + 8


def _show(value: Any) -> str:
    """A value for a message, never long (a 10⁵-digit integer by its size)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _whole(key: str, value: Any, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"record: {key} must be a whole number {low} … {high}, not {_show(value)}")
    return int(value)


@dataclass
class RecordSpec:
    """What to record: selectors, every N cycles, an optional trigger with `pre` samples
    before and `post` after the triggering one; without a trigger at most `samples` rows
    (then the recording is done)."""

    objects: list[str]
    every: int = 1
    trigger: str | None = None
    pre: int = 0
    post: int = 1000
    samples: int = DEFAULT_SAMPLES
    inputs: bool = True

    @classmethod
    def from_json(cls, body: dict[str, Any], limits: RecorderLimits = LIMITS) -> RecordSpec:
        objects = body.get("objects")
        if isinstance(objects, str):
            objects = [objects]
        if not isinstance(objects, list) or not objects:
            raise ValueError("record: 'objects' must name at least one object")
        unknown = set(body) - {"objects", "every", "trigger", "pre", "post", "samples"}
        if unknown:
            names = ", ".join(sorted(map(str, unknown)))
            names = names if len(names) <= 60 else names[:57] + "..."
            raise ValueError(
                f"record: unknown {names} (objects, every, trigger, pre, post, samples)"
            )
        if not all(isinstance(o, str) for o in objects):
            raise ValueError("record: 'objects' must be a list of texts (selectors)")
        spec = cls(list(objects))
        for key in ("every", "pre", "post", "samples"):
            if key in body:
                setattr(spec, key, body[key])
        trigger = body.get("trigger")
        if trigger is not None and not isinstance(trigger, str):
            raise ValueError("record: trigger must be a text ('SIM::program_running rising')")
        spec.trigger = trigger or None
        spec.check(limits)
        return spec

    def check(self, limits: RecorderLimits = LIMITS) -> None:
        """ValueError naming the first setting outside `limits` and its range."""
        if not 1 <= len(self.objects) <= limits.max_selectors:
            raise ValueError(
                f"record: objects must name 1 … {limits.max_selectors} selectors, "
                f"not {len(self.objects)}"
            )
        for text in [*self.objects, self.trigger or ""]:
            if len(text) > limits.max_text:
                raise ValueError(
                    f"record: {_show(text)} is longer than {limits.max_text} characters"
                )
        _whole("every", self.every, 1, limits.max_every)
        _whole("samples", self.samples, 1, limits.max_samples)
        _whole("pre", self.pre, 0, limits.max_pre)
        _whole("post", self.post, 0, limits.max_samples)

    def describe(self) -> dict[str, str]:
        out = {"selectors": ",".join(self.objects), "every": str(self.every)}
        if self.trigger:
            out.update(trigger=self.trigger, pre=str(self.pre), post=str(self.post))
        return out


def typed(raw: np.ndarray, type_name: str) -> np.ndarray:
    """Raw snapshot values as a reader gets them (`snapshot.to_python`, vectorised):
    booleans 0/1, integers rounded half away from zero, REAL64 as they are."""
    if type_name == "BOOLEAN":
        flags: np.ndarray = (raw != 0).astype(float)
        return flags
    if type_name == "REAL64":
        return raw
    rounded: np.ndarray = np.where(raw >= 0, np.floor(raw + 0.5), np.ceil(raw - 0.5))
    return rounded


@dataclass
class _Layout:
    """Where the columns sit in a snapshot: flat indices into `values` and `machine`."""

    axis_index: np.ndarray
    machine_index: np.ndarray
    order: np.ndarray  # buffer column → requested column position


class InputTaps(Protocol):
    """Where a recording hears the inputs (`commands.record.RecordingService`)."""

    def tap_inputs(self, callback: Callable[[int, Operation], None]) -> Callable[[], None]: ...


class Recorded(Protocol):
    """What a recording uses of the object service (`geo_server.seam`)."""

    @property
    def info(self) -> MachineFacts: ...
    @property
    def recordings(self) -> InputTaps: ...
    def demand_cycles(self) -> Callable[[], None]: ...
    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]: ...


class Recorder:
    """Records `spec` from `service` (any `ObjectService`). In memory: `start`, then
    `stop` → `Trace`. To a file (`out`, a place the caller has checked, see
    `recorder.paths`): `start`, then `finish` → what was written."""

    def __init__(
        self,
        service: Recorded,
        spec: RecordSpec,
        name: str = "",
        *,
        out: Path | None = None,
        limits: RecorderLimits = LIMITS,
    ) -> None:
        spec.check(limits)
        self.service = service
        self.spec = spec
        self.name = name
        self.out = out
        self.limits = limits
        axes = tuple(service.info.axes)
        names = {a: service.info.config.axes[a].params.name for a in axes}
        self.columns = resolve_columns(spec.objects, service.info.dictionary, axes, names)
        self.trigger: Trigger | None = None
        if spec.trigger:
            self.trigger = parse_trigger(spec.trigger, service.info.dictionary, axes, names)
        self._axis_cols = [c for c in self.columns if c.obj.scope == "axis"]
        self._machine_cols = [c for c in self.columns if c.obj.scope == "machine"]
        self._ordered = [*self._axis_cols, *self._machine_cols]
        width = 2 + len(self.columns)
        row_bytes = 8 * width
        lo, hi = CHUNK_ROWS
        self.chunk = max(lo, min(hi, CHUNK_BYTES // row_bytes))
        if out is None:  # in memory: every row of the recording (no ring wraps unwritten)
            self.capacity = spec.pre + 1 + spec.post if self.trigger else spec.samples
        else:
            self.capacity = spec.pre + 1 + ROOM_CHUNKS * self.chunk
            most = limits.buffer_bytes // row_bytes - 1 - ROOM_CHUNKS * self.chunk
            if spec.pre > most:
                raise ValueError(
                    f"record: pre must be 0 … {max(most, 0)} for {len(self.columns)} values "
                    f"(the ring of a recording holds at most {limits.buffer_bytes >> 20} MiB)"
                    if most >= 0
                    else f"record: {len(self.columns)} values are too many for one "
                    f"recording (its ring holds at most {limits.buffer_bytes >> 20} MiB)"
                )
        self._buf = np.zeros((self.capacity, width))
        self._layout: _Layout | None = None
        self._lock = threading.Lock()
        # Row bookkeeping, absolute row numbers (ring slot = number % capacity): rows
        # [_flushed, _rows) are held; before them, written (or given up before the trigger)
        self._rows = 0
        self._flushed = 0
        self._written = 0  # rows handed to the file / kept for the Trace
        self._first: int | None = None
        self._last_cycle = -1
        self._trigger_slot = -1
        self._trigger_prev: float | None = None
        self._trigger_row: int | None = None
        self.triggered_at: int | None = None  # the cycle that fired the trigger
        self.done = False
        self._halted = False
        #: samples not taken because the writer was a whole ring behind (real time only)
        self.dropped = 0
        self._cycle_ms = service.info.cycle_s * 1000
        # inputs as JSON lines: those held and their size; `_input_count` ever kept
        self._inputs: deque[str] = deque()
        self._inputs_bytes = 0
        self._input_count = 0
        self.inputs_dropped = 0
        self._undo: list[Callable[[], None]] = []
        # the file side (out): the writer thread and what it writes into
        self._realtime = service.info.mode == "realtime"
        self._trace_file: TraceWriter | None = None
        self._inputs_file: AtomicFile | None = None
        self._writer: threading.Thread | None = None
        self._kick = threading.Event()
        self._room = threading.Event()
        self._closing = False
        self._error: BaseException | None = None
        self._result: dict[str, Any] | None = None

    @property
    def buffer_bytes(self) -> int:
        """What the ring of samples takes (fixed when the recording is made)."""
        return int(self._buf.nbytes)

    @property
    def inputs(self) -> list[dict[str, Any]]:
        """The inputs held (in memory: every one recorded, docs/recorder.md §4)."""
        return [json.loads(line) for line in list(self._inputs)]

    # ------------------------------------------------------------------ control

    def start(self) -> Recorder:
        """Start sampling (and, to a file, make the temporary files and the writer)."""
        if self.out is not None:
            self._open_files(self.out)
        try:
            if self.spec.inputs:
                self._undo.append(self.service.recordings.tap_inputs(self._on_input))
            self._undo.append(self.service.demand_cycles())
            self._undo.append(self.service.subscribe(self._on_cycle))
        except BaseException:
            self.abort()
            raise
        return self

    def _halt(self) -> None:
        undo, self._undo = self._undo, []
        for fn in reversed(undo):
            fn()
        with self._lock:  # a sample under way ends first; none follows
            self._halted = True

    def stop(self) -> Trace:
        """Stop recording (idempotent) and return what was recorded (in memory)."""
        if self.out is not None:
            raise TypeError(f"this recording streams to {self.out}: finish() it")
        self._halt()
        with self._lock:
            start, end = self._held(final=True)
            data = self._rows_between(start, end)
        return Trace(
            [c.label for c in self.columns],
            data,
            [c.obj.type.name for c in self.columns],
            [c.obj.unit for c in self.columns],
            self._meta(),
        )

    def finish(self) -> dict[str, Any]:
        """Stop recording (idempotent), write the rows and inputs not written yet and put
        both files in place atomically; what was written. OSError when they cannot be
        written (the targets are then as they were)."""
        if self._writer is None:
            raise TypeError("this recording is in memory: stop() it")
        self._halt()
        self._closing = True
        self._kick.set()
        self._writer.join()
        if self._error is not None:
            raise OSError(f"cannot write {self.out}: {self._error}") from self._error
        assert self._result is not None
        return self._result

    def abort(self) -> None:
        """Stop recording and remove what was written of it (the targets stay as they
        were; after `finish`, nothing happens)."""
        self._halt()
        if self._writer is not None and self._error is None:
            self._error = OSError("recording aborted")
            self._closing = True
            self._kick.set()
            self._writer.join()

    @property
    def running(self) -> bool:
        return bool(self._undo) and not self.done

    @property
    def _waiting(self) -> bool:
        """Whether the trigger is awaited (only the last `pre` samples are kept)."""
        return self.trigger is not None and self._trigger_row is None

    def status(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "columns": len(self.columns),
            "rows": self._written + (self._rows - self._flushed),
            "every": self.spec.every,
            "trigger": self.spec.trigger or "",
            "triggered_at": self.triggered_at,
            "waiting": self._waiting and not self.done,
            "done": self.done,
            "inputs": self._input_count,
            "dropped": self.dropped,
            "inputs_dropped": self.inputs_dropped,
            "buffer_bytes": self.buffer_bytes,
        }

    # ------------------------------------------------------------------ the cycle thread

    def _on_input(self, cycle: int, op: Any) -> None:
        line = op_to_json(cycle, op)
        if line is None or self.done or self._halted:
            return
        text = json.dumps(line)
        cost = _held_bytes(text)
        limit = self.limits.input_buffer_bytes
        with self._lock:
            self._inputs.append(text)
            self._inputs_bytes += cost
            self._input_count += 1
            bounded = self.out is not None or self._waiting
            while bounded and self._inputs_bytes > limit and len(self._inputs) > 1:
                # the oldest go: while the trigger is awaited they are the least likely
                # to matter; to a file, only a writer stalled for long gets here
                self._inputs_bytes -= _held_bytes(self._inputs.popleft())
                self._input_count -= 1
                self.inputs_dropped += 1
        if self._writer is not None and not self._waiting and self._inputs_bytes > limit // 4:
            self._kick.set()  # (awaiting the trigger, the writer has nothing to do)

    def _on_cycle(self, snap: Any) -> None:
        cycle = snap.cycle
        if self.done or cycle <= self._last_cycle:
            return  # (a cycle published twice is sampled once)
        self._last_cycle = cycle
        if self._first is None:
            self._first = cycle
        if (cycle - self._first) % self.spec.every:
            return
        if self._rows - self._flushed >= self.capacity and not self._make_room():
            self.dropped += 1
            return
        with self._lock:
            if not self._halted:
                self._sample(snap, cycle)
        ready = self.done or self._rows - self._flushed >= self.chunk
        if ready and self._writer is not None and not self._waiting:
            self._kick.set()

    def _make_room(self) -> bool:
        """The writer is a whole ring behind: a stepped or free-running machine waits for
        it (there is no clock to keep); a real-time one drops the sample (counted)."""
        if self._realtime or self._writer is None:
            return False
        while self._rows - self._flushed >= self.capacity:
            if self._error is not None or not self._writer.is_alive():
                return False
            self._room.clear()
            self._kick.set()
            self._room.wait(WRITER_WAKE)
        return True

    def _sample(self, snap: Any, cycle: int) -> None:
        lay = self._layout or self._build_layout(snap)
        r = self._rows
        row = self._buf[r % self.capacity]
        row[0] = cycle
        row[1] = cycle * self._cycle_ms / 1000  # (9 · 1.0 / 1000 is 0.009; 9 · 0.001 is not)
        na = len(lay.axis_index)
        np.take(snap.values, lay.axis_index, out=row[2 : 2 + na])
        np.take(snap.machine, lay.machine_index, out=row[2 + na :])
        self._rows = r + 1
        if self.trigger is None:
            self.done = self._rows >= self.spec.samples
        elif self._trigger_row is None:
            now = float(row[self._trigger_slot])
            fired = self.trigger.fires(self._trigger_prev, now)
            self._trigger_prev = now
            if fired:
                self._trigger_row = r
                self.triggered_at = cycle
                self._flushed = max(self._flushed, r - self.spec.pre)
                self.done = self.spec.post == 0
            else:  # only the last `pre` are kept
                self._flushed = max(self._flushed, self._rows - self.spec.pre)
        else:
            self.done = r - self._trigger_row >= self.spec.post

    def _build_layout(self, snap: Any) -> _Layout:
        lay = snap.layout
        width = snap.values.shape[1]
        axis_index = np.array(
            [snap.axes.index(c.axis) * width + lay.column[c.obj.name] for c in self._axis_cols],
            dtype=np.intp,
        )
        machine_index = np.array(
            [lay.machine_index[c.obj.name] for c in self._machine_cols], dtype=np.intp
        )
        order = np.array([self._ordered.index(c) for c in self.columns], dtype=np.intp)
        if self.trigger is not None:
            self._trigger_slot = 2 + self._ordered.index(self.trigger.column)
        self._layout = _Layout(axis_index, machine_index, order)
        return self._layout

    # ------------------------------------------------------------------ the rows

    def _held(self, final: bool) -> tuple[int, int]:
        """The rows to write now (under the lock): none while the trigger is awaited,
        unless the recording ends (then the last `pre`)."""
        if self._waiting and not final:
            return self._flushed, self._flushed
        return self._flushed, self._rows

    def _rows_between(self, start: int, end: int) -> np.ndarray:
        """Rows [start, end) out of the ring, in the requested column order, each value
        as a read returns it (docs §3). The ring's slots of these rows are not written
        meanwhile: the cycle thread waits for room beyond `_flushed`."""
        rows = self._buf[np.arange(start, end) % self.capacity]
        if self._layout is not None and len(rows):
            rows[:, 2:] = rows[:, 2:][:, self._layout.order]
        for i, c in enumerate(self.columns):
            rows[:, 2 + i] = typed(rows[:, 2 + i], c.obj.type.name)
        return rows

    def _meta(self) -> dict[str, str]:
        meta = {
            "geo_server": __version__,
            "machine": self.name,
            "cycle_ms": repr(self._cycle_ms),
            **self.spec.describe(),
        }
        if self.triggered_at is not None:
            meta["triggered_at"] = str(self.triggered_at)
        return meta

    # ------------------------------------------------------------------ the writer thread

    def _open_files(self, out: Path) -> None:
        self._trace_file = TraceWriter(
            out,
            [c.label for c in self.columns],
            [c.obj.type.name for c in self.columns],
            [c.obj.unit for c in self.columns],
        )
        try:
            self._inputs_file = AtomicFile(inputs_path(out))
        except BaseException:
            self._trace_file.abort()
            raise
        self._writer = threading.Thread(
            target=self._write_loop, name=f"recorder {out.name}", daemon=True
        )
        self._writer.start()

    def _write_loop(self) -> None:
        assert self._trace_file is not None and self._inputs_file is not None
        trace_file, inputs_file = self._trace_file, self._inputs_file
        try:
            while not self._closing:
                self._kick.wait(WRITER_WAKE)
                self._kick.clear()
                self._write_some(final=False)
            if self._error is not None:  # aborted
                raise self._error
            self._write_some(final=True)
            meta = self._meta()
            trace_file.commit(meta)
            inputs_file.commit()
            self._result = {
                **self.status(),
                "rows": self._written,
                "file": str(trace_file.path),
                "inputs_file": str(inputs_file.path),
            }
        except BaseException as exc:  # (disk full, …): the targets stay as they were
            if self._error is None:
                self._error = exc
            trace_file.abort()
            inputs_file.abort()
        finally:
            self._room.set()

    def _write_some(self, final: bool) -> None:
        """Write what is held, a chunk at a time (bounded memory however much it is)."""
        assert self._trace_file is not None and self._inputs_file is not None
        while True:
            with self._lock:
                start, end = self._held(final)
                end = min(end, start + self.chunk)
                lines: list[str] = []
                if final or not self._waiting:  # (awaiting the trigger, they are held)
                    lines = list(self._inputs)
                    self._inputs.clear()
                    self._inputs_bytes = 0
                meta = self._meta()
            if lines:
                self._inputs_file.fh.write("".join(x + "\n" for x in lines).encode())
            if start >= end:
                return
            self._trace_file.write(self._rows_between(start, end), meta)
            with self._lock:
                self._flushed = end
                self._written += end - start
            self._room.set()


__all__ = ["DEFAULT_SAMPLES", "RecordSpec", "Recorder"]
