"""Comparing two traces with tolerances: golden-trace tests (docs/recorder.md §6).

Rows are matched by cycle. A tolerance is `pattern=value` (fnmatch on the column label,
`TEMPC::*=0.5`, `SIM::command_position@1=2`); the first pattern that matches a column
applies, else `default` (0: exactly equal). A relative part `value%` adds that fraction of
the golden value. The report names each failing column with its tolerance, the largest
deviation, the first failing cycle with both values, and how many samples fail.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from geo_server.recorder.trace import Trace


@dataclass(frozen=True)
class Tolerance:
    pattern: str
    absolute: float = 0.0
    relative: float = 0.0  # fraction of |golden|

    def text(self) -> str:
        parts = [f"{self.absolute:g}"] if self.absolute or not self.relative else []
        if self.relative:
            parts.append(f"{self.relative * 100:g}%")
        return " + ".join(parts)


def parse_tolerances(items: Iterable[str]) -> list[Tolerance]:
    """`["TEMPC::*=0.5", "*@2=1%", "SIM::feed=10+1%"]` → tolerances (ValueError names
    the bad item)."""
    out = []
    for item in items:
        pattern, sep, value = item.partition("=")
        if not sep or not pattern:
            raise ValueError(f"tolerance {item!r}: expected PATTERN=VALUE, e.g. TEMPC::*=0.5")
        absolute = relative = 0.0
        try:
            for part in value.split("+"):
                part = part.strip()
                if part.endswith("%"):
                    relative += float(part[:-1]) / 100
                else:
                    absolute += float(part)
        except ValueError:
            raise ValueError(f"tolerance {item!r}: {value!r} is not a number or N%") from None
        if absolute < 0 or relative < 0:
            raise ValueError(f"tolerance {item!r}: must not be negative")
        out.append(Tolerance(pattern, absolute, relative))
    return out


@dataclass
class ColumnResult:
    label: str
    tolerance: Tolerance
    max_dev: float
    failures: int
    first_cycle: int | None = None
    golden: float = 0.0
    actual: float = 0.0


@dataclass
class Comparison:
    columns: list[ColumnResult] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)  # in the golden trace only
    extra: list[str] = field(default_factory=list)  # in the new trace only
    missing_cycles: list[int] = field(default_factory=list)
    extra_cycles: list[int] = field(default_factory=list)
    compared_rows: int = 0

    @property
    def failed(self) -> list[ColumnResult]:
        return [c for c in self.columns if c.failures]

    @property
    def ok(self) -> bool:
        return not (self.failed or self.missing or self.missing_cycles or self.extra)

    def report(self) -> str:
        """A readable diff; the first line says whether the traces match."""
        head = (
            f"traces match: {len(self.columns)} columns, {self.compared_rows} rows"
            if self.ok
            else f"traces differ: {len(self.failed)} of {len(self.columns)} columns "
            f"out of tolerance, {self.compared_rows} rows compared"
        )
        lines = [head]
        if self.missing:
            lines.append(f"missing columns (in the golden trace only): {', '.join(self.missing)}")
        if self.extra:
            lines.append(f"extra columns (not in the golden trace): {', '.join(self.extra)}")
        if self.missing_cycles:
            lines.append(f"missing cycles: {_span(self.missing_cycles)}")
        if self.extra_cycles:
            lines.append(f"extra cycles (ignored): {_span(self.extra_cycles)}")
        if self.failed:
            lines.append(
                "column | tolerance | max |Δ| | first failing cycle: golden → new | failing"
            )
            for c in self.failed:
                lines.append(
                    f"{c.label} | {c.tolerance.text()} | {c.max_dev:g} | "
                    f"{c.first_cycle}: {c.golden:g} → {c.actual:g} | {c.failures}"
                )
        return "\n".join(lines)


def _span(cycles: list[int]) -> str:
    shown = ", ".join(str(c) for c in cycles[:5])
    return f"{shown}{', …' if len(cycles) > 5 else ''} ({len(cycles)})"


def _tolerance(label: str, tolerances: list[Tolerance], default: float) -> Tolerance:
    for t in tolerances:
        if fnmatch.fnmatchcase(label, t.pattern):
            return t
    return Tolerance("*", default)


def compare(
    golden: Trace,
    new: Trace,
    tolerances: Iterable[Tolerance | str] = (),
    default: float = 0.0,
) -> Comparison:
    """Compare `new` against `golden` on their common cycles and columns."""
    tols = [t if isinstance(t, Tolerance) else parse_tolerances([t])[0] for t in tolerances]
    result = Comparison(
        missing=[c for c in golden.labels if c not in new.labels],
        extra=[c for c in new.labels if c not in golden.labels],
    )
    gc, nc = golden.cycles, new.cycles
    common, gi, ni = np.intersect1d(gc, nc, return_indices=True)
    result.missing_cycles = sorted(set(gc.tolist()) - set(common.tolist()))
    result.extra_cycles = sorted(set(nc.tolist()) - set(common.tolist()))
    result.compared_rows = len(common)
    for label in golden.labels:
        if label not in new.labels:
            continue
        tol = _tolerance(label, tols, default)
        g = golden.column(label)[gi]
        n = new.column(label)[ni]
        dev = np.abs(n - g)
        bad = np.nonzero(dev > tol.absolute + tol.relative * np.abs(g))[0]
        col = ColumnResult(label, tol, float(dev.max()) if len(dev) else 0.0, len(bad))
        if len(bad):
            k = int(bad[0])
            col.first_cycle, col.golden, col.actual = int(common[k]), float(g[k]), float(n[k])
        result.columns.append(col)
    return result
