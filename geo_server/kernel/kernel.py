"""Fast, data-oriented compensation kernel (docs/design.md §3, §5.1, §6, §11).

Same semantics as `geo_server.kernel.reference.ReferenceKernel` (the readable statement
and the test oracle), computed for all axes at once with numpy.

Why it is shaped like this: with the manual's table sizes the arithmetic per cycle is
tiny; the cost is the *number* of numpy calls (~0.35 µs each plus Python overhead). So
the cycle is a fixed, short sequence of whole-array calls, and everything that can be
decided from the configuration is decided when the lists are loaded (construction and
reload):

* each compensation's preloaded arrays and scratch buffers are one data object with a
  fixed layout (`PlaneTables`, `LsecTables`, ...), built by its `build` at load time,
  or None when no axis has that compensation: a compensation nobody has configured
  costs nothing; `step` binds the fields it needs to local names;
* the inputs are copied once into one source vector `S` (`SourceVector`); every input
  that only needs this cycle's commands (crosstalk state, friction sign, 1-D queries,
  plane, mode 3) comes from S with ONE `take` into `G` (`Gather`), then one `sign`, one
  subtract and one divide (0 and 1 as neutral values);
* LSEC's complex query (row id 3j + 1 ± direction, position) is one gather from S and
  one add into the query's (real, imag) pairs;
* `step` is one flat sequence of numpy calls: no helper calls in the hot path;
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

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from geo_server.kernel.common import (
    ALL_KINDS,
    BC,
    COLUMN,
    CROSS,
    CROSSTALK,
    FRICT,
    LEAD,
    PLANE,
    TEMP,
    TEMPC_ATTRS,
    TEMPC_FIELDS,
    filter_cycles,
    hold_columns,
    initial_direction,
    initial_selection,
    reload_changes,
)
from geo_server.kernel.sin2 import Sin2Filter
from geo_server.kernel.tables import Lookup, MergedTable
from geo_server.kernel.triangulation import INSIDE_EPS, Triangulation, evaluate, triangulate
from geo_server.model import AxisConfig, CompKind, MachineConfig
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM

RING = 249  # friction delay line length: delay_cycles < 249 (000 p.79)
#: Outside the hull, neighbouring regions overlap by this distance [units] so that
#: rounding can never leave a point in no region; the value there is continuous, so the
#: overlap changes results by at most REGION_TOL·|gradient| (≪ 1e-9 for real tables).
REGION_TOL = 1e-6
#: Blocks of the source vector S (`SourceVector`): S[block·n + slot].
POS, VEL, ACC, REV = range(4)

#: (is modulo, period) of the axis in a slot: a table over a modulo master wraps with it.
MasterWrap = Callable[[int], tuple[bool, float]]


def _i64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=np.int64).reshape(-1)


def _f64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=float).reshape(-1)


def _xt_lut(veldep: bool, inv_acc: float, inv_dec: float) -> tuple[list[int], list[float]]:
    """Correction column and 1/|a_ref| for the 9 sign combinations of (v, a).

    Index 3·sign(v) + sign(a) + 4. Accelerating ⇔ a·v ≥ 0 (decelerate columns 2, 3);
    negative direction ⇔ v < 0, or v = 0 and a < 0 (columns 1, 3 when velocity
    dependent) — the reference's rules (docs/design.md §6.7), tabulated so that the
    kernel needs no per-cycle comparisons.
    """
    cols, invs = [], []
    for sv in (-1, 0, 1):
        for sa in (-1, 0, 1):
            accelerating = sv * sa >= 0
            neg = sv < 0 or (sv == 0 and sa < 0)
            cols.append((0 if accelerating else 2) + (1 if neg and veldep else 0))
            invs.append(inv_acc if accelerating else inv_dec)
    return cols, invs


def _hull_cycle(tri: Triangulation) -> list[int] | None:
    """Hull vertices in CCW order when the hull edges form one convex cycle that the
    triangles cover; None otherwise (then the row uses the scalar `evaluate`)."""
    nxt = {}
    for a, b in tri.edges:
        if a in nxt:
            return None
        nxt[a] = b
    start = tri.edges[0][0]
    cyc, v = [start], nxt.get(start)
    while v is not None and v != start and len(cyc) <= len(tri.edges):
        cyc.append(v)
        v = nxt.get(v)
    if v != start or len(cyc) != len(tri.edges):
        return None
    pts = tri.points
    area = 0.0
    scale = 0.0
    for i, a in enumerate(cyc):
        b, c = cyc[(i + 1) % len(cyc)], cyc[(i + 2) % len(cyc)]
        (ax, ay), (bx, by), (cx, cy) = pts[a], pts[b], pts[c]
        cross = (bx - ax) * (cy - by) - (by - ay) * (cx - bx)
        scale = max(scale, abs(bx - ax) + abs(by - ay))
        if cross < -1e-9 * scale * scale:  # a reflex hull vertex
            return None
        area += ax * by - bx * ay
    tri_area = 0.0
    for t in tri.triangles:
        (ax, ay), (bx, by), (cx, cy) = (pts[v] for v in t)
        tri_area += (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
    if abs(area - tri_area) > 1e-9 * max(abs(area), scale * scale):
        return None
    return cyc


def _regions(tri: Triangulation, vals: np.ndarray) -> list[tuple] | None:
    """Convex regions covering the plane with the mode-3 value affine in each.

    Each region is (3 half-planes (a, b, c), 4 columns of (α, β, γ)); a point is in a
    region when min(a·x + b·y + c) ≥ −INSIDE_EPS, and the value there is α·x + β·y + γ.
    Triangles come first with the reference's own barycentric coefficients (so inside
    the hull the region choice equals the reference's triangle choice); the exterior
    regions' half-planes are unit normals scaled so that −INSIDE_EPS means −REGION_TOL.
    """
    pad = (0.0, 0.0, 1.0)  # always satisfied
    kappa = INSIDE_EPS / REGION_TOL
    pts = tri.points
    out = []

    def const(v: int) -> list[tuple[float, float, float]]:
        return [(0.0, 0.0, float(vals[v, c])) for c in range(4)]

    def edge_value(a: int, b: int) -> list[tuple[float, float, float]]:
        # va + s·(vb − va), s = ((x − ax)·dx + (y − ay)·dy)·inv: affine in (x, y)
        (ax, ay), (bx, by) = pts[a], pts[b]
        dx, dy = bx - ax, by - ay
        inv = 1.0 / (dx * dx + dy * dy)
        res = []
        for c in range(4):
            dv = float(vals[b, c] - vals[a, c])
            res.append(
                (dv * dx * inv, dv * dy * inv, float(vals[a, c]) - dv * (ax * dx + ay * dy) * inv)
            )
        return res

    def half(nx: float, ny: float, px: float, py: float) -> tuple[float, float, float]:
        # κ·n·(p − p0) ≥ 0 with n a unit vector
        return (kappa * nx, kappa * ny, -kappa * (nx * px + ny * py))

    def unit(a: int, b: int) -> tuple[float, float]:
        dx, dy = pts[b][0] - pts[a][0], pts[b][1] - pts[a][1]
        ln = math.hypot(dx, dy)
        return dx / ln, dy / ln

    for t, coef in zip(tri.triangles, tri.bary, strict=True):
        value = []
        for c in range(4):
            v = [float(vals[i, c]) for i in t]
            value.append(tuple(sum(coef[k][j] * v[k] for k in range(3)) for j in range(3)))
        out.append((tuple(coef), value))
    if tri.triangles:
        cyc = _hull_cycle(tri)
        if cyc is None:
            return None
        m = len(cyc)
        for i in range(m):
            a, b = cyc[i], cyc[(i + 1) % m]
            ux, uy = unit(a, b)
            slab = (
                half(ux, uy, *pts[a]),  # beyond a along the edge
                half(-ux, -uy, *pts[b]),  # before b
                half(uy, -ux, *pts[a]),  # outside (right of the CCW edge)
            )
            out.append((slab, edge_value(a, b)))
        for i in range(m):
            p, v, w = cyc[i - 1], cyc[i], cyc[(i + 1) % m]
            u1, u2 = unit(p, v), unit(v, w)
            wedge = (half(*u1, *pts[v]), half(-u2[0], -u2[1], *pts[v]), pad)
            out.append((wedge, const(v)))
        return out
    # no triangles: a chain of collinear points sorted along the line, or one point
    (a0, b0) = tri.edges[0]
    if a0 == b0:
        return [((pad, pad, pad), const(a0))]
    for a, b in tri.edges:
        ux, uy = unit(a, b)
        out.append(((half(ux, uy, *pts[a]), half(-ux, -uy, *pts[b]), pad), edge_value(a, b)))
    first, last = tri.edges[0][0], tri.edges[-1][1]
    ux, uy = unit(*tri.edges[0])
    out.append(((half(-ux, -uy, *pts[first]), pad, pad), const(first)))
    ux, uy = unit(*tri.edges[-1])
    out.append(((half(ux, uy, *pts[last]), pad, pad), const(last)))
    return out


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
class SourceVector:
    """S = [pos | vel | acc | trunc(rev) | 0 | 1 | direction]: this cycle's commands and
    the direction state in one vector, so that every per-cycle input is a gather from S.

    The direction is the sign of the command velocity, held at standstill; it starts from
    `anwahl_losekomp` (000 §2.3.2, P-AXIS-00021; docs/design.md §3.6) and is kept across
    reloads.
    """

    n: int
    S: np.ndarray
    inputs: np.ndarray  # S[:4n]: filled with one concatenate
    pos: np.ndarray
    vel: np.ndarray
    rev: np.ndarray  # cycles until a reversal known in advance (< 0: none)
    dir: np.ndarray  # ±1
    dp: np.ndarray  # (direction, position) as one [2, n] view of S
    zero: int  # index of the constant 0
    one: int  # index of the constant 1

    @classmethod
    def create(cls, n: int, init_dir: list[float]) -> SourceVector:
        S = np.zeros(5 * n + 2)
        S[4 * n + 1] = 1.0
        d = S[4 * n + 2 :]
        d[:] = init_dir
        dp = np.lib.stride_tricks.as_strided(
            S[4 * n + 2 :], shape=(2, n), strides=(-(4 * n + 2) * 8, 8), writeable=False
        )
        return cls(
            n=n,
            S=S,
            inputs=S[: 4 * n],
            pos=S[:n],
            vel=S[n : 2 * n],
            rev=S[3 * n : 4 * n],
            dir=d,
            dp=dp,
            zero=4 * n,
            one=4 * n + 1,
        )

    def index(self, block: int, slots: np.ndarray | int) -> np.ndarray | int:
        """Index into S of block (POS, VEL, ACC, REV) of the axes in `slots`."""
        return block * self.n + slots

    def dir_index(self, slots: np.ndarray) -> np.ndarray:
        """Index into S of the direction of the axes in `slots`."""
        return 4 * self.n + 2 + slots


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

    Laid out so that both targets take one subtract and one multiply:

        (backlash, temp − offset_0) = ((d, s) − (init, position_0)) · (lose/2, coef·1e-6)

    Backlash is 0 in the start-up direction and d·lose after a reversal; with d, init
    ∈ {±1} that is (d − init)·lose/2, exactly. s is the command position, wrapped into
    [0, period) on a modulo axis (docs/design.md §3.8). `par` has the rows [init dir,
    lose/2, coefficient·1e-6, (unused), coefficient, offset_0, position_0]; its last three
    rows are the live TEMPC parameters (000 §3.2.3 objects 0x43–0x45, `TEMPC_ATTRS`
    order), of which the machine keeps views: the block is allocated once and its static
    rows are refilled in place on reload (`load`).
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
    mul: np.ndarray  # rows (lose/2, coefficient·1e-6)
    t: np.ndarray  # [2, n] scratch
    t_pos: np.ndarray  # t[1]
    out: np.ndarray  # (backlash, temperature) target columns as [2, n]
    out_temp: np.ndarray
    any_modulo: bool = False
    period: np.ndarray | None = None  # modulo period (1 on other axes)
    not_modulo: np.ndarray | None = None

    @classmethod
    def create(cls, axes: list[AxisConfig], target: np.ndarray) -> BacklashTemp:
        n = len(axes)
        par = np.zeros((7, n))
        tempc = par[4:7]
        for row, attr in enumerate(TEMPC_ATTRS):
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
            mul=par[1:3],
            t=t,
            t_pos=t[1],
            out=target[:, 0:2].T,
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
        np.multiply(self.coef, 1e-6, out=self.tc6)


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


@dataclass(slots=True, eq=False)
class Gather:
    """G = S[src]: every input that only needs this cycle's commands, with one `take`.

    G = [xt vel | xt acc | friction vel | 1-D queries | plane (u, v) | mode 3 (x, y, 1)].
    One `sign` serves the first three parts (`ns` entries), one subtract and one divide
    the query parts q = G[ns:], q ← (q − sub)/div (neutral 0 and 1 where nothing is
    scaled); before that, the 1-D and plane queries over a modulo master (the first `nw`
    query entries) are wrapped into [0, period) (000 p.31). `layout` allocates G from the
    part sizes; each compensation's builder fills `src`, `sub`, `div`, `per` and `wrap`
    for its part (arrays over the whole of G) and keeps views of its values.
    """

    G: np.ndarray
    src: np.ndarray  # index into S of every entry
    sub: np.ndarray
    div: np.ndarray
    per: np.ndarray
    wrap: np.ndarray
    sign_in: np.ndarray  # G[:ns]
    sign: np.ndarray  # sign(G[:ns])
    q: np.ndarray  # G[ns:]
    q_sub: np.ndarray
    q_div: np.ndarray
    w: np.ndarray  # G[ns:ns + nw]: the entries that may wrap
    w_per: np.ndarray
    w_wrap: np.ndarray
    w_tmp: np.ndarray
    any: bool
    any_sign: bool
    any_q: bool
    any_wrap: bool = False

    @classmethod
    def layout(cls, ns: int, nw: int, nq: int) -> Gather:
        """`ns` sign entries, then `nq` query entries of which the first `nw` may wrap."""
        ng = ns + nq
        G = np.zeros(ng)
        src = np.full(ng, -1, dtype=np.int64)
        sub, div, per = np.zeros(ng), np.ones(ng), np.ones(ng)
        wrap = np.zeros(ng, dtype=bool)
        return cls(
            G=G,
            src=src,
            sub=sub,
            div=div,
            per=per,
            wrap=wrap,
            sign_in=G[:ns],
            sign=np.zeros(ns),
            q=G[ns:],
            q_sub=sub[ns:],
            q_div=div[ns:],
            w=G[ns : ns + nw],
            w_per=per[ns : ns + nw],
            w_wrap=wrap[ns : ns + nw],
            w_tmp=np.zeros(nw),
            any=bool(ng),
            any_sign=bool(ns),
            any_q=bool(nq),
        )

    def finish(self) -> None:
        """After every part has been filled."""
        assert (self.src >= 0).all(), "every gather entry has a source"
        self.any_wrap = bool(self.w_wrap.any())


@dataclass(frozen=True, slots=True, eq=False)
class CrosstalkTables:
    """Crosstalk, new model (000 §4.6 p.84; docs/design.md §6.7): correction column and
    ratio min(|a|/a_ref, 1) of every mode 1/2/3 row (mode-3 rows first).

    The sign code 3·sign(v) + sign(a) + 4 of the dynamic master picks, per row, one row of
    `tab`: (sign(a)/(|a_ref|·UNITS_PER_MM), mode-3 region block, 1-D variant row id), so
    that a·tab[0] = |a|/|a_ref| (a in units/s², a_ref in mm/s²) without an abs and a
    divide. The ratio,
    clamped to 1 (docs/design.md §12), is the row's factor in the target vector; the
    mode-3 and 1-D builders fill columns 1 and 2 of `tab` and read `now`.
    """

    col: np.ndarray  # [rows·9] correction column per sign code
    w31: np.ndarray  # code = (3, 1)·(sign(v), sign(a))
    sign: np.ndarray  # [2, rows] (sign(v), sign(a)): a view of the gather's signs
    acc: np.ndarray  # [rows] a of the dynamic master: a view of G
    code: np.ndarray
    idx: np.ndarray
    rowoff: np.ndarray  # 9·row + 4
    tab: np.ndarray  # [rows·9, 3]
    now: np.ndarray  # [rows, 3] this cycle's rows of `tab`
    ratio: np.ndarray  # now[:, 0]
    fac: np.ndarray  # the rows' factors in the target vector

    @classmethod
    def build(
        cls,
        axes: list[AxisConfig],
        rows: list[int],
        slot: dict[int, int],
        src: SourceVector,
        g: Gather,
        part: slice,
        fac: np.ndarray,
    ) -> CrosstalkTables | None:
        if not rows:
            return None
        k = len(rows)
        xs = [axes[i].comp.crosstalk for i in rows]
        dyn = _i64([slot[x.master_dyn_ax_nr] for x in xs])
        g.src[part] = np.concatenate([src.index(VEL, dyn), src.index(ACC, dyn)])
        cols, invs = [], []
        for x in xs:
            c, v = _xt_lut(
                bool(x.velocity_dependent),
                1.0 / abs(x.acceleration) if x.acceleration else 0.0,
                1.0 / abs(x.deceleration) if x.deceleration else 0.0,
            )
            cols.append(c)
            invs.append(v)
        sa = np.tile(np.array([-1.0, 0.0, 1.0] * 3), k)
        tab = np.zeros((k * 9, 3))
        tab[:, 0] = sa * _f64(invs) / UNITS_PER_MM
        now = np.zeros((k, 3))
        return cls(
            col=_i64(cols),
            w31=np.array([3.0, 1.0]),
            sign=g.sign[part].reshape(2, k),
            acc=g.G[part][k:],
            code=np.zeros(k),
            idx=np.zeros(k, dtype=np.int64),
            rowoff=np.arange(k, dtype=float) * 9 + 4,
            tab=tab,
            now=now,
            ratio=now[:, 0],
            fac=fac,
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


@dataclass(frozen=True, slots=True, eq=False)
class PlaneTables:
    """Plane (000 §4.3 p.38–43; docs/design.md §6.4): bilinear on table[j][i], j along
    master 2, i along master 1, positions clamped to the grid.

    u = clamp((q − start)/interval, 0, last) (the gather gives (q − start)/interval),
    cell = min(floor(u), last − 1); all tables are concatenated into `tab`, and the four
    corners of the cell are gathered with one `take` at base + j0·stride + i0 + corner
    offset.
    """

    u: np.ndarray  # [2, P] (u, v): a view of G
    last: np.ndarray  # [2, P] last index along each master
    lim: np.ndarray  # max(last − 1, 0)
    fl: np.ndarray  # [2, P] floor, then cell
    frac: np.ndarray  # [2, P] fractions (u − cell)
    gfrac: np.ndarray  # [2, P] 1 − fraction
    wv: np.ndarray  # (1 − fv | fv) as [2, 1, P]
    wu: np.ndarray  # (1 − fu | fu) as [1, 2, P]
    w: np.ndarray  # [2, 2, P] corner weights [j, i]
    w4: np.ndarray  # the same as [4, P]
    sw: np.ndarray  # [2, P] (1, stride): flat cell index = i0 + j0·stride
    tmp: np.ndarray  # [2, P]
    tmp0: np.ndarray
    tmp1: np.ndarray
    k00: np.ndarray  # [P] flat cell index
    k00b: np.ndarray  # k00 as [1, 1, P]
    base4: np.ndarray  # [2, 2, P] corner offsets in `tab`
    k: np.ndarray  # [2, 2, P] corner indices
    c: np.ndarray  # [2, 2, P] corner values
    tab: np.ndarray
    out: np.ndarray  # the targets: a view of the target vector

    @classmethod
    def build(
        cls,
        axes: list[AxisConfig],
        rows: list[int],
        slot: dict[int, int],
        src: SourceVector,
        master_wrap: MasterWrap,
        g: Gather,
        part: slice,
        out: np.ndarray,
    ) -> PlaneTables | None:
        P = len(rows)
        if not P:
            return None
        ps = [axes[i].comp.plane for i in rows]
        m = np.array([[slot[x.master1_ax_nr] for x in ps], [slot[x.master2_ax_nr] for x in ps]])
        w = [[master_wrap(int(s)) for s in row] for row in m]
        g.src[part] = src.index(POS, m).reshape(-1)
        g.sub[part] = _f64(
            [[x.start_position_master1 for x in ps], [x.start_position_master2 for x in ps]]
        )
        g.div[part] = _f64([[x.interval1 for x in ps], [x.interval2 for x in ps]])
        g.wrap[part] = np.array([[a for a, _ in r] for r in w], dtype=bool).reshape(-1)
        g.per[part] = _f64([[b for _, b in r] for r in w])
        tabs = [np.atleast_2d(np.asarray(x.table, dtype=float)) for x in ps]
        last = np.array(
            [[t.shape[1] - 1 for t in tabs], [t.shape[0] - 1 for t in tabs]], dtype=float
        )
        stride = np.array([t.shape[1] for t in tabs], dtype=float)
        sizes = [t.size for t in tabs]
        base = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(float)
        step1 = (last[0] > 0).astype(float)
        step2 = (last[1] > 0) * stride
        # corner offsets [j, i]: (j0, i0), (j0, i1), (j1, i0), (j1, i1) — the reference's order
        base4 = np.stack(
            [np.stack([base, base + step1]), np.stack([base + step2, base + step2 + step1])]
        )
        uv = np.zeros((2, 2, P))  # [axis u/v][1 − frac, frac]
        wts = np.zeros((2, 2, P))
        tmp = np.zeros((2, P))
        k00 = np.zeros(P)
        return cls(
            u=g.G[part].reshape(2, P),
            last=last,
            lim=np.maximum(last - 1, 0),
            fl=np.zeros((2, P)),
            frac=uv[:, 1],
            gfrac=uv[:, 0],
            wv=uv[1][:, None, :],
            wu=uv[0][None, :, :],
            w=wts,
            w4=wts.reshape(4, P),
            sw=np.stack([np.ones(P), stride]),
            tmp=tmp,
            tmp0=tmp[0],
            tmp1=tmp[1],
            k00=k00,
            k00b=k00[None, None, :],
            base4=base4,
            k=np.zeros((2, 2, P), dtype=np.int64),
            c=np.zeros((2, 2, P)),
            tab=np.concatenate([t.ravel() for t in tabs]),
            out=out,
        )


@dataclass(frozen=True, slots=True, eq=False)
class Mode3Tables:
    """Crosstalk mode 3 (000 §4.6 p.84; docs/design.md §6.7, §12): the first convex
    region containing (x, y) of the row's correction column, and its affine value
    (see `_regions`); rows whose hull is not a plain convex cycle use the scalar
    `evaluate` (`slow`).

    λ[j, v·G + g] = (a, b, c)[j, v, g] · (x, y, 1)[j] for every half-plane v of every
    region g: one stacked matmul; then min over v, ≥ −INSIDE_EPS, first region wins.
    """

    xy1: np.ndarray  # [T, 3] (x, y, 1): a view of G
    xy1c: np.ndarray  # as [T, 3, 1]
    H: np.ndarray  # [T, 3·G, 3] half-planes
    lamm: np.ndarray  # [T, 3·G, 1]
    lam0: np.ndarray  # λ of half-plane 0, 1, 2: [T, G]
    lam1: np.ndarray
    lam2: np.ndarray
    min: np.ndarray  # [T, G]
    inside: np.ndarray  # [T, G]
    sel: np.ndarray  # [T] chosen region (+ block of the column)
    off_now: np.ndarray  # [T] this cycle's region block (CrosstalkTables.now)
    val: np.ndarray  # [T·4·G, 3] (α, β, γ) per region and column
    coef: np.ndarray  # [T, 3]
    coef1: np.ndarray  # as [T, 1, 3]
    out: np.ndarray  # [T] the values: a view of the target vector
    out11: np.ndarray  # as [T, 1, 1]
    colv: np.ndarray  # correction column per sign code
    slow: list[tuple[int, Triangulation, list[list[float]]]]

    @classmethod
    def build(
        cls,
        axes: list[AxisConfig],
        rows: list[int],
        slot: dict[int, int],
        src: SourceVector,
        g: Gather,
        part: slice,
        out: np.ndarray,
        xt: CrosstalkTables | None,
    ) -> Mode3Tables | None:
        T = len(rows)
        if not T:
            return None
        xs = [axes[i].comp.crosstalk for i in rows]
        regs, slow = [], []
        for j, x in enumerate(xs):
            corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
            m = min(len(x.ax_1), len(x.ax_2), corr.shape[0])
            t = triangulate(tuple((float(x.ax_1[i]), float(x.ax_2[i])) for i in range(m)))
            r = _regions(t, corr) if t.edges else None
            if r is None:  # unusual hull: this row uses the scalar reference evaluation
                slow.append((j, t, [list(map(float, corr[:, c])) for c in range(4)]))
                r = []
            regs.append(r)
        G = max(1, max(len(r) for r in regs))
        never = ((0.0, 0.0, -1.0),) * 3
        H = np.zeros((T, 3, G, 3))
        H[...] = -1.0  # padding: λ = −1 never matches
        H[..., 0] = H[..., 1] = 0.0
        VALC = np.zeros((T, 4, G, 3))
        for j, r in enumerate(regs):
            for k, (hp, val) in enumerate(r or [(never, [(0.0, 0.0, 0.0)] * 4)]):
                for v in range(3):
                    H[j, v, k] = hp[v]
                for c in range(4):
                    VALC[j, c, k] = val[c]
        # region block of (row j, column c) starts at (4·j + c)·G, per sign code
        cols = xt.col.reshape(-1, 9)[:T]
        xt.tab[: T * 9, 1] = ((np.arange(T)[:, None] * 4 + cols) * G).reshape(-1)
        p1 = [slot[x.master_pos1_ax_nr] for x in xs]
        p2 = [slot[x.master_pos2_ax_nr] for x in xs]
        g.src[part] = _i64(
            [[src.index(POS, a), src.index(POS, b), src.one] for a, b in zip(p1, p2, strict=True)]
        )
        xy1 = g.G[part].reshape(T, 3)
        lamm = np.zeros((T, 3 * G, 1))
        lam = lamm.reshape(T, 3, G)
        coef = np.zeros((T, 3))
        return cls(
            xy1=xy1,
            xy1c=xy1[:, :, None],
            H=np.ascontiguousarray(H.reshape(T, 3 * G, 3)),
            lamm=lamm,
            lam0=lam[:, 0],
            lam1=lam[:, 1],
            lam2=lam[:, 2],
            min=np.zeros((T, G)),
            inside=np.zeros((T, G), dtype=bool),
            sel=np.zeros(T, dtype=np.int64),
            off_now=xt.now[:T, 1],
            val=VALC.reshape(-1, 3),
            coef=coef,
            coef1=coef[:, None, :],
            out=out,
            out11=out.reshape(T, 1, 1),
            colv=cols.reshape(-1),
            slow=slow,
        )


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


@dataclass(slots=True, eq=False)
class FrictionState:
    """Friction (000 §4.5 p.64–79; docs/design.md §6.6) state kept across reloads: the
    delay line of every axis (one row per cycle; rows of axes without friction carry
    zeros, as in the reference's per-axis delay lines) and the path since the last
    reversal."""

    ring: np.ndarray  # [RING, n]
    ring_flat: np.ndarray
    ring_rows: list[np.ndarray]  # ring[i], for every write position i
    ring_pos: int
    path: np.ndarray
    dpos: np.ndarray  # |pos − previous pos|
    target: np.ndarray  # the friction column of the kernel's arrays (views)
    actual: np.ndarray
    effective: np.ndarray

    @classmethod
    def create(cls, target: np.ndarray, actual: np.ndarray, eff: np.ndarray) -> FrictionState:
        n = len(target)
        ring = np.zeros((RING, n))
        return cls(
            ring=ring,
            ring_flat=ring.reshape(-1),
            ring_rows=list(ring),
            ring_pos=0,
            path=np.full(n, np.inf),
            dpos=np.zeros(n),
            target=target[:, FRICT],
            actual=actual[:, FRICT],
            effective=eff[:, FRICT],
        )


@dataclass(frozen=True, slots=True, eq=False)
class FrictionTables:
    """Friction (000 §4.5 p.64–79; docs/design.md §6.6) parameters of one load.

    base = sign(v)·scaling_factor/1000·table(|v|) (the table is a row of the merged 1-D
    lookup; sign·scale is its factor in the target vector); weighted before a reversal by
    r/(lookahead + 1) (`wpre`, from the merged lookup) and after it by min(1, path /
    position_delay) (`wpost`); the output is the value written `delay_cycles` ago.
    """

    any: bool  # some axis has friction
    slots: np.ndarray
    scale: np.ndarray  # scaling_factor/1000
    sign: np.ndarray  # sign(v): a view of the gather's signs
    fac: np.ndarray  # sign·scale: a view of the target vector's factors
    wpre_in: np.ndarray  # pre-reversal weights: a view of the target vector
    wpre: np.ndarray  # [n], 1 on axes without friction
    pd: np.ndarray  # position_delay (0: no post-reversal weight)
    has_pd: np.ndarray
    any_pd: bool
    wpost: np.ndarray  # [n]
    ridx_rows: list[np.ndarray]  # per write position: read index of every axis
    rv: np.ndarray  # [n] scratch

    @classmethod
    def build(
        cls,
        axes: list[AxisConfig],
        rows: list[int],
        src: SourceVector,
        g: Gather,
        part: slice,
        fac: np.ndarray,
        wpre_in: np.ndarray,
    ) -> FrictionTables:
        n = len(axes)
        slots = _i64(rows)
        g.src[part] = src.index(VEL, slots)
        pd = np.zeros(n)
        delay = np.zeros(n, dtype=np.int64)
        for i in rows:
            fr = axes[i].comp.frict
            pd[i] = float(fr.position_delay)
            delay[i] = int(fr.delay_cycles)
        has_pd = pd > 0
        # read index of every axis for every write position: (pos − delay) mod RING
        pos = np.arange(RING)[:, None]
        ridx = ((pos - delay[None, :]) % RING) * n + np.arange(n)[None, :]
        return cls(
            any=bool(rows),
            slots=slots,
            scale=_f64([axes[i].comp.frict.scaling_factor / 1000.0 for i in rows]),
            sign=g.sign[part],
            fac=fac,
            wpre_in=wpre_in,
            wpre=np.ones(n),
            pd=pd,
            has_pd=has_pd,
            any_pd=bool(has_pd.any()),
            wpost=np.ones(n),
            ridx_rows=list(ridx),
            rv=np.zeros(n),
        )


# ---------------------------------------------------------------------- the kernel


class Kernel:
    """Vectorised compensation kernel for a whole machine (interface: see package doc)."""

    def __init__(self, cfg: MachineConfig) -> None:
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
        self._bt = BacklashTemp.create(axes, self.target)
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
        self._xt = xt = CrosstalkTables.build(
            axes, rows.tri + rows.lin, slot, src, g, slice(0, 2 * nxt), vec.fac_xt
        )
        self._l1 = Lookup1DTables.build(
            axes, rows, slot, src, master_wrap, g, slice(ns, o_pl), vec.l1, xt
        )
        self._plane = PlaneTables.build(
            axes, rows.plane, slot, src, master_wrap, g, slice(o_pl, o_tri), vec.plane
        )
        self._tri = Mode3Tables.build(
            axes, rows.tri, slot, src, g, slice(o_tri, o_tri + 3 * T), vec.tri, xt
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
        self._bt.tempc[TEMPC_FIELDS.index(field), slot] = float(value)
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
            selection, values = reload_changes(old.axes[int(a)], cfg.axes[int(a)])
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
        """One GEO cycle for every axis (docs/design.md §5.1 step 3).

        Written as one flat sequence of numpy calls on local names (attribute lookups
        and helper calls cost as much as a small numpy call here).
        """
        mul, add, subtract = np.multiply, np.add, np.subtract
        copyto, minimum, maximum = np.copyto, np.minimum, np.maximum
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

        # effective = selected ∧ preconditions (docs/design.md §6.8); a change is a step
        # event (§3.5)
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

        # backlash (d − init)·lose/2 (000 §2) and temperature offset_0 + coefficient·1e-6
        # ·(s − position_0) (000 §3.1 p.15): see `BacklashTemp`
        bt = self._bt
        btt = bt.t
        subtract(src.dp, bt.sub, btt)  # (d − init, s − position_0)
        if bt.any_modulo:
            np.mod(pos, bt.period, t1)
            copyto(t1, pos, where=bt.not_modulo)
            subtract(t1, bt.pos0, bt.t_pos)
        mul(btt, bt.mul, bt.out)
        add(bt.off0, bt.out_temp, bt.out_temp)

        # the inputs of cross, plane, crosstalk and friction: one gather from S
        g = self._gather
        if g.any:
            S.take(g.src, out=g.G)
            if g.any_sign:
                np.sign(g.sign_in, g.sign)
            if g.any_q:
                q = g.q
                if g.any_wrap:  # modulo master: position wrapped into [0, period)
                    gw, gt = g.w, g.w_tmp
                    np.mod(gw, g.w_per, gt)
                    copyto(gw, gt, where=g.w_wrap)
                subtract(q, g.q_sub, q)
                np.divide(q, g.q_div, q)
        xt = self._xt
        if xt is not None:
            # crosstalk (000 §4.6 p.84): column by accelerate/decelerate × direction and
            # the ratio |a|/a_ref clamped to 1 (docs/design.md §12), every new-model row
            code, idx = xt.code, xt.idx
            np.dot(xt.w31, xt.sign, out=code)
            add(code, xt.rowoff, idx, casting="unsafe")
            xt.tab.take(idx, axis=0, out=xt.now)
            fx = xt.fac
            mul(xt.acc, xt.ratio, fx)
            minimum(fx, 1.0, out=fx)
        l1 = self._l1
        if l1 is not None:
            # cross (000 §4.2), friction base (§4.5), crosstalk modes 1/2 and old model
            # (§4.6, 001 §4.5) and the friction pre-reversal weight: one merged lookup
            lk = l1.lookup
            if l1.has_lin:  # this cycle's correction column of the crosstalk rows
                copyto(l1.lin_rowid, l1.lin_now)
            copyto(lk.q, l1.raw)
            lk.seg_table.take(lk.keys.searchsorted(lk.qc, "right"), axis=0, out=lk.seg)
            lt = lk.tmp
            subtract(lk.q, lk.x0, lt)
            mul(lt, lk.slope, lt)
            add(lt, lk.y0, l1.out)
        pl = self._plane
        if pl is not None:
            # plane (000 §4.3): u = clamp((q − start)/interval, 0, last);
            # cell = min(floor(u), last − 1); bilinear on table[j][i]
            u, fl = pl.u, pl.fl
            maximum(u, 0.0, out=u)
            minimum(u, pl.last, out=u)
            np.floor(u, fl)
            minimum(fl, pl.lim, out=fl)
            subtract(u, fl, pl.frac)
            subtract(1.0, pl.frac, pl.gfrac)
            # weights [j, i] = (1 − fv | fv)_j · (1 − fu | fu)_i
            pw = pl.w
            mul(pl.wv, pl.wu, pw)
            # corner indices: base + j0·stride + i0 + corner offset
            mul(fl, pl.sw, pl.tmp)
            add(pl.tmp0, pl.tmp1, pl.k00)
            pk, pc = pl.k, pl.c
            add(pl.k00b, pl.base4, pk, casting="unsafe")
            pl.tab.take(pk, out=pc)
            mul(pw, pc, pw)
            po = pl.out  # the corners in a fixed order (the batch adds them alike)
            add(pw[0, 0], pw[0, 1], po)
            add(po, pw[1, 0], po)
            add(po, pw[1, 1], po)
        tri = self._tri
        if tri is not None:
            # crosstalk mode 3 (000 §4.6 p.84, docs/design.md §12): first region
            # containing (x, y), then its affine value in the selected column (× ratio via
            # the factor vector). λ may round differently from the reference's order by
            # an ulp: the value is continuous across region boundaries, so this moves
            # results by ≪ 1e-9.
            xy1c = tri.xy1c
            np.matmul(tri.H, xy1c, out=tri.lamm)
            tmin, tin, sel = tri.min, tri.inside, tri.sel
            minimum(tri.lam0, tri.lam1, out=tmin)  # cheaper than a reduce
            minimum(tmin, tri.lam2, out=tmin)
            np.greater_equal(tmin, -INSIDE_EPS, tin)
            tin.argmax(axis=1, out=sel)  # first region wins
            add(sel, tri.off_now, sel, casting="unsafe")
            coef = tri.coef
            tri.val.take(sel, axis=0, out=coef)
            np.matmul(tri.coef1, xy1c, out=tri.out11)  # (α, β, γ)·(x, y, 1)
            if tri.slow:
                vt, xy1 = tri.out, tri.xy1
                for j, t, cols in tri.slow:
                    col = int(tri.colv[xt.idx[j]])
                    vt[j] = evaluate(t, cols[col], xy1[j, 0], xy1[j, 1])
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
        mul(jump, w, t7)
        subtract(tgt, t7, act)
        if self._any_held:  # COMP … NO_MOVE: output held (LSEC reads the held values)
            copyto(act, prev, where=self.held)

        ls = self._lsec
        if ls is not None:
            # LSEC (000 §4.4): see `LsecTables`
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
            lk.seg_table.take(lk.keys.searchsorted(lk.qc, "right"), axis=0, out=lk.seg)
            lt = lk.tmp
            subtract(lk.q, lk.x0, lt)
            mul(lt, lk.slope, lt)
            c = ls.col
            tl = c.target
            if ls.all:
                add(lt, lk.y0, tl)
            else:
                add(lt, lk.y0, ls.val)
                tflat.put(ls.flat, ls.val)
            mul(tl, c.effective, tl)
            tld = c.tmp
            subtract(tl, c.prev, tld)
            copyto(c.jump, tld, where=c.event)
            mul(c.jump, c.weight, tld)
            subtract(tl, tld, c.actual)
            if self._any_held:
                copyto(c.actual, c.prev, where=self.held[:, LEAD])

        # friction (000 §4.5): reversal weights and the delay line, for every axis
        path = fs.path
        copyto(path, 0.0, where=rev)  # path since the last reversal
        np.abs(dpos, dpos)
        add(path, dpos, path)
        wpos = fs.ring_pos
        fs.ring_pos = wpos + 1 if wpos < RING - 1 else 0
        # this cycle's value into the delay line: sign(v)·scale·table(|v|) (0 when not
        # effective) × the pre-reversal and the post-reversal weight
        cur = fs.ring_rows[wpos]
        if fr.any:
            # before the reversal: r/(lookahead + 1) while 0 ≤ r ≤ lookahead
            wpre = fr.wpre
            wpre.put(fr.slots, fr.wpre_in)
            mul(fs.target, wpre, cur)
        else:
            copyto(cur, fs.target)
        if fr.any_pd:  # after the reversal: min(1, path / position_delay)
            wp = fr.wpost
            np.divide(path, fr.pd, wp, where=fr.has_pd)
            minimum(wp, 1.0, out=wp)
            mul(cur, wp, cur)
        # delay line: read `delay_cycles` back; output only while effective
        rv = fr.rv
        fs.ring_flat.take(fr.ridx_rows[wpos], out=rv)
        mul(rv, fs.effective, fs.actual)  # = friction_current

        subtract(act, prev, self.delta)
        np.matmul(act, self._not_fr, out=self.total_offset)  # Σ columns but friction
