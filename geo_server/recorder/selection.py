"""Which objects a recording holds, and its trigger (docs/recorder.md §1–2).

A *selector* names objects: `TEMPC::coefficient` (every configured axis; a machine-wide
object once), `TEMPC::coefficient@1` or `@X` (one axis, by number or name), a wildcard
`TEMPC::*` / `*::f_is_active@2` (fnmatch on the dictionary's names, any case), or an ADS
address `0x120300:0x10043` (index group : index offset). Only numeric and boolean objects
that can be read are recorded (texts and write-only commands are skipped by wildcards
and refused by name).

A *trigger* is `<one column> <op> <number>` with op `> >= < <= == !=`, or `<one column>
rising|falling|changes` (rising: from ≤ 0 / FALSE to > 0 / TRUE).
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.errors import AdsError, GeoError


class SelectionError(GeoError, ValueError):
    """A selector or trigger that names nothing recordable; the message says why."""


@dataclass(frozen=True)
class Column:
    """One recorded value: an object of one axis (axis 0: machine-wide)."""

    obj: ObjectDef
    axis: int

    @property
    def label(self) -> str:
        """`NAME@axis` for axis objects, `NAME` for machine-wide ones (the CSV header)."""
        return f"{self.obj.name}@{self.axis}" if self.obj.scope == "axis" else self.obj.name


def recordable(obj: ObjectDef) -> bool:
    return "r" in obj.access and obj.type.name != "STRING" and obj.command is None


def _axis_of(text: str, axes: tuple[int, ...], names: Mapping[int, str]) -> int:
    if text.isdigit() and int(text) in axes:
        return int(text)
    for a, n in names.items():
        if n.upper() == text.upper():
            return a
    known = ", ".join(f"{a} {names.get(a, '')}".strip() for a in axes)
    raise SelectionError(f"no axis {text!r} (axes: {known})")


def _by_address(text: str, dictionary: Dictionary, axes: tuple[int, ...]) -> list[Column] | None:
    m = re.fullmatch(r"(0x[0-9a-fA-F]+|\d+):(0x[0-9a-fA-F]+|\d+)", text)
    if m is None:
        return None
    try:
        obj, axis, attr = dictionary.resolve(int(m[1], 0), int(m[2], 0), axes)
    except AdsError as exc:
        raise SelectionError(f"selector {text!r}: {exc.message}") from None
    if attr or not recordable(obj):
        raise SelectionError(f"selector {text!r}: {obj.name} cannot be recorded")
    return [Column(obj, axis if obj.scope == "axis" else 0)]


def select(
    text: str, dictionary: Dictionary, axes: tuple[int, ...], names: Mapping[int, str]
) -> list[Column]:
    """The columns one selector names, in dictionary and axis order."""
    text = text.strip()
    by_address = _by_address(text, dictionary, axes)
    if by_address is not None:
        return by_address
    pattern, _, axis_text = text.partition("@")
    only = _axis_of(axis_text, axes, names) if axis_text else None
    if any(c in pattern for c in "*?["):
        objs = [
            o
            for o in dictionary.objects
            if recordable(o) and fnmatch.fnmatchcase(o.name.lower(), pattern.lower())
        ]
    else:
        try:
            obj = dictionary.by_name(pattern)
        except AdsError as exc:
            raise SelectionError(f"selector {text!r}: {exc.message}") from None
        if not recordable(obj):
            raise SelectionError(f"selector {text!r}: {obj.name} cannot be recorded")
        objs = [obj]
    cols: list[Column] = []
    for o in objs:
        if o.scope == "machine":
            if only is None:
                cols.append(Column(o, 0))
        else:
            cols += [Column(o, a) for a in axes if only is None or a == only]
    if not cols:
        raise SelectionError(f"selector {text!r} names no recordable object")
    return cols


def resolve_columns(
    selectors: Iterable[str],
    dictionary: Dictionary,
    axes: tuple[int, ...],
    names: Mapping[int, str] | None = None,
) -> list[Column]:
    """Every column of `selectors`, each once, in the order first named."""
    out: dict[str, Column] = {}
    for s in selectors:
        for c in select(s, dictionary, axes, names or {}):
            out.setdefault(c.label, c)
    if not out:
        raise SelectionError("nothing to record: give at least one selector")
    return list(out.values())


OPS = (">=", "<=", "==", "!=", ">", "<")
EDGES = ("rising", "falling", "changes")


@dataclass(frozen=True)
class Trigger:
    """`column op value` or an edge of `column` (docs/recorder.md §2)."""

    column: Column
    op: str
    value: float = 0.0
    text: str = ""

    def fires(self, before: float | None, now: float) -> bool:
        """Does this sample (with the one before it) fire the trigger?"""
        op = self.op
        if op in EDGES:
            if before is None:
                return False
            if op == "rising":
                return before <= 0 < now
            if op == "falling":
                return before > 0 >= now
            return before != now
        return {
            ">": now > self.value,
            ">=": now >= self.value,
            "<": now < self.value,
            "<=": now <= self.value,
            "==": now == self.value,
            "!=": now != self.value,
        }[op]


def parse_trigger(
    text: str, dictionary: Dictionary, axes: tuple[int, ...], names: Mapping[int, str]
) -> Trigger:
    """`SIM::command_position@1 > 100000`, `SIM::program_running rising`, …"""
    m = re.fullmatch(r"\s*(\S+)\s+(rising|falling|changes)\s*", text)
    if m:
        subject, op, rest = m[1], m[2], ""
    else:
        m = re.fullmatch(r"\s*(\S+?)\s*(>=|<=|==|!=|>|<)\s*(\S+)\s*", text)
        if m is None:
            raise SelectionError(
                f"trigger {text!r}: expected '<object>[@axis] <op> <number>' (op one of "
                f"{' '.join(OPS)}) or '<object>[@axis] rising|falling|changes'"
            )
        subject, op, rest = m[1], m[2], m[3]
    cols = select(subject, dictionary, axes, names)
    if len(cols) != 1:
        raise SelectionError(
            f"trigger {text!r}: {subject!r} names {len(cols)} values; name one axis (@1)"
        )
    value = 0.0
    if rest:
        low = rest.lower()
        try:
            value = 1.0 if low == "true" else 0.0 if low == "false" else float(rest)
        except ValueError:
            raise SelectionError(f"trigger {text!r}: {rest!r} is not a number") from None
    return Trigger(cols[0], op, value, text.strip())
