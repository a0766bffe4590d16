"""Recording chosen objects every N cycles, with a trigger (docs/recorder.md §1–3).

The recorder subscribes to the object service: its callback runs on the thread that
publishes each cycle, and it holds `demand_every_cycle` so the exact engine publishes
every cycle while it records. Per sample it copies the selected values straight from the
snapshot's arrays into a preallocated buffer (`np.take` with precomputed flat indices):
no dict lookups, no allocation, no I/O on the cycle's thread. Files are written by the
caller (`stop`, then `Trace.save`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from geo_server import __version__
from geo_server.recorder.inputs import op_to_json
from geo_server.recorder.selection import Trigger, parse_trigger, resolve_columns
from geo_server.recorder.trace import Trace

#: Rows kept without a trigger when the spec sets no limit (a minute of 1 ms cycles × 10).
DEFAULT_SAMPLES = 600_000


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
    def from_json(cls, body: dict[str, Any]) -> RecordSpec:
        objects = body.get("objects")
        if isinstance(objects, str):
            objects = [objects]
        if not isinstance(objects, list) or not objects:
            raise ValueError("record: 'objects' must name at least one object")
        unknown = set(body) - {"objects", "every", "trigger", "pre", "post", "samples"}
        if unknown:
            raise ValueError(
                f"record: unknown {', '.join(sorted(unknown))} (objects, every, trigger, "
                "pre, post, samples)"
            )
        spec = cls([str(o) for o in objects])
        for key in ("every", "pre", "post", "samples"):
            if key in body:
                value = body[key]
                if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                    raise ValueError(f"record: {key} must be a whole number ≥ 0, not {value!r}")
                setattr(spec, key, value)
        if body.get("trigger"):
            spec.trigger = str(body["trigger"])
        spec.check()
        return spec

    def check(self) -> None:
        if self.every < 1:
            raise ValueError(f"record: every must be ≥ 1, not {self.every}")
        if self.samples < 1 or self.post < 0 or self.pre < 0:
            raise ValueError("record: samples must be ≥ 1, pre and post ≥ 0")

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


class Recorder:
    """Records `spec` from `service` (any `ObjectService`); `start`, then `stop` → Trace."""

    def __init__(self, service: Any, spec: RecordSpec, name: str = "") -> None:
        spec.check()
        self.service = service
        self.spec = spec
        self.name = name
        axes = tuple(service.axes)
        names = {a: service.machine.cfg.axes[a].params.name for a in axes}
        self.columns = resolve_columns(spec.objects, service.dictionary, axes, names)
        self.trigger: Trigger | None = None
        if spec.trigger:
            self.trigger = parse_trigger(spec.trigger, service.dictionary, axes, names)
        self._axis_cols = [c for c in self.columns if c.obj.scope == "axis"]
        self._machine_cols = [c for c in self.columns if c.obj.scope == "machine"]
        self._ordered = [*self._axis_cols, *self._machine_cols]
        # one more row than kept: the ring never overwrites the row being filled
        self.capacity = spec.pre + 1 + spec.post if self.trigger else spec.samples
        self._buf = np.zeros((self.capacity, 2 + len(self.columns)))
        self._layout: _Layout | None = None
        self._lock = threading.Lock()
        self._rows = 0  # rows written (ring position = rows % capacity)
        self._first: int | None = None
        self._last_cycle = -1
        self._trigger_slot = -1
        self._trigger_prev: float | None = None
        self.triggered_at: int | None = None  # the cycle that fired the trigger
        self._after = 0  # samples after the trigger
        self.done = False
        self._cycle_ms = service.cycle_s * 1000
        self.inputs: list[dict[str, Any]] = []
        self._undo: list[Callable[[], None]] = []

    # ------------------------------------------------------------------ control

    def start(self) -> Recorder:
        machine = self.service.machine
        if self.spec.inputs:
            taps = getattr(machine, "input_taps", None)
            if taps is not None:
                taps.append(self._on_input)
                self._undo.append(lambda: taps.remove(self._on_input))
        self._undo.append(self.service.scheduler.demand_every_cycle())
        self._undo.append(self.service.subscribe(self._on_cycle))
        return self

    def stop(self) -> Trace:
        """Stop recording (idempotent) and return what was recorded."""
        undo, self._undo = self._undo, []
        for fn in reversed(undo):
            fn()
        with self._lock:
            return self._trace()

    @property
    def running(self) -> bool:
        return bool(self._undo) and not self.done

    def status(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "columns": len(self.columns),
            "rows": min(self._rows, self.capacity),
            "every": self.spec.every,
            "trigger": self.spec.trigger or "",
            "triggered_at": self.triggered_at,
            "done": self.done,
            "inputs": len(self.inputs),
        }

    # ------------------------------------------------------------------ the cycle thread

    def _on_input(self, cycle: int, op: Any) -> None:
        line = op_to_json(cycle, op)
        if line is not None and not self.done:
            self.inputs.append(line)

    def _on_cycle(self, snap: Any) -> None:
        cycle = snap.cycle
        if self.done or cycle <= self._last_cycle:
            return  # (a cycle published twice is sampled once)
        self._last_cycle = cycle
        if self._first is None:
            self._first = cycle
        if (cycle - self._first) % self.spec.every:
            return
        with self._lock:
            self._sample(snap, cycle)

    def _sample(self, snap: Any, cycle: int) -> None:
        lay = self._layout or self._build_layout(snap)
        row = self._buf[self._rows % self.capacity]
        row[0] = cycle
        row[1] = cycle * self._cycle_ms / 1000  # (9 · 1.0 / 1000 is 0.009; 9 · 0.001 is not)
        na = len(lay.axis_index)
        np.take(snap.values, lay.axis_index, out=row[2 : 2 + na])
        np.take(snap.machine, lay.machine_index, out=row[2 + na :])
        self._rows += 1
        if self.trigger is None:
            self.done = self._rows >= self.capacity
            return
        if self.triggered_at is None:
            now = float(row[self._trigger_slot])
            fired = self.trigger.fires(self._trigger_prev, now)
            self._trigger_prev = now
            if fired:
                self.triggered_at = cycle
            return
        self._after += 1
        self.done = self._after >= self.spec.post

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

    # ------------------------------------------------------------------ the result

    def _trace(self) -> Trace:
        n = min(self._rows, self.capacity)
        start = self._rows - n
        idx = [(start + k) % self.capacity for k in range(n)]
        rows = self._buf[idx]
        if self.trigger is not None and self.triggered_at is not None:
            # `pre` rows before the triggering one (stopped early, the ring holds more)
            k = int(np.searchsorted(rows[:, 0], self.triggered_at))
            rows = rows[max(0, k - self.spec.pre) :]
        elif self.trigger is not None:
            rows = rows[-self.spec.pre :] if self.spec.pre else rows[:0]
        data = np.empty_like(rows)
        data[:, :2] = rows[:, :2]
        if self._layout is not None and len(rows):
            data[:, 2:] = rows[:, 2:][:, self._layout.order]
        for i, c in enumerate(self.columns):  # the value a read returns (docs §3)
            data[:, 2 + i] = typed(data[:, 2 + i], c.obj.type.name)
        meta = {
            "geo_server": __version__,
            "machine": self.name,
            "cycle_ms": repr(self._cycle_ms),
            **self.spec.describe(),
        }
        if self.triggered_at is not None:
            meta["triggered_at"] = str(self.triggered_at)
        return Trace(
            [c.label for c in self.columns],
            data,
            [c.obj.type.name for c in self.columns],
            [c.obj.unit for c in self.columns],
            meta,
        )


__all__ = ["DEFAULT_SAMPLES", "RecordSpec", "Recorder"]
