"""Typed entry values of one list, and the reporter that turns checks into diagnostics.

002 §1.3: "any defective entries found by the plausibility check are replaced by default
values. Unknown entries are not taken over. These irregularities are displayed by
warning messages." `read_values` implements exactly that for one list; range problems of
compensation entries are kept aside (`Values.range_errors`) so the builder can report
them with the axis number and deactivate that compensation (docs/design.md §4).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import overload

from geo_server.listfile.checks import CHECK_BY_KEY
from geo_server.listfile.schema import (
    ListKind,
    Spec,
    Value,
    convert,
    list_kinds_of,
    lookup,
    nearest_name,
    out_of_range,
)
from geo_server.listfile.syntax import Entry, ParsedList
from geo_server.model import CompKind, Diagnostic

#: Unknown entries of one list that get a "did you mean" hint; the search costs about a
#: third of a millisecond, and a list of nothing but unknown names gains nothing from more.
HINTED_UNKNOWN_ENTRIES = 100


@dataclass
class Item:
    """A converted value and the line it came from."""

    value: Value
    entry: Entry


@dataclass
class Values:
    """Converted entries of one list: canonical base name -> indices -> item."""

    path: str
    data: dict[str, dict[tuple[int, ...], Item]] = field(default_factory=dict)
    range_errors: list[tuple[Spec, Entry, str]] = field(default_factory=list)

    def item(self, base: str, index: tuple[int, ...] = ()) -> Item | None:
        return self.data.get(base, {}).get(index)

    @overload
    def get(self, base: str, default: None = None, index: tuple[int, ...] = ()) -> Value | None: ...

    @overload
    def get(self, base: str, default: Value, index: tuple[int, ...] = ()) -> Value: ...

    def get(
        self, base: str, default: Value | None = None, index: tuple[int, ...] = ()
    ) -> Value | None:
        it = self.item(base, index)
        return default if it is None else it.value

    def table(self, base: str) -> dict[tuple[int, ...], Item]:
        return self.data.get(base, {})

    def section(self, prefix: str) -> list[Item]:
        """Every item whose name starts with `prefix`, in file order."""
        items = [
            it for base, t in self.data.items() if base.startswith(prefix) for it in t.values()
        ]
        return sorted(items, key=lambda it: it.entry.line)


class Reporter:
    """Appends diagnostics for the checks of `checks.CHECKS` to one list."""

    def __init__(self, out: list[Diagnostic]) -> None:
        self.out = out

    def report(
        self,
        key: str,
        message: str,
        *,
        file: str = "",
        line: int = 0,
        entry: str = "",
        axis: int = 0,
    ) -> Diagnostic:
        check = CHECK_BY_KEY[key]
        diag = Diagnostic(
            check.severity,
            message,
            file=file,
            line=line,
            entry=entry,
            error_id=check.error_id,
            axis=axis,
            deactivated=check.comp if check.deactivates else None,
            replaced=check.replaces,
        )
        self.out.append(diag)
        return diag

    def at(self, key: str, message: str, entry: Entry, axis: int = 0) -> Diagnostic:
        """Report a check at the line of `entry`."""
        return self.report(
            key, message, file=entry.file, line=entry.line, entry=entry.name, axis=axis
        )


def read_values(parsed: ParsedList, kind: ListKind, rep: Reporter) -> Values:
    """Convert every entry of `parsed` as a list of `kind` (002 §1.3 plausibility)."""
    rep.out.extend(parsed.warnings)
    values = Values(parsed.path)
    unknown = 0
    for entry in parsed.entries:
        spec = lookup(kind, entry.base)
        if spec is None:
            hint = unknown < HINTED_UNKNOWN_ENTRIES
            rep.at("list.unknown", unknown_message(kind, entry, hint), entry)
            unknown += 1
            continue
        _store(values, spec, entry, rep)
    return values


def unknown_message(kind: ListKind, entry: Entry, hint: bool = True) -> str:
    """The warning for an entry a list of `kind` does not know (002 §1.3: not taken
    over); with `hint`, the list the entry belongs to or the nearest known name."""
    message = f"unknown entry in the {kind.value}: ignored"
    if not hint:
        return message
    other = [k for k in list_kinds_of(entry.base) if k != kind]
    if other:
        return f"{message} (an entry of the {other[0].value})"
    near = nearest_name(kind, entry.base)
    if near is None:
        return message
    return f"{message}; did you mean {with_indices(near, entry.indices)}?"


def with_indices(base: str, indices: tuple[int, ...]) -> str:
    """`kw.ssfk.table[].pos`, (3,) -> `kw.ssfk.table[3].pos` (unchanged if they do not fit)."""
    if base.count("[]") != len(indices):
        return base
    for i in indices:
        base = base.replace("[]", f"[{i}]", 1)
    return base


def _store(values: Values, spec: Spec, entry: Entry, rep: Reporter) -> None:
    if spec.alias_warning:
        rep.at("list.alias", f"read as {spec.key} (name as misprinted in a manual)", entry)
    try:
        value = convert(spec, entry.value)
    except ValueError as exc:
        rep.at("list.defective", f"defective value, default used: {exc}", entry)
        return
    if spec.max_len is not None and len(str(value)) > spec.max_len:
        rep.at(
            "list.length",
            f"{len(str(value))} characters, at most {spec.max_len} ({spec.pid}): kept as given",
            entry,
        )
    problem = out_of_range(spec, value)
    if problem and spec.comp is None:
        rep.at("list.defective", f"{problem}: default used", entry)
        return
    if problem:
        values.range_errors.append((spec, entry, problem))
    table = values.data.setdefault(spec.key, {})
    if entry.indices in table:
        prev = table[entry.indices].entry
        rep.at("list.duplicate", f"given twice (also line {prev.line}); this one counts", entry)
    table[entry.indices] = Item(value, entry)


def range_errors_of(values: Values, comp: CompKind) -> list[tuple[Spec, Entry, str]]:
    """The out-of-range entries that belong to compensation `comp`."""
    return [r for r in values.range_errors if r[0].comp == comp]
