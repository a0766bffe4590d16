"""Fast, data-oriented compensation kernel (docs/design.md §3, §5.1, §6, §11).

Same semantics as `ReferenceKernel` (the readable statement and the test oracle, in
tests/support/reference.py), computed for all axes at once with numpy.

Why it is shaped like this: with the manual's table sizes the arithmetic per cycle is
tiny; the cost is the *number* of numpy calls (~0.35 µs each plus Python overhead). So
the cycle is a fixed, short sequence of whole-array calls, and everything that can be
decided from the configuration is decided when the lists are loaded (construction and
reload):

* each compensation's module owns its preloaded arrays (one data object with a fixed
  layout, built by its `build` at load time, or None when no axis has that compensation:
  a compensation nobody has configured costs nothing) and its law, a function written
  once for a single cycle and for a pass of steady cycles (`batch.py`) alike:
  `temperature`, `plane`, `lsec`, `friction`, `crosstalk`, the 1-D tables
  (`tables.interpolate`) and the sin² filter (`sin2`) (docs/design.md §13.3); `step`
  orchestrates them in the manual's order;
* the inputs are copied once into one source vector `S` (`SourceVector`); every input
  that only needs this cycle's commands (crosstalk state, friction sign, 1-D queries,
  plane, mode 3) comes from S with ONE `take` into `G` (`Gather`), then one `sign`, one
  subtract and one divide (0 and 1 as neutral values);
* LSEC's complex query (row id 3j + 1 ± direction, position) is one gather from S and
  one add into the query's (real, imag) pairs;
* `step` is a flat sequence of numpy calls and law calls (a Python call costs about a
  third of a numpy call: the laws are few and each does several numpy calls);
* every 1-D table (cross, friction, crosstalk modes 1/2 and old model, the friction
  pre-reversal weight) is one row of a single `tables.MergedTable`: one `searchsorted`
  serves all of them; LSEC has its own (its lookup position needs this cycle's filtered
  cross and plane outputs);
* all target values go through one vector `V` (`TargetVector`), one multiplication by a
  factor vector (crosstalk acceleration ratio, friction sign·scale) and one scatter;
* crosstalk mode 3 is precomputed into convex regions with an affine value each (the
  Delaunay triangles, and outside the hull the Voronoi regions of the hull edges and
  vertices, where the nearest-hull-point value is affine too): one region test over all
  regions and one gather replace the per-vertex and per-edge evaluation;
* the sin² weights come from a table (`sin2.Sin2Filter`), all seven columns at once.

All arrays are preallocated; the only per-cycle allocations are the index arrays numpy
returns from `searchsorted`.

Column order (`COMP_ORDER`): BACKLASH, TEMP, CROSS, PLANE, LEAD, FRICT, CROSSTALK.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geo_server.kernel import crosstalk, friction, sin2, temperature
from geo_server.kernel.common import (
    ACC,
    ALL_KINDS,
    BC,
    COLUMN,
    CROSS,
    CROSSTALK,
    FRICT,
    LEAD,
    PLANE,
    POS,
    REV,
    TEMP,
    VEL,
    filter_cycles,
    hold_columns,
    initial_direction,
    initial_selection,
    reload_changes,
)
from geo_server.kernel.crosstalk import CrosstalkTables, Mode3Tables
from geo_server.kernel.friction import RING, FrictionState, FrictionTables
from geo_server.kernel.inputs import Gather, GatherWork, SourceVector, gather
from geo_server.kernel.lsec import ColumnViews, LsecTables
from geo_server.kernel.plane import MasterWrap, PlaneTables, PlaneWork, bilinear
from geo_server.kernel.sin2 import Sin2Filter
from geo_server.kernel.tables import Lookup, MergedTable, interpolate
from geo_server.kernel.triangulation import evaluate
from geo_server.model import AxisConfig, CompKind, MachineConfig
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM


def _i64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=np.int64).reshape(-1)


def _f64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=float).reshape(-1)


# ---------------------------------------------------------------------- load time


@dataclass(slots=True)
class Rows:
    """Slots of the axes on which each compensation is configured: a valid list whose
    masters are axes of this machine (docs/design.md §6.0)."""

    cross: list[int] = field(default_factory=list)
    plane: list[int] = field(default_factory=list)
    lsec: list[int] = field(default_factory=list)
    frict: list[int] = field(default_factory=list)  # mode 3 (000 §4.5 p.77)
    lin: list[int] = field(default_factory=list)  # crosstalk new model, modes 1, 2 (000 §4.6)
    tri: list[int] = field(default_factory=list)  # crosstalk new model, mode 3
    old: list[int] = field(default_factory=list)  # crosstalk old model (001 §4.5, 003 §3.5)

    @classmethod
    def of(cls, axes: list[AxisConfig], slot: dict[int, int]) -> Rows:
        r = cls()
        for i, ax in enumerate(axes):
            comp = ax.comp
            if comp is None:
                continue
            c = comp.cross
            if c is not None and c.valid and c.master_ax_nr in slot and len(c.setpoint):
                r.cross.append(i)
            pl = comp.plane
            if (
                pl is not None
                and pl.valid
                and pl.master1_ax_nr in slot
                and pl.master2_ax_nr in slot
                and pl.table.size
            ):
                r.plane.append(i)
            ls = comp.lsec
            if ls is not None and ls.valid and len(ls.setpoint):
                r.lsec.append(i)
            fr = comp.frict
            if fr is not None and fr.valid and fr.mode == 3 and len(fr.vin):
                r.frict.append(i)
            x = comp.crosstalk
            if x is None or not x.valid or x.master_dyn_ax_nr not in slot:
                continue
            if x.dialect == "old":
                if len(x.acc_table):
                    r.old.append(i)
            elif np.atleast_2d(np.asarray(x.corrections, dtype=float)).shape[0]:
                if x.mode == 3:
                    if x.master_pos1_ax_nr in slot and x.master_pos2_ax_nr in slot:
                        r.tri.append(i)
                elif x.mode != 2 or x.master_pos1_ax_nr in slot:
                    r.lin.append(i)
        return r


@dataclass(frozen=True, slots=True, eq=False)
class EffectiveTables:
    """Preconditions of the effective flags (docs/design.md §6.0, §6.8) and reversals.

    effective = selected ∧ homed[h[0]] ∧ homed[h[1]] per axis and column; `homed` holds
    this cycle's homing flags in slots 0 … n − 1, True in slot n (no homing needed) and
    False in slot n + 1 (not configured). Temperature needs the axis homed (000 §3.2
    p.17), LSEC too (000 §5.3 item 2), cross its master (000 p.29), plane both masters
    (000 §5.3 item 3); backlash (000 p.10), friction and crosstalk need no homing.
    `rev_mask` marks the columns whose reversal is a step event: backlash and bilateral
    LSEC (P-AXIS-00243).
    """

    h: np.ndarray  # [2, n, 7] indices into `homed`
    rev_mask: np.ndarray  # [n, 7]
    homed: np.ndarray  # [n + 2]
    homed_in: np.ndarray  # homed[:n]
    hb: np.ndarray  # [2, n, 7] scratch: homed[h]
    hb0: np.ndarray
    hb1: np.ndarray
    ne: np.ndarray  # [n, 7] this cycle's effective flags
    b7: np.ndarray  # [n, 7] scratch: reversal events

    @classmethod
    def build(cls, axes: list[AxisConfig], rows: Rows, slot: dict[int, int]) -> EffectiveTables:
        n = len(axes)
        h = np.full((2, n, 7), n, dtype=np.int64)
        h[0, :, TEMP] = np.arange(n)
        h[0, :, LEAD] = np.arange(n)
        for i, ax in enumerate(axes):
            p = ax.params
            if not (p.anwahl_losekomp != 0 and p.lose != 0):
                h[0, i, BC] = n + 1
        for c in (CROSS, PLANE, LEAD, FRICT, CROSSTALK):
            h[1, :, c] = n + 1  # until configured below
        rev_mask = np.zeros((n, 7), dtype=bool)
        rev_mask[:, BC] = True
        for i in rows.cross:
            h[0, i, CROSS] = slot[axes[i].comp.cross.master_ax_nr]
            h[1, i, CROSS] = n
        for i in rows.plane:
            h[0, i, PLANE] = slot[axes[i].comp.plane.master1_ax_nr]
            h[1, i, PLANE] = slot[axes[i].comp.plane.master2_ax_nr]
        for i in rows.lsec:
            h[1, i, LEAD] = n
            rev_mask[i, LEAD] = axes[i].comp.lsec.bilateral
        for i in rows.frict:
            h[1, i, FRICT] = n
        for i in rows.lin + rows.tri + rows.old:
            h[1, i, CROSSTALK] = n
        homed = np.ones(n + 2, dtype=bool)
        homed[n + 1] = False
        hb = np.zeros((2, n, 7), dtype=bool)
        return cls(
            h=h,
            rev_mask=rev_mask,
            homed=homed,
            homed_in=homed[:n],
            hb=hb,
            hb0=hb[0],
            hb1=hb[1],
            ne=np.zeros((n, 7), dtype=bool),
            b7=np.zeros((n, 7), dtype=bool),
        )


@dataclass(slots=True, eq=False)
class BacklashTemp:
    """Backlash (000 §2; docs/design.md §6.1) and temperature (000 §3.1 p.15; §6.2).

    Laid out so that both take one subtract:

        (d − init, s − position_0) = (d, s) − (init, position_0)

    then backlash = (d − init)·lose/2 and the temperature law `temperature.offset_into`.

    Backlash is 0 in the start-up direction and d·lose after a reversal; with d, init
    ∈ {±1} that is (d − init)·lose/2, exactly. s is the command position, wrapped into
    [0, period) on a modulo axis (docs/design.md §3.8). `par` has the rows [init dir,
    lose/2, coefficient·1e-6, (unused), coefficient, offset_0, position_0]; its last three
    rows are the live TEMPC parameters (000 §3.2.3 objects 0x43–0x45, in the order of
    `temperature.Bindings`), of which the machine keeps views: the block is allocated once
    and its static rows are refilled in place on reload (`load`).
    """

    par: np.ndarray  # [7, n]
    init_dir: np.ndarray
    half_lose: np.ndarray
    tc6: np.ndarray  # coefficient·1e-6, as the reference groups it
    tempc: np.ndarray  # [3, n] coefficient, offset_0, position_0
    coef: np.ndarray
    off0: np.ndarray
    pos0: np.ndarray
    sub: np.ndarray  # rows (init dir, position_0)
    t: np.ndarray  # [2, n] scratch
    t_dir: np.ndarray  # t[0]
    t_pos: np.ndarray  # t[1]
    out_bc: np.ndarray  # the backlash target column
    out_temp: np.ndarray
    any_modulo: bool = False
    period: np.ndarray | None = None  # modulo period (1 on other axes)
    not_modulo: np.ndarray | None = None

    @classmethod
    def create(
        cls, axes: list[AxisConfig], target: np.ndarray, tempc_attrs: tuple[str, ...]
    ) -> BacklashTemp:
        n = len(axes)
        par = np.zeros((7, n))
        tempc = par[4:7]
        for row, attr in enumerate(tempc_attrs):
            tempc[row] = [getattr(ax.params, attr) for ax in axes]
        t = np.zeros((2, n))
        bt = cls(
            par=par,
            init_dir=par[0],
            half_lose=par[1],
            tc6=par[2],
            tempc=tempc,
            coef=tempc[0],
            off0=tempc[1],
            pos0=tempc[2],
            sub=par[0:7:6],
            t=t,
            t_dir=t[0],
            t_pos=t[1],
            out_bc=target[:, BC],
            out_temp=target[:, TEMP],
        )
        bt.tempc_changed()
        return bt

    def load(self, axes: list[AxisConfig], modulo: np.ndarray, period: np.ndarray) -> None:
        """The static rows from the axis parameters (construction and reload)."""
        self.init_dir[:] = _f64([initial_direction(ax.params.anwahl_losekomp) for ax in axes])
        self.half_lose[:] = _f64([ax.params.lose for ax in axes]) / 2.0
        self.any_modulo = bool(modulo.any())
        self.period, self.not_modulo = period, ~modulo

    def tempc_changed(self) -> None:
        temperature.slope_into(self.coef, self.tc6)


@dataclass(frozen=True, slots=True, eq=False)
class TargetVector:
    """V = [plane | xt mode 3 | xt modes 1/2 | friction | cross | xt old | friction
    pre-reversal weight]: every target computed from tables, multiplied by `fac`
    (crosstalk ratio, friction sign·scale; 1 elsewhere) and scattered into the target
    array with one `put`. The last part is a weight, not a target. The merged 1-D lookup
    fills V from "xt modes 1/2" on."""

    V: np.ndarray
    fac: np.ndarray
    any_fac: bool
    flat: np.ndarray  # index into target.reshape(-1) of every target in V
    tgt: np.ndarray  # the targets: V without the weights
    # parts of V and fac handed to the compensations' builders
    plane: np.ndarray
    tri: np.ndarray
    l1: np.ndarray
    wpre: np.ndarray
    fac_xt: np.ndarray
    fac_fr: np.ndarray

    @classmethod
    def build(cls, rows: Rows) -> TargetVector:
        P, T, X, F = len(rows.plane), len(rows.tri), len(rows.lin), len(rows.frict)
        o_tri, o_lin = P, P + T
        o_fr = o_lin + X
        o_cross = o_fr + F
        o_old = o_cross + len(rows.cross)
        o_wpre = o_old + len(rows.old)
        V = np.zeros(o_wpre + F)
        fac = np.ones(o_wpre + F)
        flat = _i64(
            [i * 7 + PLANE for i in rows.plane]
            + [i * 7 + CROSSTALK for i in rows.tri + rows.lin]
            + [i * 7 + FRICT for i in rows.frict]
            + [i * 7 + CROSS for i in rows.cross]
            + [i * 7 + CROSSTALK for i in rows.old]
        )
        return cls(
            V=V,
            fac=fac,
            any_fac=bool(T + X + F),
            flat=flat,
            tgt=V[:o_wpre],
            plane=V[:P],
            tri=V[o_tri:o_lin],
            l1=V[o_lin:],
            wpre=V[o_wpre:],
            fac_xt=fac[o_tri:o_fr],
            fac_fr=fac[o_fr:o_cross],
        )


@dataclass(frozen=True, slots=True, eq=False)
class Lookup1DTables:
    """Every 1-D table that only needs this cycle's inputs, as the rows of one
    `MergedTable` served by one `searchsorted` (linear, edges held: docs/design.md §6.0).

    Rows: crosstalk modes 1/2 (000 §4.6; four variant rows per axis, one per correction
    column, chosen per cycle by the crosstalk state), the friction base sign(v)·table(|v|)
    as the table mirrored to negative v (000 §4.5), cross (000 §4.2; a modulo master
    wraps, 000 p.31), the crosstalk old model over the signed acceleration in mm/s²
    (001 §4.5), and the friction pre-reversal weight as a table over the cycles r left
    before the reversal: r/(lookahead + 1) for 0 ≤ r ≤ lookahead, else 1 (000 §4.5).
    """

    lookup: Lookup
    raw: np.ndarray  # query positions: a view of G
    out: np.ndarray  # the values: a view of the target vector
    lin_rowid: np.ndarray  # row ids of the crosstalk queries
    lin_now: np.ndarray | None  # this cycle's variant row ids (CrosstalkTables.now)
    has_lin: bool

    @classmethod
    def build(
        cls,
        axes: list[AxisConfig],
        rows: Rows,
        slot: dict[int, int],
        src: SourceVector,
        master_wrap: MasterWrap,
        g: Gather,
        part: slice,
        out: np.ndarray,
        xt: CrosstalkTables | None,
    ) -> Lookup1DTables | None:
        tables: list[tuple[np.ndarray, np.ndarray]] = []
        row_ids, qsrc, div, wrap, per = [], [], [], [], []

        def row(table: tuple, s: int, d: float = 1.0, w: tuple[bool, float] = (False, 1.0)) -> None:
            row_ids.append(len(tables))
            tables.append(table)
            qsrc.append(s)
            div.append(d)
            wrap.append(w[0])
            per.append(w[1])

        lin_base = []
        for i in rows.lin:  # four variant rows each: the correction columns
            x = axes[i].comp.crosstalk
            corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
            if x.mode == 1:
                keys, vals = np.zeros(1), corr[:1]
                s = src.zero
            else:
                ax1 = np.asarray(x.ax_1, dtype=float)[: corr.shape[0]]
                if len(ax1) == 0:
                    ax1 = np.zeros(1)
                order = np.argsort(ax1, kind="stable")
                keys, vals = ax1[order], corr[order]
                s = src.index(POS, slot[x.master_pos1_ax_nr])
            lin_base.append(len(tables))
            row((keys, vals[:, 0]), s)
            tables.extend((keys, vals[:, c]) for c in range(1, 4))
        for i in rows.frict:  # sign(v)·table(|v|) = mirrored table(v)
            fr = axes[i].comp.frict
            x, y = np.asarray(fr.vin, dtype=float), np.asarray(fr.out, dtype=float)
            keep = x[::-1] > 0 if x[0] == 0 else np.ones(len(x), dtype=bool)
            mirrored = (np.concatenate([-x[::-1][keep], x]), np.concatenate([y[::-1][keep], y]))
            row(mirrored, src.index(VEL, i), UNITS_PER_UM)
        for i in rows.cross:
            c = axes[i].comp.cross
            m = slot[c.master_ax_nr]
            table = (np.asarray(c.setpoint, dtype=float), np.asarray(c.correction, dtype=float))
            row(table, src.index(POS, m), w=master_wrap(m))
        for i in rows.old:
            x = axes[i].comp.crosstalk
            a = np.asarray(x.acc_table, dtype=float)
            order = np.argsort(a, kind="stable")
            table = (a[order], np.asarray(x.corr_table, dtype=float)[order])
            row(table, src.index(ACC, slot[x.master_dyn_ax_nr]), UNITS_PER_MM)
        for i in rows.frict:
            look = int(axes[i].comp.frict.reversal_lookahead)
            if look > 0:
                weight = (
                    np.array([-1.0, 0.0, look, look + 1.0]),
                    np.array([1.0, 0.0, look / (look + 1), 1.0]),
                )
            else:
                weight = (np.zeros(1), np.ones(1))
            row(weight, src.index(REV, i))
        if not row_ids:
            return None
        g.src[part], g.div[part], g.wrap[part], g.per[part] = qsrc, div, wrap, per
        lookup = Lookup(MergedTable(tables), _f64(row_ids))
        X = len(rows.lin)
        if X:
            # variant row id = base + correction column, per sign code
            cols = xt.col.reshape(-1, 9)[-X:]
            rowid = np.array(lin_base, dtype=float)[:, None] + cols
            xt.tab[-X * 9 :, 2] = rowid.reshape(-1)
        return cls(
            lookup=lookup,
            raw=g.G[part],
            out=out,
            lin_rowid=lookup.rowid[:X],
            lin_now=xt.now[-X:, 2] if X else None,
            has_lin=bool(X),
        )


# ---------------------------------------------------------------------- the kernel


class Kernel:
    """Vectorised compensation kernel for a whole machine (interface: see package doc)."""

    def __init__(self, cfg: MachineConfig, tempc: temperature.Bindings | None = None) -> None:
        #: the TEMPC parameter objects of the machine's dictionary (`write_tempc`)
        self.tempc = tempc or temperature.default_bindings()
        self.axis_numbers = np.array(sorted(cfg.axes), dtype=np.int64)
        n = len(self.axis_numbers)
        self.n = n
        self._slot = {int(a): i for i, a in enumerate(self.axis_numbers)}
        axes = [cfg.axes[int(a)] for a in self.axis_numbers]
        self.selected = np.array([initial_selection(ax) for ax in axes], dtype=bool).reshape(n, 7)
        # outputs (updated in place: the machine keeps references to them)
        self.target = np.zeros((n, 7))
        self.actual = np.zeros((n, 7))
        self.delta = np.zeros((n, 7))
        self.effective = np.zeros((n, 7), dtype=bool)
        self.friction_current = self.actual[:, FRICT]  # the friction column, as a vector
        self.total_offset = np.zeros(n)
        # state kept across reloads
        self._src = SourceVector.create(
            n, [initial_direction(ax.params.anwahl_losekomp) for ax in axes]
        )
        self._bt = BacklashTemp.create(axes, self.target, self.tempc.attrs)
        self._fr_state = FrictionState.create(self.target, self.actual, self.effective)
        self._filter: Sin2Filter | None = None
        self._first = True
        self._pending = np.zeros((n, 7), dtype=bool)  # step events from writes and reload
        self._pending_any = False
        #: columns whose output is held at its last value (`hold`, COMP … NO_MOVE)
        self.held = np.zeros((n, 7), dtype=bool)
        self._any_held = False
        #: what besides the selection makes each column effective, as of the last step
        #: (homing, valid tables): the NC's 70435 check combines it with the selection
        self.preconditions = np.zeros((n, 7), dtype=bool)
        #: the drives' enables (`SIM::drive_enable`): cross and plane compensation of an
        #: axis are effective only with its drive enabled (000 §5.3 p.97 item 4)
        self.drive_enabled = np.ones(n, dtype=bool)
        self._drives_off = False
        #: compensations whose configuration is valid, per axis (`Rows`; TEMP needs
        #: none): with the axis list's selection, what `V.A.*_COMP_INIT` reports
        self.configured = np.zeros((n, 7), dtype=bool)
        # scratch
        self._prev = np.zeros((n, 7))
        self._event = np.zeros((n, 7), dtype=bool)
        self._t7 = np.zeros((n, 7))
        self._s = np.zeros(n)  # sign of the command velocity
        self._t1 = np.zeros(n)
        self._rev = np.zeros(n, dtype=bool)
        self._rev_col = self._rev[:, None]
        self._tflat, self._aflat = self.target.reshape(-1), self.actual.reshape(-1)
        # total offset: Σ columns but friction (docs/design.md §3.7)
        self._not_fr = np.ones(7)
        self._not_fr[FRICT] = 0.0
        #: counts `_setup` calls: whoever keeps buffers shaped by the tables (the batch,
        #: `geo_server.kernel.batch`) rebuilds them when it changes
        self.generation = 0
        self._setup(cfg)

    # ------------------------------------------------------------------ configuration

    def _setup(self, cfg: MachineConfig) -> None:
        """Build every compensation's tables from `cfg` (construction and reload)."""
        if sorted(cfg.axes) != [int(a) for a in self.axis_numbers]:
            raise ValueError("the set of axes cannot change on reload")
        self.cfg = cfg
        self.generation += 1
        n, slot, src = self.n, self._slot, self._src
        axes = [cfg.axes[int(a)] for a in self.axis_numbers]
        p = [ax.params for ax in axes]
        ncyc = np.array([filter_cycles(ax) for ax in axes], dtype=np.int64).reshape(n, 7)
        ncyc[:, FRICT] = 0  # friction is not sin²-filtered: its output is the delay line
        if self._filter is None:
            self._filter = Sin2Filter(ncyc)
        else:
            self._filter.set_n(ncyc)
        modulo = np.array([x.modulo for x in p], dtype=bool)
        period = _f64([x.modulo_period if x.modulo else 1.0 for x in p])

        def master_wrap(m: int) -> tuple[bool, float]:
            return bool(modulo[m]), float(period[m])

        rows = Rows.of(axes, slot)
        self._configured(axes, rows)
        self._bt.load(axes, modulo, period)
        self._eff = EffectiveTables.build(axes, rows, slot)
        self._vec = vec = TargetVector.build(rows)
        # the gather's parts: [xt (vel, acc) | friction vel | 1-D | plane | mode 3]
        X, T, F, P = len(rows.lin), len(rows.tri), len(rows.frict), len(rows.plane)
        nxt = T + X  # crosstalk new-model rows, mode 3 first
        L1 = X + 2 * F + len(rows.cross) + len(rows.old)  # rows of the merged 1-D lookup
        ns = 2 * nxt + F
        o_pl = ns + L1
        o_tri = o_pl + 2 * P
        self._gather = g = Gather.layout(ns, L1 + 2 * P, L1 + 2 * P + 3 * T)
        self._gather_work = GatherWork.of(g, src.S)
        self._xt = xt = CrosstalkTables.build(
            axes, rows.tri + rows.lin, slot, src, g, slice(0, 2 * nxt), vec.fac_xt
        )
        self._l1 = Lookup1DTables.build(
            axes, rows, slot, src, master_wrap, g, slice(ns, o_pl), vec.l1, xt
        )
        self._plane = pl = PlaneTables.build(
            axes, rows.plane, slot, src, master_wrap, g, slice(o_pl, o_tri)
        )
        self._plane_work = None if pl is None else PlaneWork.create(pl.P, pl.u, vec.plane)
        self._tri = tri = Mode3Tables.build(
            axes, rows.tri, slot, src, g, slice(o_tri, o_tri + 3 * T), vec.tri, xt
        )
        # the single cycle's work of the crosstalk laws: the tables' own buffers
        self._xt_work = None
        if xt is not None:
            self._xt_work = crosstalk.StateWork(
                sign_v=xt.sign[0],
                sign_a=xt.sign[1],
                acc=xt.acc,
                code=xt.code,
                idx=xt.idx,
                now=xt.now,
                ratio=xt.ratio,
                fac=xt.fac,
            )
        self._tri_work = None
        if tri is not None:
            self._tri_work = crosstalk.Mode3Work(
                xy1c=tri.xy1c,
                lamm=tri.lamm,
                lam0=tri.lam0,
                lam1=tri.lam1,
                lam2=tri.lam2,
                min=tri.min,
                inside=tri.inside,
                sel=tri.sel,
                off_now=tri.off_now,
                coef=tri.coef,
                coef1=tri.coef1,
                out11=tri.out11,
            )
        self._frict = FrictionTables.build(
            axes, rows.frict, src, g, slice(2 * nxt, ns), vec.fac_fr, vec.wpre
        )
        g.finish()
        f = self._filter
        lead = ColumnViews(
            target=self.target[:, LEAD],
            actual=self.actual[:, LEAD],
            effective=self.effective[:, LEAD],
            prev=self._prev[:, LEAD],
            event=self._event[:, LEAD],
            tmp=self._t7[:, LEAD],
            jump=f.jump[:, LEAD],
            weight=f.w[:, LEAD],
        )
        self._lsec = LsecTables.build(axes, rows.lsec, src, modulo, period, lead)

    def _configured(self, axes: list[AxisConfig], rows: Rows) -> None:
        c = self.configured
        c.fill(False)
        c[:, TEMP] = True
        for i, ax in enumerate(axes):
            c[i, BC] = ax.params.anwahl_losekomp != 0 and ax.params.lose != 0
        for col, slots in (
            (CROSS, rows.cross),
            (PLANE, rows.plane),
            (LEAD, rows.lsec),
            (FRICT, rows.frict),
            (CROSSTALK, rows.lin + rows.tri + rows.old),
        ):
            c[slots, col] = True

    # ------------------------------------------------------------------ interface

    def set_drive_enabled(self, slot: int, on: bool) -> None:
        """`SIM::drive_enable`: a precondition of cross and plane compensation (000 §5.3
        p.97 item 4), taken into the effective flags at the next step (a change is a
        step event, like homing)."""
        self.drive_enabled[slot] = bool(on)
        self._drives_off = not bool(self.drive_enabled.all())

    def slot_of(self, axis_number: int) -> int:
        return self._slot[int(axis_number)]

    def ramping(self, slot: int) -> bool:
        """True while a sin² ramp of the axis has cycles left or an event is pending."""
        f = self._filter
        return bool(np.any(f.kidx[slot] != f.end[slot]) or self._pending[slot].any())

    @property
    def previous(self) -> np.ndarray:
        """The actual values of the cycle before the last step ([n, 7])."""
        return self._prev

    def at_rest(self) -> bool:
        """True when a step with unchanged inputs would change nothing but the delay
        line's write position: no sin² ramp under way, no step event pending, and the
        friction delay line holds only zeros (so every position in it is alike)."""
        f = self._filter
        return (
            not self._pending_any
            and np.array_equal(f.kidx, f.end)
            and not np.count_nonzero(self._fr_state.ring_flat)
        )

    def skip(self, n: int) -> None:
        """`n` steps of a kernel `at_rest` with unchanged inputs (docs/design.md §13)."""
        fs = self._fr_state
        fs.ring_pos = (fs.ring_pos + n) % RING

    def set_selected(self, slot: int, kind: CompKind, on: bool) -> None:
        """COMP ON/OFF or a `TEMPC::activated` write (000 §5.1 p.94, §3.2 p.15)."""
        self.selected[slot, COLUMN[kind]] = bool(on)

    def hold(self, slot: int, kinds: CompKind) -> None:
        """`COMP … NO_MOVE` (000 §5.1 p.94): the selection has changed, but the offset it
        causes is only executed at the axis' next motion, so the output of these columns
        stays at its present value until `release`."""
        for c in hold_columns(kinds):
            self.held[slot, c] = True
        self._any_held = bool(self.held.any())

    def release(self, slot: int, kinds: CompKind = ALL_KINDS) -> None:
        """The axis' next motion (or a switch without NO_MOVE): held columns ramp from
        their held output to the present target with their sin² length (a step event)."""
        for c in hold_columns(kinds):
            if self.held[slot, c]:
                self.held[slot, c] = False
                self._pending[slot, c] = True
                self._pending_any = True
        self._any_held = bool(self.held.any())

    @property
    def tempc_params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Live coefficient, offset_0, position_0 (views, 000 §3.2.3 objects 0x43–0x45)."""
        t = self._bt.tempc
        return t[0], t[1], t[2]

    def write_tempc(self, slot: int, field: str, value: float) -> None:
        """TEMPC parameter write: a step event with temp_comp_n_cycles (docs/design.md
        §3.5)."""
        self._bt.tempc[self.tempc.fields.index(field), slot] = float(value)
        self._bt.tempc_changed()
        self._pending[slot, TEMP] = True
        self._pending_any = True

    def reload(self, cfg: MachineConfig) -> None:
        """Swap tables at this cycle boundary: a step event on every column
        (docs/design.md §4.4).

        Selection and live TEMPC values follow the new lists only where the lists
        changed them (docs/design.md §12 "reload").
        """
        old = self.cfg
        self._setup(cfg)
        tempc = self._bt.tempc
        for i, a in enumerate(self.axis_numbers):
            selection, values = reload_changes(old.axes[int(a)], cfg.axes[int(a)], self.tempc.attrs)
            for c, on in selection:
                self.selected[i, c] = on
            for row, value in values:
                tempc[row, i] = value
        self._bt.tempc_changed()
        self._pending[:] = True
        self._pending_any = True

    # ------------------------------------------------------------------ the cycle

    def step(
        self,
        cmd_pos: np.ndarray,
        cmd_vel: np.ndarray,
        cmd_acc: np.ndarray,
        homed: np.ndarray,
        reversal_in: np.ndarray,
    ) -> None:
        """One GEO cycle for every axis (docs/design.md §5.1 step 3): the compensations'
        laws (their modules, docs/design.md §13.3) in the manual's order, with the
        bookkeeping between them as numpy calls on local names (attribute lookups cost
        as much as a small numpy call here).
        """
        mul, subtract = np.multiply, np.subtract
        copyto = np.copyto
        tgt, act, eff, ev = self.target, self.actual, self.effective, self._event
        prev, t1, tflat = self._prev, self._t1, self._tflat
        src, fs = self._src, self._fr_state
        S, pos = src.S, src.pos
        copyto(prev, act)
        if self._first:
            copyto(pos, cmd_pos)
            self._first = False
        dpos = fs.dpos
        subtract(cmd_pos, pos, dpos)  # pos still holds the previous cycle's
        np.concatenate((cmd_pos, cmd_vel, cmd_acc, reversal_in), out=src.inputs)
        if reversal_in.dtype.kind != "i":
            np.trunc(src.rev, out=src.rev)  # the reference's int(): −0.5 → 0

        # direction: sign of the command velocity, the last one held at standstill
        # (docs/design.md §3.6). d is always ±1, so "s ≠ 0 and s ≠ d" is s·d < 0, and the
        # update is a flip.
        s, rev, d = self._s, self._rev, src.dir
        np.sign(src.vel, s)
        mul(s, d, t1)
        np.less(t1, 0.0, rev)
        np.negative(d, out=d, where=rev)

        self._effective_now(homed)

        # backlash (d − init)·lose/2 (000 §2) and temperature (000 §3.1 p.15, the law in
        # `temperature`): see `BacklashTemp`
        bt = self._bt
        btt = bt.t
        subtract(src.dp, bt.sub, btt)  # (d − init, s − position_0)
        if bt.any_modulo:
            np.mod(pos, bt.period, t1)
            copyto(t1, pos, where=bt.not_modulo)
            subtract(t1, bt.pos0, bt.t_pos)
        mul(bt.t_dir, bt.half_lose, bt.out_bc)
        temperature.offset_into(bt.off0, bt.tc6, bt.t_pos, bt.out_temp)

        # the inputs of cross, plane, crosstalk and friction: one gather from S
        g = self._gather
        if g.any:
            gather(g, self._gather_work)
        xt = self._xt
        if xt is not None:
            # crosstalk (000 §4.6 p.84): `crosstalk.state` of every new-model row
            crosstalk.state(xt.rowoff, xt.tab, self._xt_work)
        l1 = self._l1
        if l1 is not None:
            # cross (000 §4.2), friction base (§4.5), crosstalk modes 1/2 and old model
            # (§4.6, 001 §4.5) and the friction pre-reversal weight: one merged lookup
            lk = l1.lookup
            if l1.has_lin:  # this cycle's correction column of the crosstalk rows
                copyto(l1.lin_rowid, l1.lin_now)
            copyto(lk.q, l1.raw)
            interpolate(lk, l1.out)
        pl, pw = self._plane, self._plane_work
        if pl is not None and pw is not None:  # plane (000 §4.3): `plane.bilinear`
            bilinear(pl, pw)
        tri = self._tri
        if tri is not None:  # crosstalk mode 3 (000 §4.6 p.84)
            self._mode3(tri, xt)
        fr = self._frict
        if fr.any:  # friction factor: sign(v)·scaling_factor/1000 (000 §4.5)
            mul(fr.sign, fr.scale, fr.fac)
        vec = self._vec
        V = vec.V
        if vec.any_fac:
            mul(V, vec.fac, V)
        tflat.put(vec.flat, vec.tgt)
        mul(tgt, eff, tgt)

        # sin² filter of every column (LSEC again below, once its target is known;
        # docs/design.md §3.4): k ← offset(N) on an event, then k ← min(k + 1, offset(N)
        # + N) (one successor table), w = cos²(πk/(2N)); J ← target − out where event;
        # out = target − J·w
        f = self._filter
        kidx, w, jump, t7 = f.kidx, f.w, f.jump, self._t7
        copyto(kidx, f.off, where=ev)
        f.succ.take(kidx, out=kidx)
        f.table.take(kidx, out=w)
        subtract(tgt, prev, t7)
        copyto(jump, t7, where=ev)
        sin2.output(tgt, jump, w, t7, act)
        if self._any_held:  # COMP … NO_MOVE: output held (LSEC reads the held values)
            copyto(act, prev, where=self.held)

        ls = self._lsec
        if ls is not None:  # LSEC (000 §4.4)
            self._lsec_cycle(ls, S, tflat)
        self._friction_cycle(fs, fr, rev, dpos)  # friction (000 §4.5)

        subtract(act, prev, self.delta)
        np.matmul(act, self._not_fr, out=self.total_offset)  # Σ columns but friction

    # The parts of `step` below are methods of their own only to keep `step` readable
    # (ruff C901): a call costs less than one numpy call, and each takes what `step`
    # already holds in local names as arguments.

    def _effective_now(self, homed: np.ndarray) -> None:
        """Effective = selected ∧ preconditions (docs/design.md §6.8; cross and plane
        also need the drive enabled, 000 §5.3 p.97 item 4); a change is a step event
        (§3.5), as are pending TEMPC writes and reloads, and a reversal for backlash and
        bilateral LSEC (P-AXIS-00243)."""
        copyto = np.copyto
        eff, ev = self.effective, self._event
        et = self._eff
        copyto(et.homed_in, homed)
        ne = et.ne
        et.homed.take(et.h, out=et.hb)
        np.logical_and(et.hb0, et.hb1, ne)
        if self._drives_off:  # cross and plane need the drive enabled (000 p.97 item 4)
            for col in (CROSS, PLANE):
                np.logical_and(ne[:, col], self.drive_enabled, out=ne[:, col])
        copyto(self.preconditions, ne)
        np.logical_and(ne, self.selected, ne)
        np.not_equal(ne, eff, ev)
        copyto(eff, ne)
        if self._pending_any:  # TEMPC writes, reload
            np.logical_or(ev, self._pending, ev)
            self._pending.fill(False)
            self._pending_any = False
        # reversal: step event of backlash and bilateral LSEC (P-AXIS-00243)
        b7 = et.b7
        np.logical_and(et.rev_mask, self._rev_col, b7)
        np.logical_and(b7, eff, b7)
        np.logical_or(ev, b7, ev)

    def _mode3(self, tri: Mode3Tables, xt: CrosstalkTables | None) -> None:
        """Crosstalk mode 3 (000 §4.6 p.84): `crosstalk.mode3` (× ratio via the factor
        vector); a row with an unusual hull evaluates its triangulation."""
        crosstalk.mode3(tri.H, tri.val, self._tri_work)
        if tri.slow:
            vt, xy1 = tri.out, tri.xy1
            for j, t, cols in tri.slow:
                col = int(tri.colv[xt.idx[j]])
                vt[j] = evaluate(t, cols[col], xy1[j, 0], xy1[j, 1])

    def _lsec_cycle(self, ls: LsecTables, S: np.ndarray, tflat: np.ndarray) -> None:
        """LSEC (000 §4.4; the tables: `LsecTables`): looked up at the command position
        plus this cycle's filtered cross and plane outputs, so after the sin² filter of
        the other columns, then through its own filter column."""
        mul, add, subtract = np.multiply, np.add, np.subtract
        copyto = np.copyto  # (four names in one assignment would build a tuple)
        lk = ls.lookup
        t = ls.t
        self._aflat.take(ls.cp, out=ls.cpv)
        add(ls.cp0, ls.cp1, t)
        if not ls.all_wc:  # set_pos_without_comp: command position only
            mul(t, ls.wc, t)
        S.take(ls.src, out=ls.g)
        add(ls.g, ls.add, ls.qf)  # (row id, position)
        if ls.any_wrap:  # modulo table: wrap into [x0, x0 + period)
            lq, lt = lk.q, ls.d
            subtract(lq, ls.x0, lt)
            np.mod(lt, ls.per, lt)
            add(lt, ls.x0, lt)
            copyto(lq, lt, where=ls.wrap)
        c = ls.col
        tl = c.target
        if ls.all:
            interpolate(lk, tl)
        else:
            interpolate(lk, ls.val)
            tflat.put(ls.flat, ls.val)
        mul(tl, c.effective, tl)
        tld = c.tmp
        subtract(tl, c.prev, tld)
        copyto(c.jump, tld, where=c.event)
        sin2.output(tl, c.jump, c.weight, tld, c.actual)
        if self._any_held:
            copyto(c.actual, c.prev, where=self.held[:, LEAD])

    def _friction_cycle(
        self, fs: FrictionState, fr: FrictionTables, rev: np.ndarray, dpos: np.ndarray
    ) -> None:
        """Friction (000 §4.5): reversal weights and the delay line, for every axis."""
        add, copyto = np.add, np.copyto
        path = fs.path
        copyto(path, 0.0, where=rev)  # path since the last reversal
        np.abs(dpos, dpos)
        add(path, dpos, path)
        wpos = fs.ring_pos
        fs.ring_pos = wpos + 1 if wpos < RING - 1 else 0
        # this cycle's value into the delay line: sign(v)·scale·table(|v|) (0 when not
        # effective) × the pre-reversal and the post-reversal weight
        cur = fs.ring_rows[wpos]
        wpre = None
        if fr.any:  # the pre-reversal weights: from the merged lookup
            wpre = fr.wpre
            wpre.put(fr.slots, fr.wpre_in)
        pd = fr.pd if fr.any_pd else None
        friction.weigh(fs.target, wpre, path, pd, fr.has_pd, fr.wpost, cur)
        # delay line: read `delay_cycles` back; output only while effective
        rv = fr.rv
        fs.ring_flat.take(fr.ridx_rows[wpos], out=rv)
        np.multiply(rv, fs.effective, fs.actual)  # = friction_current
