"""Leadscrew error compensation LSEC (000 §4.4 p.50–63; docs/design.md §6.5): its tables.

Its lookup is the 1-D law of every table (`tables.interpolate`); its query position
includes this cycle's filtered cross and plane outputs, so the kernel runs it after the
sin² filter of the other columns, with its own sin² pass on column LEAD (`sin2.output`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geo_server.kernel.common import CROSS, LEAD, PLANE, POS
from geo_server.kernel.inputs import SourceVector
from geo_server.kernel.tables import Lookup, MergedTable
from geo_server.model import AxisConfig


def _i64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=np.int64).reshape(-1)


def _f64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=float).reshape(-1)


@dataclass(frozen=True, slots=True, eq=False)
class ColumnViews:
    """One column c of the kernel's [n, 7] arrays and of its sin² filter (views)."""

    target: np.ndarray
    actual: np.ndarray
    effective: np.ndarray
    prev: np.ndarray  # output of the previous cycle
    event: np.ndarray
    tmp: np.ndarray
    jump: np.ndarray
    weight: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class LsecTables:
    """Leadscrew error (000 §4.4; docs/design.md §6.5): −Δs at the command position plus
    this cycle's filtered cross and plane outputs (command alone with
    `set_pos_without_comp`), from `pos`, or from `neg` while moving negative when
    bilateral; a `modulo` table wraps into [first setpoint, first + period).

    Its own `MergedTable` with three rows per axis j: 3j (neg; = pos when unilateral),
    3j + 1 (unused), 3j + 2 (pos), values negated once here. One gather of (direction,
    command position) from S and one add of (3j + 1, cross + plane) give the complex
    query (row id 3j + 1 ± 1, position) directly. Then its own sin² pass on column LEAD
    (its reversal events were set with the others').
    """

    lookup: Lookup
    src: np.ndarray  # [L, 2] index into S of (direction, position)
    g: np.ndarray  # [L, 2] scratch
    add: np.ndarray  # [L, 2] (3j + 1, cross + plane)
    t: np.ndarray  # add[:, 1]
    qf: np.ndarray  # the query as [L, 2] (row id, position) pairs
    cp: np.ndarray  # [2, L] index into actual.reshape(-1) of (cross, plane)
    cpv: np.ndarray  # [2, L]
    cp0: np.ndarray
    cp1: np.ndarray
    wc: np.ndarray  # 0 with set_pos_without_comp, else 1
    all_wc: bool
    x0: np.ndarray  # first setpoint
    per: np.ndarray  # the table's period
    wrap: np.ndarray
    any_wrap: bool
    d: np.ndarray  # [L] scratch
    all: bool  # every axis has LSEC: straight into the target column
    flat: np.ndarray  # index into target.reshape(-1) of the LSEC targets
    val: np.ndarray  # [L]
    col: ColumnViews  # column LEAD

    @classmethod
    def build(
        cls,
        axes: list[AxisConfig],
        rows: list[int],
        src: SourceVector,
        modulo: np.ndarray,
        period: np.ndarray,
        col: ColumnViews,
    ) -> LsecTables | None:
        L = len(rows)
        if not L:
            return None
        ls = [axes[i].comp.lsec for i in rows]
        tables = []
        for x in ls:
            tables.append((x.setpoint, x.neg if x.bilateral else x.pos))
            tables.append((np.zeros(1), np.zeros(1)))
            tables.append((x.setpoint, x.pos))
        # the table holds measured errors Δs = s_actual − s_programmed: apply −Δs
        tables = [(np.asarray(k, dtype=float), -np.asarray(v, dtype=float)) for k, v in tables]
        lookup = Lookup(MergedTable(tables), np.arange(L, dtype=float) * 3 + 1)
        slots = _i64(rows)
        add = np.zeros((L, 2))
        add[:, 0] = np.arange(L, dtype=float) * 3 + 1
        wc = _f64([0.0 if x.set_pos_without_comp else 1.0 for x in ls])
        x0 = _f64([float(x.setpoint[0]) for x in ls])
        # the table's period: the axis period on a modulo axis, else the distance between
        # first and last setpoint (000 §4.4: they are one period apart)
        spans = _f64([float(x.setpoint[-1] - x.setpoint[0]) for x in ls])
        per = np.where(modulo[slots], period[slots], spans)
        wrap = np.logical_and([x.modulo for x in ls], per > 0)
        cpv = np.zeros((2, L))
        return cls(
            lookup=lookup,
            src=np.stack([src.dir_index(slots), src.index(POS, slots)], axis=1),
            g=np.zeros((L, 2)),
            add=add,
            t=add[:, 1],
            qf=lookup.pairs,
            cp=np.stack([slots * 7 + CROSS, slots * 7 + PLANE]),
            cpv=cpv,
            cp0=cpv[0],
            cp1=cpv[1],
            wc=wc,
            all_wc=bool(wc.all()),
            x0=x0,
            per=np.where(per > 0, per, 1.0),
            wrap=wrap,
            any_wrap=bool(wrap.any()),
            d=np.zeros(L),
            all=rows == list(range(len(axes))),
            flat=slots * 7 + LEAD,
            val=np.zeros(L),
            col=col,
        )
