"""Compensation value list [COMP] (`achskw*.lis`) -> `CompList` (002/003 §2–§3, 000 §4).

Every builder reads one compensation's entries, runs that compensation's checks (table
in `checks.py`) and returns the config dataclass with `valid=False` if any check failed;
the other compensations of the same list are not affected (docs/design.md §4).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import overload

import numpy as np

from geo_server.listfile.checks import RANGE_CHECK
from geo_server.listfile.schema import Value
from geo_server.listfile.syntax import Entry
from geo_server.listfile.values import Reporter, Values, range_errors_of
from geo_server.model import (
    CROSSTALK_COLUMNS,
    AxisParams,
    CompKind,
    CompList,
    CrossComp,
    CrosstalkComp,
    FrictComp,
    LsecComp,
    PlaneComp,
)

#: Section prefixes of the compensations (000 §4.1 p.27 "Body of the list").
PREFIX: dict[CompKind, str] = {
    CompKind.CROSS: "kw.crosscomp.",
    CompKind.PLANE: "kw.crosscomp2.",
    CompKind.LEAD: "kw.ssfk.",
    CompKind.FRICT: "frict_comp.",
    CompKind.CROSSTALK: "kw.crosstalk.",
}
MAX_CROSSTALK_POINTS = 15  # 000 §4.6 "up to 15 measurement tests"
#: Each plane last index without `max_points` ("the previous restrictions", 000 p.44)
PLANE_LAST_INDEX_MAX = 100
_PLANE_READ_LIMIT = 4_000_000  # grid points read into memory at most


@dataclass
class Ctx:
    """What a builder needs to know about the machine."""

    axis: AxisParams  # the axis the list belongs to (the slave)
    axes: dict[int, AxisParams]
    rep: Reporter


class _Build:
    """Failure bookkeeping and common reads for one compensation of one list."""

    def __init__(self, comp: CompKind, values: Values, ctx: Ctx) -> None:
        self.comp, self.v, self.ctx, self.ok = comp, values, ctx, True
        self.incomplete: set[str] = set()
        self.prefix = PREFIX[comp]
        items = values.section(self.prefix)
        self.anchor_line = items[0].entry.line if items else 0
        for _spec, entry, problem in range_errors_of(values, comp):
            self.fail(RANGE_CHECK[comp], problem, entry)

    def fail(self, key: str, message: str, where: Entry | str) -> None:
        self.ok = False
        self.note(key, message, where)

    def note(self, key: str, message: str, where: Entry | str) -> None:
        axis = self.ctx.axis.log_nr
        if isinstance(where, Entry):
            self.ctx.rep.at(key, message, where, axis=axis)
        else:
            self.ctx.rep.report(
                key, message, file=self.v.path, line=self.anchor_line, entry=where, axis=axis
            )

    def name(self, short: str) -> str:
        return self.prefix + short

    @overload
    def get(self, short: str, default: Value = 0) -> Value: ...

    @overload
    def get(self, short: str, default: None) -> Value | None: ...

    def get(self, short: str, default: Value | None = 0) -> Value | None:
        return self.v.get(self.name(short), default)

    def entry(self, short: str) -> Entry | str:
        item = self.v.item(self.name(short))
        return item.entry if item else self.name(short)

    def required(self, short: str, key: str) -> int | None:
        item = self.v.item(self.name(short))
        if item is None:
            self.fail(key, "required entry missing", self.name(short))
            return None
        return item.value  # type: ignore[return-value]

    def axis_ref(self, short: str, missing: str, bad: str, *, slave_ok: bool = False) -> int:
        """A logical axis number entry that must name an axis of the machine."""
        nr = self.required(short, missing)
        if nr is None:
            return 0
        if nr not in self.ctx.axes:
            self.fail(bad, f"axis {nr} is not an axis of the machine", self.entry(short))
        elif nr == self.ctx.axis.log_nr and not slave_ok:
            self.fail(bad, f"axis {nr} is the compensated axis itself", self.entry(short))
        return nr

    def column(
        self, short: str, n: int | None, index_key: str, missing_key: str | None
    ) -> np.ndarray:
        """Values `table[0..n-1].<short>` as float64; checks indices and completeness."""
        base = self.name(short)
        table = self.v.table(base)
        out = np.zeros(max(n or 0, 0))
        if n is None:
            return out
        beyond = [it.entry for idx, it in table.items() if not 0 <= idx[0] < n]
        if beyond:
            self.fail(index_key, f"index outside 0…{n - 1} ({len(beyond)} entries)", beyond[0])
        missing = [i for i in range(n) if (i,) not in table]
        if missing:
            self.incomplete.add(short)
        if missing and missing_key:
            where = base.replace("[]", f"[{missing[0]}]")
            self.fail(missing_key, f"{len(missing)} of {n} values missing", where)
        for (i, *_), it in table.items():
            if 0 <= i < n:
                out[i] = float(it.value)
        return out

    def ascending(self, arr: np.ndarray, short: str, key: str) -> None:
        """Strictly ascending values (not checked when the column has gaps)."""
        if short in self.incomplete:
            return
        bad = np.nonzero(np.diff(arr) <= 0)[0]
        if bad.size:
            i = int(bad[0]) + 1
            where = self.v.item(self.name(short), (i,))
            loc = where.entry if where else self.name(short)
            self.fail(key, f"values not strictly ascending at index {i}", loc)


# --------------------------------------------------------------------------- cross


def build_cross(values: Values, ctx: Ctx) -> CrossComp | None:
    """`kw.crosscomp.*` (002 §3.1, 000 §4.2): one master, ascending setpoints."""
    if not values.section(PREFIX[CompKind.CROSS]):
        return None
    b = _Build(CompKind.CROSS, values, ctx)
    master = b.axis_ref("master_ax_nr", "cross.master", "cross.axis")
    max_points = int(b.get("max_points") or 1001)  # 0 / missing: default (002 §3.1.1)
    last = b.required("last_index", "cross.last_index")
    n = None
    if last is not None and last >= max_points:
        b.fail("cross.size", f"last_index {last} >= max_points {max_points}", b.entry("last_index"))
    elif last is not None and last >= 0:
        n = last + 1
    setpoint = b.column("table[].setpoint", n, "cross.index", "cross.incomplete")
    correction = b.column("table[].correction", n, "cross.index", "cross.incomplete")
    b.ascending(setpoint, "table[].setpoint", "cross.order")
    return CrossComp(
        master_ax_nr=master,
        setpoint=setpoint,
        correction=correction,
        n_cycles=int(b.get("n_cycles")),
        manual_activation=bool(b.get("manual_activation", False)),
        max_points=max_points,
        unit=int(b.get("unit", 1)),
        valid=b.ok,
    )


# --------------------------------------------------------------------------- plane


def build_plane(values: Values, ctx: Ctx) -> PlaneComp | None:
    """`kw.crosscomp2.*` (002 §3.2, 000 §4.3): grid `table[j][i]`, j = master 2."""
    if not values.section(PREFIX[CompKind.PLANE]):
        return None
    b = _Build(CompKind.PLANE, values, ctx)
    grid = str(b.get("grid", "QUADRATIC")).strip().upper()
    if grid not in ("QUADRATIC", "RECTANGULAR"):
        b.fail("plane.range", f"grid {grid!r} is not QUADRATIC or RECTANGULAR", b.entry("grid"))
    i1, i2 = _plane_intervals(b, grid)
    # "One of the master axes can also be the slave axis itself" (001 §4.4; 000 §4.3 p.38)
    m1 = b.axis_ref("master1_ax_nr", "plane.missing", "plane.axis", slave_ok=True)
    m2 = b.axis_ref("master2_ax_nr", "plane.missing", "plane.axis", slave_ok=True)
    if m1 and m1 == m2:
        b.fail("plane.axis", "both master axes are the same axis", b.entry("master2_ax_nr"))
    given = int(b.get("max_points") or 0)  # 0 / missing: the default (002 §3.2.1)
    max_points = given or 10201
    l1 = b.required("last_index_master1", "plane.missing")
    l2 = b.required("last_index_master2", "plane.missing")
    table = np.zeros((1, 1))
    if l1 is not None and l2 is not None and l1 >= 0 and l2 >= 0:
        points = (l1 + 1) * (l2 + 1)
        # 000 p.44: without max_points "the previous restrictions apply": each last
        # index at most 100 (a 201 x 21 table fits 10201 points, and is still refused)
        over = [(k, v) for k, v in ((1, l1), (2, l2)) if v > PLANE_LAST_INDEX_MAX]
        if not given and over:
            k, v = over[0]
            b.fail(
                "plane.size",
                f"last_index_master{k} {v} > {PLANE_LAST_INDEX_MAX}: without max_points "
                f"each last index is at most {PLANE_LAST_INDEX_MAX} (000 p.44)",
                b.entry(f"last_index_master{k}"),
            )
        elif points > max_points:
            msg = f"(last_index_master1+1)·(last_index_master2+1) = {points}"
            b.fail("plane.size", f"{msg} > max_points {max_points}", b.entry("last_index_master2"))
        if points <= _PLANE_READ_LIMIT:  # read even when too big, for the diagnostics
            table = _plane_table(b, l1, l2)
    return PlaneComp(
        master1_ax_nr=m1,
        master2_ax_nr=m2,
        start_position_master1=float(b.get("start_position_master1")),
        start_position_master2=float(b.get("start_position_master2")),
        interval1=float(i1),
        interval2=float(i2),
        table=table,
        grid=grid,
        n_cycles=int(b.get("n_cycles")),
        manual_activation=bool(b.get("manual_activation", False)),
        max_points=max_points,
        unit=int(b.get("unit", 1)),
        valid=b.ok,
    )


def _plane_intervals(b: _Build, grid: str) -> tuple[int, int]:
    """QUADRATIC: `interval` for both; RECTANGULAR: `interval1`/`interval2` (002 §3.2.2)."""
    if grid != "RECTANGULAR":
        iv = b.required("interval", "plane.missing")
        return iv or 0, iv or 0
    common = b.get("interval", None)
    out = []
    for short in ("interval1", "interval2"):
        value = b.get(short, common)
        if value is None:
            b.fail("plane.missing", "required entry missing (RECTANGULAR grid)", b.name(short))
        out.append(int(value or 0))
    return out[0], out[1]


def _plane_table(b: _Build, l1: int, l2: int) -> np.ndarray:
    table = np.zeros((l2 + 1, l1 + 1))  # unassigned points are 0 (002 §3.2.14)
    for idx, it in b.v.table(b.name("table[][].correction")).items():
        j, i = idx
        if 0 <= j <= l2 and 0 <= i <= l1:
            table[j, i] = float(it.value)
        else:
            b.fail("plane.size", f"index [{j}][{i}] beyond [{l2}][{l1}]", it.entry)
    return table


# --------------------------------------------------------------------------- LSEC


def build_lsec(values: Values, ctx: Ctx) -> LsecComp | None:
    """`kw.ssfk.*` (002 §3.3, 000 §4.4): table index 0…kw_nr_max−1 (docs/design.md §12)."""
    if not values.section(PREFIX[CompKind.LEAD]):
        return None
    b = _Build(CompKind.LEAD, values, ctx)
    max_points = int(b.get("max_points") or 1500)
    n = _lsec_count(b, max_points)
    interval, start = int(b.get("interval")), int(b.get("kw_startpos"))
    if interval > 0:
        setpoint = start + interval * np.arange(max(n or 0, 0), dtype=float)
        if b.v.table(b.name("table[].setpoint")):
            b.note(
                "list.ignored", "setpoints ignored: the table is equidistant", "table[].setpoint"
            )
    else:
        setpoint = b.column("table[].setpoint", n, "lead.index", "lead.setpoint")
        b.ascending(setpoint, "table[].setpoint", "lead.order")
    pos = b.column("table[].pos", n, "lead.index", "lead.pos")
    bilateral = bool(b.get("bilateral", False))
    if bilateral:
        neg = b.column("table[].neg", n, "lead.index", "lead.bilateral")
    else:
        if b.v.table(b.name("table[].neg")):
            b.note(
                "list.ignored", "neg values ignored: the table is unilateral", b.name("table[].neg")
            )
        neg = pos.copy()
    modulo = bool(b.get("modulo", False))
    _lsec_axis_checks(b, ctx.axis, setpoint, modulo)
    return LsecComp(
        setpoint=setpoint,
        pos=pos,
        neg=neg,
        bilateral=bilateral,
        modulo=modulo,
        set_pos_without_comp=bool(b.get("set_pos_without_comp", False)),
        manual_activation=bool(b.get("manual_activation", False)),
        interval=interval,
        kw_startpos=start,
        max_points=max_points,
        unit=int(b.get("unit", 1)),
        valid=b.ok,
    )


def _lsec_count(b: _Build, max_points: int) -> int | None:
    n = b.get("kw_nr_max", None)
    if not n:
        b.fail("lead.missing", "kw_nr_max missing or 0: no table", b.entry("kw_nr_max"))
        return None
    if n >= max_points:  # type: ignore[operator]  # ("must be smaller", 000 p.57)
        msg = f"kw_nr_max {n} must be smaller than max_points {max_points} (000 p.57)"
        b.fail("lead.size", msg, b.entry("kw_nr_max"))
        return None
    return n if n > 0 else None  # type: ignore[operator, return-value]


def _lsec_axis_checks(b: _Build, axis: AxisParams, setpoint: np.ndarray, modulo: bool) -> None:
    if axis.kind == "S":
        b.fail("lead.axis_type", "LSEC is for axis types T and R only", b.entry("kw_nr_max"))
    if not modulo:
        return
    where = b.entry("modulo")
    if not axis.modulo:
        b.fail("lead.modulo", "kw.ssfk.modulo 1 but the axis is not a modulo axis", where)
    elif setpoint.size and abs(setpoint[-1] - setpoint[0] - axis.modulo_period) > 0.5:
        span = setpoint[-1] - setpoint[0]
        msg = f"first/last setpoints {span:g} apart, modulo period {axis.modulo_period:g}"
        b.fail("lead.modulo", msg, where)


# --------------------------------------------------------------------------- friction


def build_frict(values: Values, ctx: Ctx) -> FrictComp | None:
    """`frict_comp.*` (002 §3.4, 000 §4.5): current over |velocity|, mode 3 only."""
    if not values.section(PREFIX[CompKind.FRICT]):
        return None
    b = _Build(CompKind.FRICT, values, ctx)
    mode = int(b.get("mode"))
    if mode not in (0, 3):
        b.fail("frict.values", f"unknown mode {mode} (only 3, or 0 = off)", b.entry("mode"))
    elif mode == 0 and ctx.axis.frict_comp:
        b.fail("frict.values", "mode 0 (off) while lr_param.frict_comp is 1", b.entry("mode"))
    max_points = int(b.get("max_points") or 20)
    n = int(b.get("table_entries"))
    if n == 0:
        b.fail("frict.values", "no values: table_entries missing or 0", b.entry("table_entries"))
    elif n > max_points:
        msg = f"table_entries {n} > max_points {max_points}"
        b.fail("frict.values", msg, b.entry("table_entries"))
    size = n if 0 < n <= max_points else None
    vin = b.column("table[].in", size, "frict.values", "frict.values")
    out = b.column("table[].out", size, "frict.values", "frict.values")
    if vin.size and vin[0] < 0:
        first = b.v.item(b.name("table[].in"), (0,))
        where = first.entry if first else b.name("table[].in")
        b.fail("frict.velocity", "negative input velocity", where)
    b.ascending(vin, "table[].in", "frict.velocity")
    delay = int(b.get("position_delay"))
    if not 0 <= delay <= 10:
        b.note(
            "frict.position_delay",
            f"position_delay {delay} outside 0…10: kept",
            b.entry("position_delay"),
        )
    return FrictComp(
        vin=vin,
        out=out,
        mode=mode,
        position_delay=delay,
        reversal_lookahead=int(b.get("reversal_lookahead")),
        scaling_factor=int(b.get("scaling_factor", 1000)),
        delay_cycles=int(b.get("delay_cycles")),
        max_points=max_points,
        valid=b.ok,
    )


# --------------------------------------------------------------------------- crosstalk


def crosstalk_dialect(values: Values) -> str:
    """ "old" if `table[...]` entries exist, "mixed" if also `mode`/`position[...]`, else "new"."""
    p = PREFIX[CompKind.CROSSTALK]
    old = any(k.startswith(p + "table[]") for k in values.data)
    new = any(k.startswith(p + "position[]") or k == p + "mode" for k in values.data)
    return "mixed" if old and new else "old" if old else "new"


def build_crosstalk(values: Values, ctx: Ctx) -> CrosstalkComp | None:
    """`kw.crosstalk.*`, both dialects (000 §4.6 new; 001 §4.5, 003 §3.5 old)."""
    if not values.section(PREFIX[CompKind.CROSSTALK]):
        return None
    b = _Build(CompKind.CROSSTALK, values, ctx)
    dialect = crosstalk_dialect(values)
    if dialect == "mixed":
        b.fail("crosstalk.mode", "entries of both the old and the new model", b.entry("mode"))
    master = b.axis_ref("master_dyn_ax_nr", "crosstalk.master", "crosstalk.master")
    comp = CrosstalkComp(
        dialect="old" if dialect == "old" else "new",
        master_dyn_ax_nr=master,
        n_cycles=int(b.get("n_cycles")),
        manual_activation=bool(b.get("manual_activation", False)),
    )
    if comp.dialect == "old":
        _crosstalk_old(b, comp)
    else:
        _crosstalk_new(b, comp)
    comp.valid = b.ok
    return comp


def _crosstalk_old(b: _Build, comp: CrosstalkComp) -> None:
    """Old model: `last_index` 0…4, `table[i].acceleration`/`.correction` (003 §3.5)."""
    last = b.required("last_index", "crosstalk.old_table")
    n = None
    if last is not None and not 0 <= last <= 4:
        b.fail("crosstalk.old_table", f"last_index {last} not 0…4", b.entry("last_index"))
    elif last is not None:
        n = last + 1
    key = "crosstalk.old_table"
    comp.acc_table = b.column("table[].acceleration", n, key, key)
    comp.corr_table = b.column("table[].correction", n, key, key)
    b.ascending(comp.acc_table, "table[].acceleration", key)


def _crosstalk_new(b: _Build, comp: CrosstalkComp) -> None:
    """New model: mode 1/2/3, reference accelerations, `position[i]` records (000 §4.6)."""
    comp.mode = int(b.get("mode", 1))
    if comp.mode not in (1, 2, 3):
        b.fail("crosstalk.mode", f"mode {comp.mode} not 1…3", b.entry("mode"))
    if b.v.item(b.name("last_index")):
        b.note("list.ignored", "last_index belongs to the old model", b.entry("last_index"))
    comp.acceleration = float(b.get("acceleration"))
    if comp.acceleration <= 0:
        b.fail("crosstalk.acceleration", "acceleration missing or <= 0", b.entry("acceleration"))
    comp.deceleration = float(b.get("deceleration"))
    if comp.deceleration >= 0:
        b.fail("crosstalk.deceleration", "deceleration missing or >= 0", b.entry("deceleration"))
    comp.velocity_dependent = bool(b.get("velocity_dependent", False))
    comp.max_points = int(b.get("max_points") or MAX_CROSSTALK_POINTS)
    if comp.max_points > MAX_CROSSTALK_POINTS:
        b.fail("crosstalk.points", f"max_points {comp.max_points} > 15", b.entry("max_points"))
    _adaptation_axes(b, comp)
    n = _record_count(b, comp)
    comp.ax_1 = b.column("position[].ax_1", n, "crosstalk.points", None)
    comp.ax_2 = b.column("position[].ax_2", n, "crosstalk.points", None)
    cols = [b.column(f"position[].{c}", n, "crosstalk.points", None) for c in _CT_COLS]
    comp.corrections = np.column_stack(cols) if n else np.zeros((0, 4))
    _record_geometry(b, comp)


_CT_COLS = tuple(f"correction_{c}" for c in CROSSTALK_COLUMNS)


def _adaptation_axes(b: _Build, comp: CrosstalkComp) -> None:
    if comp.mode >= 2:
        comp.master_pos1_ax_nr = b.axis_ref(
            "master_pos1_ax_nr", "crosstalk.adapt1", "crosstalk.adapt1", slave_ok=True
        )
    if comp.mode == 3:
        comp.master_pos2_ax_nr = b.axis_ref(
            "master_pos2_ax_nr", "crosstalk.adapt2", "crosstalk.adapt2", slave_ok=True
        )
        if comp.master_pos2_ax_nr and comp.master_pos2_ax_nr == comp.master_pos1_ax_nr:
            b.fail(
                "crosstalk.adapt2", "same axis as master_pos1_ax_nr", b.entry("master_pos2_ax_nr")
            )


def _record_count(b: _Build, comp: CrosstalkComp) -> int | None:
    """Number of `position[i]` records; checks the 15-point limit and gaps."""
    indices = sorted(
        {idx[0] for k, t in b.v.data.items() if k.startswith(b.name("position[]")) for idx in t}
    )
    limit = min(comp.max_points, MAX_CROSSTALK_POINTS)
    if indices and (indices[0] < 0 or indices[-1] >= limit):
        msg = f"position[{indices[-1]}] beyond the {limit} test points allowed"
        b.fail("crosstalk.points", msg, b.name(f"position[{indices[-1]}]"))
        return None
    need = {1: 1, 2: 2, 3: 3}.get(comp.mode, 1)
    if len(indices) < need:
        b.fail(
            "crosstalk.records", f"mode {comp.mode} needs {need} test records", b.name("position[]")
        )
        return None
    if indices != list(range(len(indices))):
        gap = next(i for i in range(len(indices)) if i not in indices)
        b.fail("crosstalk.records", f"test record {gap} missing", b.name(f"position[{gap}]"))
        return None
    return len(indices)


def _record_geometry(b: _Build, comp: CrosstalkComp) -> None:
    if comp.mode == 2 and comp.ax_1.size >= 2 and np.any(np.diff(comp.ax_1) <= 0):
        b.fail("crosstalk.geometry", "ax_1 not strictly ascending", b.name("position[].ax_1"))
    if comp.mode == 3 and comp.ax_1.size >= 3:
        pts = np.column_stack([comp.ax_1, comp.ax_2])
        if len(np.unique(pts, axis=0)) < len(pts):
            b.fail("crosstalk.geometry", "a test point is repeated", b.name("position[].ax_1"))
        elif np.linalg.matrix_rank(pts[1:] - pts[0]) < 2:
            b.fail("crosstalk.geometry", "all test points on one line", b.name("position[].ax_1"))


# --------------------------------------------------------------------------- list


BUILDERS = {
    "cross": build_cross,
    "plane": build_plane,
    "lsec": build_lsec,
    "frict": build_frict,
    "crosstalk": build_crosstalk,
}


def build_comp_list(values: Values, ctx: Ctx) -> CompList:
    """Every compensation of one list, each validated on its own."""
    comp = CompList(
        path=values.path,
        achs_nr=ctx.axis.log_nr,
        log_achs_name=str(values.get("kopf.log_achs_name", "")),
    )
    for attr, build in BUILDERS.items():
        setattr(comp, attr, build(values, ctx))
    return comp


def sections_present(values: Values) -> list[CompKind]:
    """The compensations a list has entries for."""
    return [k for k, p in PREFIX.items() if values.section(p)]
