"""One consistent picture of every object after a GEO cycle (docs/design.md §5 step 4).

The machine fills one `Snapshot` per cycle and publishes it by swapping a reference, so
a reader on any thread sees either the old or the new snapshot, never a mix: a read, a
sum read or a Modbus block read served from one snapshot never mixes two cycles.

Values are stored as float64 (the kernel's internal values) and converted to the wire
type only when encoded: SGN32 rounds half away from zero (docs/design.md §3).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from geo_server.dictionary import Dictionary, ObjectDef, round_half_away


class ObjectLayout:
    """Column of every axis object and index of every machine object in a snapshot."""

    def __init__(self, dictionary: Dictionary) -> None:
        self.dictionary = dictionary
        self.axis_objects = [o for o in dictionary.objects if o.scope == "axis"]
        machine = [o for o in dictionary.objects if o.scope == "machine"]
        #: machine-wide numeric objects: `Snapshot.machine[i]`
        self.machine_objects = [o for o in machine if o.type.name != "STRING"]
        #: machine-wide text objects (`SIM::last_error`): `Snapshot.texts[i]`
        self.text_objects = [o for o in machine if o.type.name == "STRING"]
        self.column = {o.name: i for i, o in enumerate(self.axis_objects)}
        self.machine_index = {o.name: i for i, o in enumerate(self.machine_objects)}
        self.text_index = {o.name: i for i, o in enumerate(self.text_objects)}

    def col(self, name: str) -> int:
        return self.column[self.dictionary.by_name(name).name]

    def mcol(self, name: str) -> int:
        return self.machine_index[self.dictionary.by_name(name).name]


#: Windows FILETIME epoch (1601-01-01) to Unix epoch in 100 ns ticks: the time base of
#: `Snapshot.stamp` and of ADS time stamps.
FILETIME_UNIX_OFFSET = 116_444_736_000_000_000


def filetime_now() -> int:
    """Now as a Windows FILETIME: 100 ns ticks since 1601-01-01."""
    return time.time_ns() // 100 + FILETIME_UNIX_OFFSET


def to_python(obj: ObjectDef, raw: float) -> Any:
    """The decoded value of an object as a reader sees it (bool, int or float)."""
    t = obj.type.name
    if t == "BOOLEAN":
        return bool(raw)
    if t == "REAL64":
        return float(raw)
    return round_half_away(float(raw))


@dataclass(frozen=True)
class Snapshot:
    """Object values of all axes after cycle `cycle`.

    `values[slot, column]` for axis objects (slot order = `axes`), `machine[i]` for the
    machine-wide numeric emulator objects, `texts[i]` for the machine-wide text ones.
    """

    cycle: int
    axes: tuple[int, ...]
    values: np.ndarray
    machine: np.ndarray
    layout: ObjectLayout
    texts: tuple[str, ...] = ()
    #: the cycle's place on the time line: Windows FILETIME (100 ns since 1601) of the
    #: end of this cycle, `Machine.epoch + cycle · T` (what ADS notifications carry)
    stamp: int = 0
    #: answers already encoded from this snapshot (`kept`): a machine at rest answers
    #: its reads from one snapshot (docs/design.md §13, *Reads at rest*)
    _kept: dict[tuple[str, str, int], bytes] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def slot(self, axis: int) -> int:
        return self.axes.index(axis)

    def wire(self) -> tuple[Any, ...]:
        """The snapshot as another process is sent it (the cycle's own process, OPC UA's):
        its numbers as bytes; the receiver has its own layout (`from_wire`)."""
        return (
            self.cycle,
            self.axes,
            self.values.tobytes(),
            self.values.shape,
            self.machine.tobytes(),
            self.texts,
            self.stamp,
        )

    @classmethod
    def from_wire(cls, wire: tuple[Any, ...], layout: ObjectLayout) -> Snapshot:
        """The snapshot `wire` carries, with `layout` (of the same dictionary)."""
        cycle, axes, values, shape, machine, texts, stamp = wire
        return cls(
            cycle,
            tuple(axes),
            np.frombuffer(values, dtype=np.float64).reshape(shape),
            np.frombuffer(machine, dtype=np.float64),
            layout,
            tuple(texts),
            stamp,
        )

    def value(self, obj: ObjectDef, axis: int) -> Any:
        """Decoded value of `obj` for `axis` (axis 0 for machine objects)."""
        if obj.scope == "machine":
            if obj.type.name == "STRING":
                i = self.layout.text_index[obj.name]
                return self.texts[i] if i < len(self.texts) else ""
            return to_python(obj, self.machine[self.layout.machine_index[obj.name]])
        return to_python(obj, self.values[self.slot(axis), self.layout.column[obj.name]])

    def changed(self, prev: Snapshot | None) -> list[tuple[ObjectDef, int]]:
        """`(object, axis)` of every value that differs from `prev` (all of them when
        `prev` is None; axis 0 for machine objects). One array comparison: an idle
        machine costs almost nothing."""
        lay = self.layout
        if prev is None:
            return [(o, a) for a in self.axes for o in lay.axis_objects] + [
                (o, 0) for o in (*lay.machine_objects, *lay.text_objects)
            ]
        rows, cols = np.nonzero(self.values != prev.values)
        out = [
            (lay.axis_objects[c], self.axes[r])
            for r, c in zip(rows.tolist(), cols.tolist(), strict=True)
        ]
        out += [(lay.machine_objects[i], 0) for i in np.nonzero(self.machine != prev.machine)[0]]
        if self.texts != prev.texts:
            out += [
                (o, 0)
                for i, o in enumerate(lay.text_objects)
                if self.value(o, 0) != prev.value(o, 0)
            ]
        return out

    def encode(self, obj: ObjectDef, axis: int) -> bytes:
        """ADS bytes of `obj` for `axis`, as they were at the end of this cycle."""
        return self.kept("ads", obj, axis, lambda: obj.encode_reply(self.value(obj, axis)))

    def kept(self, form: str, obj: ObjectDef, axis: int, make: Callable[[], bytes]) -> bytes:
        """`make()`: the value of `obj` for `axis` in the form `form` ("ads" bytes, an
        interface's own), made once per snapshot (a snapshot never changes); at most one
        entry per form, object and axis."""
        key = (form, obj.name, axis)
        data = self._kept.get(key)
        if data is None:
            data = self._kept[key] = make()
        return data
