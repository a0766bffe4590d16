"""Fast, data-oriented compensation kernel (SPEC §3, §6, §11).

Same semantics as `geo_server.kernel.reference.ReferenceKernel` (the readable statement
and the test oracle), computed for all axes at once with numpy.

Why it is shaped like this: with the manual's table sizes the arithmetic per cycle is
tiny; the cost is the *number* of numpy calls (~0.35 µs each plus Python overhead). So
the cycle is a fixed, short sequence of whole-array calls, and everything that can be
decided from the configuration is decided in `_setup` (construction and reload):

* the inputs are copied once into one source vector `S = [pos | vel | acc | trunc(rev)
  | 0 | 1]`; every compensation gathers its inputs from S with one precomputed `take`;
* every 1-D table (cross, friction, crosstalk modes 1/2 and old model, the friction
  pre-reversal weight) is one row of a single `tables.MergedTable`: one `searchsorted`
  serves all of them; LSEC has its own (its lookup position needs this cycle's filtered
  cross and plane outputs);
* all target values go through one vector `V` (layout below), one multiplication by a
  factor vector (crosstalk acceleration ratio, friction sign·scale) and one scatter;
* crosstalk mode 3 is precomputed into convex regions with an affine value each (the
  Delaunay triangles, and outside the hull the Voronoi regions of the hull edges and
  vertices, where the nearest-hull-point value is affine too): one region test over all
  regions and one gather replace the per-vertex and per-edge evaluation;
* the sin² weights come from a table (`sin2.Sin2Filter`), all seven columns at once;
* a compensation kind nobody has configured costs nothing (Python flags from `_setup`).

All arrays are preallocated; the only per-cycle allocations are the index arrays numpy
returns from `searchsorted`.

Column order (`COMP_ORDER`): BACKLASH, TEMP, CROSS, PLANE, LEAD, FRICT, CROSSTALK.
"""

from __future__ import annotations

import math

import numpy as np

from geo_server.config import CompKind, MachineConfig
from geo_server.kernel.common import (
    BC,
    COLUMN,
    CROSS,
    CROSSTALK,
    FRICT,
    LEAD,
    PLANE,
    TEMP,
    TEMPC_FIELDS,
    filter_cycles,
    initial_direction,
    initial_selection,
)
from geo_server.kernel.sin2 import Sin2Filter, sin2_apply
from geo_server.kernel.tables import Lookup, MergedTable
from geo_server.kernel.triangulation import INSIDE_EPS, Triangulation, evaluate, triangulate

UNITS_PER_MM = 10_000.0
UNITS_PER_UM = 10.0
RING = 249  # friction delay line length: delay_cycles < 249 (000 p.79)
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
    dependent) — the reference's rules, tabulated so that the kernel needs no per-cycle
    comparisons.
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


