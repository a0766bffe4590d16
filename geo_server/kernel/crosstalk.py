"""Crosstalk compensation, new model (000 §4.6 p.82–84; docs/design.md §6.7, §12): the
laws of a cycle, written once for a single cycle (`Kernel.step`) and a pass of steady
cycles (`KernelBatch.run`).

The tables (`CrosstalkTables`, `Mode3Tables`, with the mode-3 regions of `_regions`) are
built at load time; the laws run on a work object of any leading shape — () for one cycle,
(B,) for a pass — so both paths compute the same IEEE operations in the same order:

* `state`: the correction column by accelerate/decelerate × direction of the dynamic
  master (sign code 3·sign(v) + sign(a), exact for signs) and the ratio min(|a|/a_ref, 1);
* `mode3`: the first convex region containing (x, y) and its affine value (mode 3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from geo_server.kernel.common import ACC, POS, VEL
from geo_server.kernel.triangulation import INSIDE_EPS, Triangulation, triangulate
from geo_server.model import AxisConfig
from geo_server.units import UNITS_PER_MM

if TYPE_CHECKING:
    from geo_server.kernel.inputs import Gather, SourceVector

#: Outside the hull, neighbouring regions overlap by this distance [units] so that
#: rounding can never leave a point in no region; the value there is continuous, so the
#: overlap changes results by at most REGION_TOL·|gradient| (≪ 1e-9 for real tables).
REGION_TOL = 1e-6


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
class StateWork:
    """Inputs, scratch and outputs of `state` for `rows` new-model rows."""

    sign_v: np.ndarray  # [*lead, rows] sign of the dynamic master's velocity
    sign_a: np.ndarray  # [*lead, rows] sign of its acceleration
    acc: np.ndarray  # [*lead, rows] its acceleration
    code: np.ndarray  # [*lead, rows] sign code
    idx: np.ndarray  # [*lead, rows] row of `tab`
    now: np.ndarray  # [*lead, rows, 3] this cycle's rows of `tab`
    ratio: np.ndarray  # now[..., 0]
    fac: np.ndarray  # [*lead, rows] the rows' factors (a view of the target factors)

    @classmethod
    def create(
        cls, sign_v: np.ndarray, sign_a: np.ndarray, acc: np.ndarray, fac: np.ndarray
    ) -> StateWork:
        shape = sign_v.shape
        now = np.zeros((*shape, 3))
        return cls(
            sign_v=sign_v,
            sign_a=sign_a,
            acc=acc,
            code=np.zeros(shape),
            idx=np.zeros(shape, dtype=np.int64),
            now=now,
            ratio=now[..., 0],
            fac=fac,
        )


def state(rowoff: np.ndarray, tab: np.ndarray, w: StateWork) -> None:
    """Each row's `tab` row for this cycle's sign code (`w.now`: 1/a_ref with the sign of
    a, the mode-3 region block, the 1-D variant row id) and its factor
    min(a·now[0], 1) = min(|a|/|a_ref|, 1) (docs/design.md §12)."""
    code = w.code
    np.multiply(w.sign_v, 3.0, code)  # (3, 1)·(sign(v), sign(a)): exact
    np.add(code, w.sign_a, code)
    np.add(code, rowoff, w.idx, casting="unsafe")
    tab.take(w.idx, axis=0, out=w.now)
    np.multiply(w.acc, w.ratio, w.fac)
    np.minimum(w.fac, 1.0, out=w.fac)


@dataclass(frozen=True, slots=True, eq=False)
class Mode3Work:
    """Inputs, scratch and outputs of `mode3` for T rows and G regions per row."""

    xy1c: np.ndarray  # [*lead, T, 3, 1] (x, y, 1)
    lamm: np.ndarray  # [*lead, T, 3·G, 1]
    lam0: np.ndarray  # λ of half-plane 0, 1, 2: [*lead, T, G]
    lam1: np.ndarray
    lam2: np.ndarray
    min: np.ndarray  # [*lead, T, G]
    inside: np.ndarray  # [*lead, T, G]
    sel: np.ndarray  # [*lead, T] chosen region (+ block of the column)
    off_now: np.ndarray  # [*lead, T] this cycle's region block (`StateWork.now`)
    coef: np.ndarray  # [*lead, T, 3]
    coef1: np.ndarray  # as [*lead, T, 1, 3]
    out11: np.ndarray  # [*lead, T, 1, 1] the values: a view of the target vector

    @classmethod
    def create(cls, xy1c: np.ndarray, G: int, off_now: np.ndarray, out11: np.ndarray) -> Mode3Work:
        lead_t = xy1c.shape[:-2]  # (*lead, T)
        lamm = np.zeros((*lead_t, 3 * G, 1))
        lam = lamm.reshape(*lead_t, 3, G)
        coef = np.zeros((*lead_t, 3))
        return cls(
            xy1c=xy1c,
            lamm=lamm,
            lam0=lam[..., 0, :],
            lam1=lam[..., 1, :],
            lam2=lam[..., 2, :],
            min=np.zeros((*lead_t, G)),
            inside=np.zeros((*lead_t, G), dtype=bool),
            sel=np.zeros(lead_t, dtype=np.int64),
            off_now=off_now,
            coef=coef,
            coef1=coef[..., None, :],
            out11=out11,
        )


def mode3(H: np.ndarray, val: np.ndarray, w: Mode3Work) -> None:
    """Crosstalk mode 3 (000 §4.6 p.84, docs/design.md §12): λ = H·(x, y, 1) for every
    half-plane of every region (one stacked matmul), the first region whose three λ are
    ≥ −INSIDE_EPS, and its affine value (α, β, γ)·(x, y, 1) in the row's column.

    λ may round differently from the reference's order by an ulp: the value is
    continuous across region boundaries, so this moves results by ≪ 1e-9."""
    np.matmul(H, w.xy1c, out=w.lamm)
    tmin = w.min
    np.minimum(w.lam0, w.lam1, out=tmin)  # cheaper than a reduce
    np.minimum(tmin, w.lam2, out=tmin)
    np.greater_equal(tmin, -INSIDE_EPS, w.inside)
    w.inside.argmax(axis=-1, out=w.sel)  # first region wins
    np.add(w.sel, w.off_now, w.sel, casting="unsafe")
    val.take(w.sel, axis=0, out=w.coef)
    np.matmul(w.coef1, w.xy1c, out=w.out11)