class Kernel:
    """Vectorised compensation kernel for a whole machine (interface: see package doc)."""

    def __init__(self, cfg: MachineConfig) -> None:
        self.axis_numbers = np.array(sorted(cfg.axes), dtype=np.int64)
        n = len(self.axis_numbers)
        self.n = n
        self._slot = {int(a): i for i, a in enumerate(self.axis_numbers)}
        self.selected = np.array(
            [initial_selection(cfg.axes[int(a)]) for a in self.axis_numbers], dtype=bool
        ).reshape(n, 7)
        # outputs (updated in place: the machine keeps references to them)
        self.target = np.zeros((n, 7))
        self.actual = np.zeros((n, 7))
        self.delta = np.zeros((n, 7))
        self.effective = np.zeros((n, 7), dtype=bool)
        self.friction_current = self.actual[:, FRICT]  # the friction column, as a vector
        self.total_offset = np.zeros(n)
        # state
        p = [cfg.axes[int(a)].params for a in self.axis_numbers]
        self._tempc = np.zeros((3, n))
        self._tempc[0] = [x.temp_comp_coefficient for x in p]
        self._tempc[1] = [x.temp_comp_offset_0 for x in p]
        self._tempc[2] = [x.temp_comp_position_0 for x in p]
        self._tc6 = self._tempc[0] * 1e-6  # coefficient·1e-6, as the reference groups it
        self._dir = _f64([initial_direction(x.anwahl_losekomp) for x in p])
        self._dneg = (self._dir < 0).astype(float)  # 1.0 while moving negative
        self._path = np.full(n, np.inf)  # path since the last reversal (friction)
        self._dpos = np.zeros(n)  # |pos − previous pos| (friction path)
        self._first = True
        self._pending = np.zeros((n, 7), dtype=bool)
        self._pending_any = False
        self._ring = np.zeros((RING, n))  # friction delay line, one row per cycle
        self._ring_flat = self._ring.reshape(-1)
        self._ring_pos = 0
        # source vector S = [pos | vel | acc | trunc(reversal_in) | 0 | 1]
        self._S = np.zeros(4 * n + 2)
        self._S[4 * n + 1] = 1.0
        self._S4 = self._S[: 4 * n]  # the inputs, copied with one concatenate
        self._Spos, self._Svel = self._S[:n], self._S[n : 2 * n]
        self._Sacc, self._Srev = self._S[2 * n : 3 * n], self._S[3 * n : 4 * n]
        self._zero, self._one = 4 * n, 4 * n + 1
        # scratch
        self._prev = np.zeros((n, 7))
        self._neweff = np.zeros((n, 7), dtype=bool)
        self._event = np.zeros((n, 7), dtype=bool)
        self._b7 = np.zeros((n, 7), dtype=bool)
        self._t7 = np.zeros((n, 7))
        self._homed = np.ones(n + 2, dtype=bool)  # slot n: "no homing", n + 1: "never"
        self._homed[n + 1] = False
        self._homed_in = self._homed[:n]
        self._hb = np.zeros((2, n, 7), dtype=bool)
        self._s = np.zeros(n)  # sign of the command velocity
        self._t1 = np.zeros(n)
        self._rev = np.zeros(n, dtype=bool)
        self._rev_col = self._rev[:, None]
        self._wpre = np.ones(n)
        self._wpost = np.ones(n)
        # column views used every cycle
        t, a, e = self.target, self.actual, self.effective
        self._tgt_bc, self._tgt_temp, self._tgt_lead = t[:, BC], t[:, TEMP], t[:, LEAD]
        self._tgt_fr, self._act_fr, self._eff_fr = t[:, FRICT], a[:, FRICT], e[:, FRICT]
        self._act_lead, self._eff_lead = a[:, LEAD], e[:, LEAD]
        self._prev_lead, self._ev_lead = self._prev[:, LEAD], self._event[:, LEAD]
        self._tflat, self._aflat = t.reshape(-1), a.reshape(-1)
        self._filter: Sin2Filter | None = None
        self._setup(cfg)

    # ------------------------------------------------------------------ configuration

    def _setup(self, cfg: MachineConfig) -> None:
        """(Re)build every static array from `cfg` (construction and reload)."""
        if sorted(cfg.axes) != [int(a) for a in self.axis_numbers]:
            raise ValueError("the set of axes cannot change on reload")
        self.cfg = cfg
        n, slot = self.n, self._slot
        axes = [cfg.axes[int(a)] for a in self.axis_numbers]
        p = [ax.params for ax in axes]
        ncyc = np.array([filter_cycles(ax) for ax in axes], dtype=np.int64).reshape(n, 7)
        ncyc[:, FRICT] = 0  # friction is not sin²-filtered: its output is the delay line
        if self._filter is None:
            self._filter = Sin2Filter(ncyc)
        else:
            self._filter.set_n(ncyc)
        f = self._filter
        self._f_w_lead, self._f_j_lead = f.w[:, LEAD], f.jump[:, LEAD]
        self._t_lead = self._t7[:, LEAD]
        self._init_dir = _f64([initial_direction(x.anwahl_losekomp) for x in p])
        self._half_lose = _f64([x.lose for x in p]) / 2.0
        modulo = np.array([x.modulo for x in p], dtype=bool)
        period = _f64([x.modulo_period if x.modulo else 1.0 for x in p])
        self._any_modulo = bool(modulo.any())
        self._mod_period, self._not_modulo = period, ~modulo

        def master_wrap(m: int) -> tuple[bool, float]:
            return bool(modulo[m]), float(period[m])

        # effective = selected ∧ homed[h1] ∧ homed[h2]; "not configured" → slot n + 1
        h = np.full((2, n, 7), n, dtype=np.int64)
        h[0, :, TEMP] = np.arange(n)  # 000 §3.2: homed
        h[0, :, LEAD] = np.arange(n)  # 000 §5.3 item 2
        for i, x in enumerate(p):
            if not (x.anwahl_losekomp != 0 and x.lose != 0):
                h[0, i, BC] = n + 1
        for c in (CROSS, PLANE, LEAD, FRICT, CROSSTALK):
            h[1, :, c] = n + 1  # until configured below
        rev_mask = np.zeros((n, 7), dtype=bool)  # reversal = step event (when effective)
        rev_mask[:, BC] = True

        cross, plane, lsec, frict, lin, tri, old = [], [], [], [], [], [], []
        for i, ax in enumerate(axes):
            comp = ax.comp
            if comp is None:
                continue
            c = comp.cross
            if c is not None and c.valid and c.master_ax_nr in slot and len(c.setpoint):
                h[0, i, CROSS] = slot[c.master_ax_nr]
                h[1, i, CROSS] = n
                cross.append(i)
            pl = comp.plane
            if (
                pl is not None
                and pl.valid
                and pl.master1_ax_nr in slot
                and pl.master2_ax_nr in slot
                and pl.table.size
            ):
                h[0, i, PLANE] = slot[pl.master1_ax_nr]
                h[1, i, PLANE] = slot[pl.master2_ax_nr]
                plane.append(i)
            ls = comp.lsec
            if ls is not None and ls.valid and len(ls.setpoint):
                h[1, i, LEAD] = n
                rev_mask[i, LEAD] = ls.bilateral
                lsec.append(i)
            fr = comp.frict
            if fr is not None and fr.valid and fr.mode == 3 and len(fr.vin):
                h[1, i, FRICT] = n
                frict.append(i)
            x = comp.crosstalk
            if x is not None and x.valid and x.master_dyn_ax_nr in slot:
                ok = False
                if x.dialect == "old":
                    if len(x.acc_table):
                        old.append(i)
                        ok = True
                else:
                    corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
                    if corr.shape[0] == 0:
                        continue
                    if x.mode == 3:
                        if x.master_pos1_ax_nr in slot and x.master_pos2_ax_nr in slot:
                            tri.append(i)
                            ok = True
                    elif x.mode != 2 or x.master_pos1_ax_nr in slot:
                        lin.append(i)
                        ok = True
                if ok:
                    h[1, i, CROSSTALK] = n
        self._h, self._rev_mask = h, rev_mask

        # ---- the target vector V = [plane | xt mode 3 | xt modes 1/2 | friction | cross
        #      | xt old | friction pre-reversal weight]; all but the last part are
        #      targets. The merged 1-D lookup fills V from "xt modes 1/2" on.
        P, T, X, F = len(plane), len(tri), len(lin), len(frict)
        o_tri, o_lin = P, P + T
        o_fr = o_lin + X
        o_cross = o_fr + F
        o_old = o_cross + len(cross)
        o_wpre = o_old + len(old)
        nv = o_wpre + F
        self._V = np.zeros(nv)
        self._fac = np.ones(nv)
        self._any_fac = bool(T + X + F)
        t_flat = (
            [i * 7 + PLANE for i in plane]
            + [i * 7 + CROSSTALK for i in tri + lin]
            + [i * 7 + FRICT for i in frict]
            + [i * 7 + CROSS for i in cross]
            + [i * 7 + CROSSTALK for i in old]
        )
        self._V_flat = _i64(t_flat)
        self._V_tgt = self._V[:o_wpre]
        self._V_plane, self._V_tri = self._V[:P], self._V[o_tri:o_lin]
        self._V_l1, self._V_wpre = self._V[o_lin:], self._V[o_wpre:]
        self._fac_xt, self._fac_fr = self._fac[o_tri:o_fr], self._fac[o_fr:o_cross]

        self._build_xt(axes, tri, lin)
        self._build_l1(axes, lin, frict, cross, old, master_wrap)
        self._build_plane(axes, plane, master_wrap)
        self._build_tri(axes, tri)
        self._build_lsec(axes, lsec, modulo, period)
        self._build_frict(axes, frict)

    def _build_xt(self, axes: list, tri: list[int], lin: list[int]) -> None:
        """Crosstalk (new model) acceleration state: column LUT and ratio inputs."""
        rows = tri + lin
        self._nxt = len(rows)
        if not rows:
            return
        n, slot = self.n, self._slot
        xs = [axes[i].comp.crosstalk for i in rows]
        dyn = _i64([slot[x.master_dyn_ax_nr] for x in xs])
        self._xt_src = np.stack([n + dyn, 2 * n + dyn])  # (vel, acc) of the dynamic master
        cols, invs = [], []
        for x in xs:
            c, v = _xt_lut(
                bool(x.velocity_dependent),
                1.0 / abs(x.acceleration) if x.acceleration else 0.0,
                1.0 / abs(x.deceleration) if x.deceleration else 0.0,
            )
            cols.append(c)
            invs.append(v)
        self._xt_col = _i64(cols)  # [rows·9]
        self._xt_inv = _f64(invs)
        self._xt_rowoff = np.arange(len(rows), dtype=float) * 9 + 4
        self._xt_av = np.zeros((2, len(rows)))
        self._xt_sg = np.zeros((2, len(rows)))
        self._xt_code = np.zeros(len(rows))
        self._xt_idx = np.zeros(len(rows), dtype=np.int64)
        self._xt_idx_tri, self._xt_idx_lin = self._xt_idx[: len(tri)], self._xt_idx[len(tri) :]
        self._xt_r = np.zeros(len(rows))

    def _build_l1(self, axes: list, lin, frict, cross, old, master_wrap) -> None:
        """One merged table for all 1-D lookups that only need this cycle's inputs."""
        n, slot = self.n, self._slot
        tables: list[tuple[np.ndarray, np.ndarray]] = []
        row_ids, src, div, wrap, per = [], [], [], [], []
        lin_base = []
        for i in lin:  # four variant rows each (correction columns); per-cycle choice
            x = axes[i].comp.crosstalk
            corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
            if x.mode == 1:
                keys, vals = np.zeros(1), corr[:1]
                src.append(self._zero)
            else:
                ax1 = np.asarray(x.ax_1, dtype=float)[: corr.shape[0]]
                if len(ax1) == 0:
                    ax1 = np.zeros(1)
                order = np.argsort(ax1, kind="stable")
                keys, vals = ax1[order], corr[order]
                src.append(slot[x.master_pos1_ax_nr])
            lin_base.append(len(tables))
            row_ids.append(len(tables))
            tables.extend((keys, vals[:, c]) for c in range(4))
            div.append(1.0)
            wrap.append(False)
            per.append(1.0)
        for i in frict:  # sign(v)·table(|v|) = sign(v)·mirrored table(v)
            fr = axes[i].comp.frict
            x, y = np.asarray(fr.vin, dtype=float), np.asarray(fr.out, dtype=float)
            keep = x[::-1] > 0 if x[0] == 0 else np.ones(len(x), dtype=bool)
            row_ids.append(len(tables))
            tables.append((np.concatenate([-x[::-1][keep], x]), np.concatenate([y[::-1][keep], y])))
            src.append(n + i)
            div.append(UNITS_PER_UM)
            wrap.append(False)
            per.append(1.0)
        for i in cross:
            c = axes[i].comp.cross
            m = slot[c.master_ax_nr]
            row_ids.append(len(tables))
            tables.append(
                (np.asarray(c.setpoint, dtype=float), np.asarray(c.correction, dtype=float))
            )
            src.append(m)
            div.append(1.0)
            w, pp = master_wrap(m)  # modulo master: the table wraps with it (000 p.31)
            wrap.append(w)
            per.append(pp)
        for i in old:  # old model: table over the signed acceleration in mm/s²
            x = axes[i].comp.crosstalk
            a = np.asarray(x.acc_table, dtype=float)
            order = np.argsort(a, kind="stable")
            row_ids.append(len(tables))
            tables.append((a[order], np.asarray(x.corr_table, dtype=float)[order]))
            src.append(2 * n + slot[x.master_dyn_ax_nr])
            div.append(UNITS_PER_MM)
            wrap.append(False)
            per.append(1.0)
        for i in frict:  # pre-reversal weight r/(lookahead+1) for 0 ≤ r ≤ lookahead, else 1
            look = int(axes[i].comp.frict.reversal_lookahead)
            row_ids.append(len(tables))
            if look > 0:
                tables.append(
                    (
                        np.array([-1.0, 0.0, look, look + 1.0]),
                        np.array([1.0, 0.0, look / (look + 1), 1.0]),
                    )
                )
            else:
                tables.append((np.zeros(1), np.ones(1)))
            src.append(3 * n + i)
            div.append(1.0)
            wrap.append(False)
            per.append(1.0)
        self._n_l1 = len(row_ids)
        if not self._n_l1:
            return
        self._l1 = Lookup(MergedTable(tables), _f64(row_ids))
        self._l1_src, self._l1_div = _i64(src), _f64(div)
        self._l1_raw = np.zeros(self._n_l1)
        self._l1_wrap, self._l1_per = np.array(wrap, dtype=bool), _f64(per)
        self._l1_any_wrap = bool(self._l1_wrap.any())
        self._l1_tmp = np.zeros(self._n_l1)
        # variant row ids of the crosstalk rows: base + column, tabulated per sign code
        # (indexed like the crosstalk state: mode-3 rows first, their entries unused)
        self._lin_rowid = np.zeros(self._nxt * 9)
        if lin:
            cols = self._xt_col.reshape(-1, 9)[-len(lin) :]
            rowid = np.array(lin_base, dtype=float)[:, None] + cols
            self._lin_rowid[-len(lin) * 9 :] = rowid.reshape(-1)
        self._l1_rowid_lin = self._l1.qc.real[: len(lin)]
        self._fr_slots = _i64(frict)
        self._fr_scale = _f64([axes[i].comp.frict.scaling_factor / 1000.0 for i in frict])
        self._fr_s = np.zeros(len(frict))

    def _build_plane(self, axes: list, rows: list[int], master_wrap) -> None:
        self._n_plane = P = len(rows)
        if not P:
            return
        slot = self._slot
        ps = [axes[i].comp.plane for i in rows]
        m = np.array([[slot[x.master1_ax_nr] for x in ps], [slot[x.master2_ax_nr] for x in ps]])
        self._pl_src = m.astype(np.int64)
        w = [[master_wrap(int(s)) for s in row] for row in m]
        self._pl_wrap = np.array([[a for a, _ in r] for r in w], dtype=bool)
        self._pl_per = np.array([[b for _, b in r] for r in w], dtype=float)
        self._pl_any_wrap = bool(self._pl_wrap.any())
        tabs = [np.atleast_2d(np.asarray(x.table, dtype=float)) for x in ps]
        self._pl_s0 = np.array(
            [[x.start_position_master1 for x in ps], [x.start_position_master2 for x in ps]],
            dtype=float,
        )
        self._pl_iv = np.array([[x.interval1 for x in ps], [x.interval2 for x in ps]], dtype=float)
        last = np.array(
            [[t.shape[1] - 1 for t in tabs], [t.shape[0] - 1 for t in tabs]], dtype=float
        )
        self._pl_last, self._pl_lim = last, np.maximum(last - 1, 0)
        stride = np.array([t.shape[1] for t in tabs], dtype=float)
        self._pl_sw = np.stack([np.ones(P), stride])  # flat cell index = i0 + j0·stride
        sizes = [t.size for t in tabs]
        base = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(float)
        step1 = (last[0] > 0).astype(float)
        step2 = (last[1] > 0) * stride
        # corner offsets [j, i]: (j0, i0), (j0, i1), (j1, i0), (j1, i1) — the reference's order
        self._pl_base4 = np.stack(
            [np.stack([base, base + step1]), np.stack([base + step2, base + step2 + step1])]
        )
        self._pl_tab = np.concatenate([t.ravel() for t in tabs])
        self._pl_q, self._pl_tmp = np.zeros((2, P)), np.zeros((2, P))
        self._pl_u, self._pl_f = np.zeros((2, P)), np.zeros((2, P))
        self._pl_uv = np.zeros((2, 2, P))  # [axis u/v][1 − frac, frac]
        self._pl_frac, self._pl_gfrac = self._pl_uv[:, 1], self._pl_uv[:, 0]
        self._pl_V, self._pl_U = self._pl_uv[1][:, None, :], self._pl_uv[0][None, :, :]
        self._pl_w = np.zeros((2, 2, P))
        self._pl_w4 = self._pl_w.reshape(4, P)
        self._pl_c = np.zeros((2, 2, P))
        self._pl_k = np.zeros((2, 2, P), dtype=np.int64)
        self._pl_k00 = np.zeros(P)
        self._pl_k00b = self._pl_k00[None, None, :]

    def _build_tri(self, axes: list, rows: list[int]) -> None:
        """Crosstalk mode 3: regions with affine values (see `_regions`)."""
        self._n_tri = T = len(rows)
        if not T:
            return
        slot = self._slot
        xs = [axes[i].comp.crosstalk for i in rows]
        regs, self._tri_slow = [], []
        for j, x in enumerate(xs):
            corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
            m = min(len(x.ax_1), len(x.ax_2), corr.shape[0])
            t = triangulate(tuple((float(x.ax_1[i]), float(x.ax_2[i])) for i in range(m)))
            r = _regions(t, corr) if t.edges else None
            if r is None:  # unusual hull: this row uses the scalar reference evaluation
                self._tri_slow.append((j, t, [list(map(float, corr[:, c])) for c in range(4)]))
                r = []
            regs.append(r)
        G = max(1, max(len(r) for r in regs))
        never = ((0.0, 0.0, -1.0),) * 3
        H = np.zeros((T, 3, G, 3))
        H[...] = -1.0  # padding: λ = −1 never matches
        H[..., 0] = H[..., 1] = 0.0
        VALC = np.zeros((T, 4, G, 3))
        for j, r in enumerate(regs):
            for g, (hp, val) in enumerate(r or [(never, [(0.0, 0.0, 0.0)] * 4)]):
                for v in range(3):
                    H[j, v, g] = hp[v]
                for c in range(4):
                    VALC[j, c, g] = val[c]
        self._tri_A = np.ascontiguousarray(H[..., 0])
        self._tri_B = np.ascontiguousarray(H[..., 1])
        self._tri_C = np.ascontiguousarray(H[..., 2])
        self._tri_val = VALC.reshape(-1, 3)
        # region block of (row j, column c) starts at (4·j + c)·G, tabulated per sign code
        cols = self._xt_col.reshape(-1, 9)[:T]
        self._tri_off = ((np.arange(T)[:, None] * 4 + cols) * G).reshape(-1)
        self._tri_colv = cols.reshape(-1)
        p1 = [slot[x.master_pos1_ax_nr] for x in xs]
        p2 = [slot[x.master_pos2_ax_nr] for x in xs]
        self._tri_src = np.array(
            [[a, b, self._one] for a, b in zip(p1, p2, strict=True)], dtype=np.int64
        )
        self._tri_xy1 = np.zeros((T, 3))  # (x, y, 1) per row
        self._tri_x = self._tri_xy1[:, 0, None, None]
        self._tri_y = self._tri_xy1[:, 1, None, None]
        self._tri_lam = np.zeros((T, 3, G))
        self._tri_lam2 = np.zeros((T, 3, G))
        self._tri_l0, self._tri_l1, self._tri_l2 = (self._tri_lam[:, v] for v in range(3))
        self._tri_min = np.zeros((T, G))
        self._tri_in = np.zeros((T, G), dtype=bool)
        self._tri_sel = np.zeros(T, dtype=np.int64)
        self._tri_off_now = np.zeros(T, dtype=np.int64)
        self._tri_coef = np.zeros((T, 3))

    def _build_lsec(self, axes: list, rows: list[int], modulo, period) -> None:
        self._n_lsec = L = len(rows)
        if not L:
            return
        ls = [axes[i].comp.lsec for i in rows]
        tables = []
        for x in ls:  # rows 2j (pos) and 2j + 1 (neg; = pos when unilateral)
            tables.append((x.setpoint, x.pos))
            tables.append((x.setpoint, x.neg if x.bilateral else x.pos))
        # the applied offset is −Δs: negate the values once here
        tables = [(np.asarray(k, dtype=float), -np.asarray(v, dtype=float)) for k, v in tables]
        self._ls = Lookup(MergedTable(tables), np.arange(L, dtype=float) * 2)
        self._ls_base = np.arange(L, dtype=float) * 2
        self._ls_slots = _i64(rows)
        self._ls_flat = self._ls_slots * 7 + LEAD
        self._ls_all = rows == list(range(self.n))
        self._ls_cp = np.stack([self._ls_slots * 7 + CROSS, self._ls_slots * 7 + PLANE])
        wc = _f64([0.0 if x.set_pos_without_comp else 1.0 for x in ls])
        self._ls_wc = wc
        self._ls_all_wc = bool(wc.all())
        self._ls_x0 = _f64([float(x.setpoint[0]) for x in ls])
        spans = _f64([float(x.setpoint[-1] - x.setpoint[0]) for x in ls])
        per = np.where(modulo[self._ls_slots], period[self._ls_slots], spans)
        self._ls_wrap = np.array([x.modulo for x in ls], dtype=bool) & (per > 0)
        self._ls_per = np.where(per > 0, per, 1.0)
        self._ls_any_wrap = bool(self._ls_wrap.any())
        self._ls_cpv = np.zeros((2, L))
        self._ls_t, self._ls_d, self._ls_val = np.zeros(L), np.zeros(L), np.zeros(L)

    def _build_frict(self, axes: list, rows: list[int]) -> None:
        n = self.n
        pd = np.zeros(n)
        delay = np.zeros(n, dtype=np.int64)
        for i in rows:
            fr = axes[i].comp.frict
            pd[i] = float(fr.position_delay)
            delay[i] = int(fr.delay_cycles)
        self._fr_rows = _i64(rows)
        self._fr_pd, self._fr_has_pd = pd, pd > 0
        self._fr_any_pd = bool(self._fr_has_pd.any())
        # read index of every axis for every ring position (the reference's
        # (pos − delay) mod 249), so that a cycle only picks a row of it
        pos = np.arange(RING)[:, None]
        self._fr_ridx = ((pos - delay[None, :]) % RING) * n + np.arange(n)[None, :]
        self._wpre[:] = 1.0
        self._wpost[:] = 1.0
        self._fr_rv = np.zeros(n)

    # ------------------------------------------------------------------ interface

    def slot_of(self, axis_number: int) -> int:
        return self._slot[int(axis_number)]

    def set_selected(self, slot: int, kind: CompKind, on: bool) -> None:
        """COMP ON/OFF or a `TEMPC::activated` write (000 §5.1 p.94, §3.2 p.15)."""
        self.selected[slot, COLUMN[kind]] = bool(on)

    @property
    def tempc_params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Live coefficient, offset_0, position_0 (views, 000 §3.2.3 objects 0x43–0x45)."""
        return self._tempc[0], self._tempc[1], self._tempc[2]

    def write_tempc(self, slot: int, field: str, value: float) -> None:
        """TEMPC parameter write: step event with temp_comp_n_cycles (SPEC §3)."""
        self._tempc[TEMPC_FIELDS.index(field), slot] = float(value)
        np.multiply(self._tempc[0], 1e-6, out=self._tc6)
        self._pending[slot, TEMP] = True
        self._pending_any = True

    def reload(self, cfg: MachineConfig) -> None:
        """Swap tables at this cycle boundary (SPEC §4): a step event on every column.

        Selection and live TEMPC values follow the new lists only where the lists
        changed them (see `ReferenceKernel.reload`).
        """
        old = self.cfg
        self._setup(cfg)
        for i, a in enumerate(self.axis_numbers):
            o, nw = old.axes[int(a)], cfg.axes[int(a)]
            so, sn = initial_selection(o), initial_selection(nw)
            for c in range(7):
                if so[c] != sn[c]:
                    self.selected[i, c] = sn[c]
            po, pn = o.params, nw.params
            if po.temp_comp_coefficient != pn.temp_comp_coefficient:
                self._tempc[0, i] = pn.temp_comp_coefficient
            if po.temp_comp_offset_0 != pn.temp_comp_offset_0:
                self._tempc[1, i] = pn.temp_comp_offset_0
            if po.temp_comp_position_0 != pn.temp_comp_position_0:
                self._tempc[2, i] = pn.temp_comp_position_0
        np.multiply(self._tempc[0], 1e-6, out=self._tc6)
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
        """One GEO cycle for every axis (SPEC §5 step 3)."""
        tgt, act, eff, ev = self.target, self.actual, self.effective, self._event
        s, rev, d, t1 = self._s, self._rev, self._dir, self._t1
        pos = self._Spos
        np.copyto(self._prev, act)
        if self._first:
            np.copyto(pos, cmd_pos)
            self._first = False
        np.subtract(cmd_pos, pos, self._dpos)  # pos still holds the previous cycle's
        np.concatenate((cmd_pos, cmd_vel, cmd_acc, reversal_in), out=self._S4)
        if reversal_in.dtype.kind != "i":
            np.trunc(self._Srev, out=self._Srev)  # the reference's int(): −0.5 → 0

        # direction: sign of the command velocity, last one held at standstill (SPEC §3).
        # d is always ±1, so "s ≠ 0 and s ≠ d" is s·d < 0, and the update is a flip.
        np.sign(self._Svel, s)
        np.multiply(s, d, t1)
        np.less(t1, 0.0, rev)
        np.negative(d, out=d, where=rev)
        np.less(d, 0.0, self._dneg)

        # effective = selected ∧ configured ∧ homing preconditions; events on change
        np.copyto(self._homed_in, homed)
        self._homed.take(self._h, out=self._hb)
        ne = self._neweff
        np.logical_and(self._hb[0], self._hb[1], ne)
        np.logical_and(ne, self.selected, ne)
        np.not_equal(ne, eff, ev)
        np.copyto(eff, ne)
        if self._pending_any:  # TEMPC writes, reload
            np.logical_or(ev, self._pending, ev)
            self._pending.fill(False)
            self._pending_any = False
        # reversal: step event of backlash and bilateral LSEC (P-AXIS-00243)
        b7 = self._b7
        np.logical_and(self._rev_mask, self._rev_col, b7)
        np.logical_and(b7, eff, b7)
        np.logical_or(ev, b7, ev)

        # backlash: 0 in the start-up direction, d·lose after a reversal; with d, init
        # ∈ {±1} that is (d − init)·lose/2, exactly (000 §2, SPEC §6)
        np.subtract(d, self._init_dir, t1)
        np.multiply(t1, self._half_lose, self._tgt_bc)
        # temperature: offset_0 + coefficient·1e-6·(s − position_0) (000 §3.1)
        if self._any_modulo:
            np.mod(pos, self._mod_period, t1)
            np.copyto(t1, pos, where=self._not_modulo)
            np.subtract(t1, self._tempc[2], t1)
        else:
            np.subtract(pos, self._tempc[2], t1)
        np.multiply(self._tc6, t1, t1)
        np.add(self._tempc[1], t1, self._tgt_temp)

        # cross, plane, crosstalk, friction base: all into V, then one scatter
        if self._nxt:
            self._step_xt_state()
        if self._n_l1:
            self._step_l1()
        if self._n_plane:
            self._step_plane()
        if self._n_tri:
            self._step_tri()
        if self._any_fac:
            np.multiply(self._V, self._fac, self._V)
        self._tflat.put(self._V_flat, self._V_tgt)
        np.multiply(tgt, eff, tgt)

        # sin² filter of every column (LSEC again below, once its target is known)
        f = self._filter
        f.advance(ev)
        sin2_apply(tgt, self._prev, ev, f.jump, f.w, self._t7, act)
        if self._n_lsec:
            self._step_lsec()
        self._step_frict()

        np.subtract(act, self._prev, self.delta)
        np.add.reduce(act, axis=1, out=self.total_offset)
        np.subtract(self.total_offset, self._act_fr, self.total_offset)

    def _step_xt_state(self) -> None:
        """Crosstalk (000 §4.6 p.84): column by accelerate/decelerate × direction and the
        clamped ratio |a|/|a_ref|, for every new-model row (modes 1, 2, 3)."""
        av, sg, code, idx = self._xt_av, self._xt_sg, self._xt_code, self._xt_idx
        self._S.take(self._xt_src, out=av)
        np.sign(av, sg)
        np.multiply(sg[0], 3.0, code)
        np.add(code, sg[1], code)
        np.add(code, self._xt_rowoff, idx, casting="unsafe")
        r = self._xt_r
        self._xt_inv.take(idx, out=r)
        np.abs(av[1], t := self._xt_code)  # |a| (code is no longer needed)
        np.divide(t, UNITS_PER_MM, t)
        np.multiply(t, r, t)
        np.minimum(t, 1.0, out=self._fac_xt)  # clamp beyond the reference (SPEC §12)
        if self._n_tri:
            self._tri_off.take(self._xt_idx_tri, out=self._tri_off_now)
        if len(self._xt_idx_lin):
            self._lin_rowid.take(self._xt_idx_lin, out=self._l1_rowid_lin)

    def _step_l1(self) -> None:
        """Cross (000 §4.2), friction base (§4.5), crosstalk modes 1/2 and old model
        (§4.6) and the friction pre-reversal weight: one merged lookup."""
        lk, q = self._l1, self._l1_raw
        self._S.take(self._l1_src, out=q)
        if self._l1_any_wrap:  # modulo master: position wrapped into [0, period)
            np.mod(q, self._l1_per, self._l1_tmp)
            np.copyto(q, self._l1_tmp, where=self._l1_wrap)
        np.divide(q, self._l1_div, lk.q)
        lk(self._V_l1)
        # friction: sign(v)·scaling_factor/1000
        self._s.take(self._fr_slots, out=self._fr_s)
        np.multiply(self._fr_s, self._fr_scale, self._fac_fr)

    def _step_plane(self) -> None:
        """Plane (000 §4.3): bilinear on table[j][i] (j master 2, i master 1), clamped."""
        q, u, fl = self._pl_q, self._pl_u, self._pl_f
        self._S.take(self._pl_src, out=q)
        if self._pl_any_wrap:
            np.mod(q, self._pl_per, self._pl_tmp)
            np.copyto(q, self._pl_tmp, where=self._pl_wrap)
        # u = clamp((q − start)/interval, 0, last); cell = min(floor(u), last − 1)
        np.subtract(q, self._pl_s0, u)
        np.divide(u, self._pl_iv, u)
        np.maximum(u, 0.0, out=u)
        np.minimum(u, self._pl_last, out=u)
        np.floor(u, fl)
        np.minimum(fl, self._pl_lim, out=fl)
        np.subtract(u, fl, self._pl_frac)
        np.subtract(1.0, self._pl_frac, self._pl_gfrac)
        # weights [j, i] = (1 − fv | fv)_j · (1 − fu | fu)_i
        np.multiply(self._pl_V, self._pl_U, self._pl_w)
        # corner indices: base + j0·stride + i0 + corner offset
        np.multiply(fl, self._pl_sw, self._pl_tmp)
        np.add(self._pl_tmp[0], self._pl_tmp[1], self._pl_k00)
        np.add(self._pl_k00b, self._pl_base4, self._pl_k, casting="unsafe")
        self._pl_tab.take(self._pl_k, out=self._pl_c)
        np.multiply(self._pl_w, self._pl_c, self._pl_w)
        np.add.reduce(self._pl_w4, axis=0, out=self._V_plane)

    def _step_tri(self) -> None:
        """Crosstalk mode 3 (000 §4.6 p.84, SPEC §12): first region containing (x, y),
        then its affine value in the selected column (× ratio via the factor vector)."""
        xy1, lam, lam2 = self._tri_xy1, self._tri_lam, self._tri_lam2
        self._S.take(self._tri_src, out=xy1)
        # λ = a·x + b·y + c, in the reference's order
        np.multiply(self._tri_A, self._tri_x, lam)
        np.multiply(self._tri_B, self._tri_y, lam2)
        np.add(lam, lam2, lam)
        np.add(lam, self._tri_C, lam)
        np.minimum.reduce(lam, axis=1, out=self._tri_min)
        np.greater_equal(self._tri_min, -INSIDE_EPS, self._tri_in)
        self._tri_in.argmax(axis=1, out=self._tri_sel)  # first region wins
        np.add(self._tri_sel, self._tri_off_now, self._tri_sel)
        coef = self._tri_coef
        self._tri_val.take(self._tri_sel, axis=0, out=coef)
        np.multiply(coef, xy1, coef)
        np.add.reduce(coef, axis=1, out=self._V_tri)
        for j, t, cols in self._tri_slow:
            col = int(self._tri_colv[self._xt_idx_tri[j]])
            self._V_tri[j] = evaluate(t, cols[col], xy1[j, 0], xy1[j, 1])

    def _step_lsec(self) -> None:
        """LSEC (000 §4.4): −Δs at command (+ cross + plane output), pos/neg by direction;
        then its sin² pass (reversal events were set with the others)."""
        lk = self._ls
        cp, t = self._ls_cpv, self._ls_t
        self._aflat.take(self._ls_cp, out=cp)
        np.add(cp[0], cp[1], t)
        if not self._ls_all_wc:  # set_pos_without_comp: command position only
            np.multiply(t, self._ls_wc, t)
        self._Spos.take(self._ls_slots, out=self._ls_d)
        np.add(self._ls_d, t, lk.q)
        if self._ls_any_wrap:  # modulo table: wrap into [x0, x0 + period)
            np.subtract(lk.q, self._ls_x0, t)
            np.mod(t, self._ls_per, t)
            np.add(t, self._ls_x0, t)
            np.copyto(lk.q, t, where=self._ls_wrap)
        self._dneg.take(self._ls_slots, out=self._ls_d)
        np.add(self._ls_base, self._ls_d, lk.rowid)  # row 2j pos, 2j + 1 neg
        if self._ls_all:  # every axis has LSEC: straight into the target column
            lk(self._tgt_lead)
        else:
            lk(self._ls_val)
            self._tflat.put(self._ls_flat, self._ls_val)
        np.multiply(self._tgt_lead, self._eff_lead, self._tgt_lead)
        sin2_apply(
            self._tgt_lead,
            self._prev_lead,
            self._ev_lead,
            self._f_j_lead,
            self._f_w_lead,
            self._t_lead,
            self._act_lead,
        )

    def _step_frict(self) -> None:
        """Friction (000 §4.5): reversal weights and the delay line, for every axis (the
        non-friction rows carry zeros, as in the reference's per-axis delay lines)."""
        path, t1 = self._path, self._dpos
        # path since the last reversal
        np.copyto(path, 0.0, where=self._rev)
        np.abs(t1, t1)
        np.add(path, t1, path)
        wpos = self._ring_pos
        self._ring_pos = (wpos + 1) % RING
        # this cycle's value, into the delay line: sign(v)·scale·table(|v|) (0 when not
        # effective), × the pre-reversal and the post-reversal weight
        cur = self._ring[wpos]
        if self._n_l1 and len(self._fr_slots):
            # before the reversal: r/(lookahead + 1) while 0 ≤ r ≤ lookahead
            self._wpre.put(self._fr_slots, self._V_wpre)
            np.multiply(self._tgt_fr, self._wpre, cur)
        else:
            np.copyto(cur, self._tgt_fr)
        if self._fr_any_pd:  # after the reversal: build-up over position_delay of path
            np.divide(path, self._fr_pd, self._wpost, where=self._fr_has_pd)
            np.minimum(self._wpost, 1.0, out=self._wpost)
            np.multiply(cur, self._wpost, cur)
        # delay line: read `delay_cycles` back; output only while effective
        self._ring_flat.take(self._fr_ridx[wpos], out=self._fr_rv)
        np.multiply(self._fr_rv, self._eff_fr, self._act_fr)  # = friction_current
