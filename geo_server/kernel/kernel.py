"""Fast, data-oriented compensation kernel (SPEC §3, §6, §11).

Same semantics as `geo_server.kernel.reference.ReferenceKernel` (the readable statement
and the test oracle), computed for all axes at once with numpy.

Why it is shaped like this: with the manual's table sizes the arithmetic per cycle is
tiny; the cost is the *number* of numpy calls (~0.35 µs each plus Python overhead). So
the cycle is a fixed, short sequence of whole-array calls, and everything that can be
decided from the configuration is decided in `_setup` (construction and reload):

* the inputs are copied once into one source vector `S = [pos | vel | acc | trunc(rev)
  | 0 | 1 | direction]`; every input that only needs this cycle's commands (crosstalk
  state, friction sign, 1-D queries, plane, mode 3) comes from S with ONE `take` into
  `G`, then one `sign`, one subtract and one divide (0 and 1 as neutral values);
* LSEC's complex query (row id 3j + 1 ± direction, position) is one gather from S and
  one add into the query's (real, imag) pairs;
* `step` is one flat sequence of numpy calls: no helper calls in the hot path;
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

from geo_server.kernel.common import (
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
    initial_direction,
    initial_selection,
)
from geo_server.kernel.sin2 import Sin2Filter
from geo_server.kernel.tables import Lookup, MergedTable
from geo_server.kernel.triangulation import INSIDE_EPS, Triangulation, evaluate, triangulate
from geo_server.model import CompKind, MachineConfig

try:  # the clip ufunc itself (np.clip adds a Python wrapper); = min(max(x, lo), hi)
    _clip = np._core.umath.clip
except AttributeError:  # numpy < 2
    _clip = np.core.umath.clip

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
        # backlash and temperature parameters, laid out so that both targets take one
        # subtract and one multiply: rows [init dir, lose/2, coefficient·1e-6, (unused),
        # coefficient, offset_0, position_0]
        self._bt = bt = np.zeros((7, n))
        self._init_dir, self._half_lose, self._tc6 = bt[0], bt[1], bt[2]
        self._tempc = bt[4:7]
        for row, attr in enumerate(TEMPC_ATTRS):  # coefficient, offset_0, position_0
            self._tempc[row] = [getattr(x, attr) for x in p]
        # coefficient·1e-6, as the reference groups it
        np.multiply(self._tempc[0], 1e-6, out=self._tc6)
        self._bt_sub, self._bt_mul = bt[0:7:6], bt[1:3]  # (init, position_0), (lose/2, c6)
        self._bt_t = np.zeros((2, n))
        self._path = np.full(n, np.inf)  # path since the last reversal (friction)
        self._dpos = np.zeros(n)  # |pos − previous pos| (friction path)
        self._first = True
        self._pending = np.zeros((n, 7), dtype=bool)
        self._pending_any = False
        self._ring = np.zeros((RING, n))  # friction delay line, one row per cycle
        self._ring_flat = self._ring.reshape(-1)
        self._ring_pos = 0
        # source vector S = [pos | vel | acc | trunc(rev) | 0 | 1 | direction]
        self._S = np.zeros(5 * n + 2)
        self._S[4 * n + 1] = 1.0
        self._dir = self._S[4 * n + 2 :]  # ±1: direction held at standstill
        self._dir[:] = [initial_direction(x.anwahl_losekomp) for x in p]
        self._S4 = self._S[: 4 * n]  # the inputs, copied with one concatenate
        self._Spos, self._Svel = self._S[:n], self._S[n : 2 * n]
        # (direction, position) as one [2, n] view of S
        self._dp = np.lib.stride_tricks.as_strided(
            self._S[4 * n + 2 :], shape=(2, n), strides=(-(4 * n + 2) * 8, 8), writeable=False
        )
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
        assert (BC, TEMP) == (0, 1)
        self._tgt_bt = t[:, 0:2].T  # (backlash, temperature) targets as [2, n]
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
        self._init_dir[:] = _f64([initial_direction(x.anwahl_losekomp) for x in p])
        self._half_lose[:] = _f64([x.lose for x in p]) / 2.0
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
        self._build_gather()
        self._fr_n = bool(self._n_l1 and len(self._fr_slots))
        self._flags = (
            self._nxt,
            self._n_l1,
            self._n_plane,
            self._n_tri,
            bool(len(self._g_sg)),
            bool(len(self._g_q)),
            self._any_fac,
        )
        self._not_fr = np.ones(7)
        self._not_fr[FRICT] = 0.0

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
        self._xt_code = np.zeros(len(rows))
        self._xt_idx = np.zeros(len(rows), dtype=np.int64)
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
        self._pl_tmp = np.zeros((2, P))
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
        self._tri_xy1 = np.zeros((T, 3))  # (x, y, 1) per row (a view of G, see gather)
        # λ[j, v·G + g] = (a, b, c)[j, v, g] · (x, y, 1)[j]: one stacked matmul
        self._tri_H = np.ascontiguousarray(H.reshape(T, 3 * G, 3))
        self._tri_lamm = np.zeros((T, 3 * G, 1))
        self._tri_lam = self._tri_lamm.reshape(T, 3, G)
        self._tri_l0, self._tri_l1, self._tri_l2 = (self._tri_lam[:, v] for v in range(3))
        self._tri_min = np.zeros((T, G))
        self._tri_in = np.zeros((T, G), dtype=bool)
        self._tri_sel = np.zeros(T, dtype=np.int64)
        self._tri_off_now = np.zeros(T, dtype=np.int64)
        self._tri_coef = np.zeros((T, 3))
        self._tri_coef1 = self._tri_coef[:, None, :]
        self._V_tri11 = self._V_tri.reshape(T, 1, 1)

    def _build_lsec(self, axes: list, rows: list[int], modulo, period) -> None:
        self._n_lsec = L = len(rows)
        if not L:
            return
        ls = [axes[i].comp.lsec for i in rows]
        tables = []
        for x in ls:  # rows 3j (neg; = pos when unilateral), 3j + 1 (unused), 3j + 2 (pos)
            tables.append((x.setpoint, x.neg if x.bilateral else x.pos))
            tables.append((np.zeros(1), np.zeros(1)))
            tables.append((x.setpoint, x.pos))
        # the applied offset is −Δs: negate the values once here
        tables = [(np.asarray(k, dtype=float), -np.asarray(v, dtype=float)) for k, v in tables]
        self._ls = Lookup(MergedTable(tables), np.arange(L, dtype=float) * 3 + 1)
        self._ls_slots = _i64(rows)
        # one gather of (direction, command position) and one add of (3j + 1, cross +
        # plane) give the complex query (row id 3j + 1 ± 1, position) directly
        n = self.n
        self._ls_src = np.stack([self._ls_slots + 4 * n + 2, self._ls_slots], axis=1)
        self._ls_g = np.zeros((L, 2))
        self._ls_add = np.zeros((L, 2))
        self._ls_add[:, 0] = np.arange(L, dtype=float) * 3 + 1
        self._ls_t = self._ls_add[:, 1]
        self._ls_qf = self._ls._qc_flat
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
        self._ls_d, self._ls_val = np.zeros(L), np.zeros(L)

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

    def ramping(self, slot: int) -> bool:
        """True while a sin² ramp of the axis has cycles left or an event is pending."""
        f = self._filter
        return bool(np.any(f.kidx[slot] != f.end[slot]) or self._pending[slot].any())

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
            for row, attr in enumerate(TEMPC_ATTRS):
                if getattr(po, attr) != getattr(pn, attr):
                    self._tempc[row, i] = getattr(pn, attr)
        np.multiply(self._tempc[0], 1e-6, out=self._tc6)
        self._pending[:] = True
        self._pending_any = True

    def _build_gather(self) -> None:
        """One gather for every input that only needs this cycle's commands.

        G = [xt vel | xt acc | friction vel | 1-D queries | plane (u, v) | mode 3 (x, y, 1)]
        is taken from S with one `take`; one `sign` serves the first three parts, one
        subtract and one divide (neutral 0 and 1 elsewhere) the last three.
        """
        n, nxt, F = self.n, self._nxt, len(self._fr_slots) if self._n_l1 else 0
        L1, P, T = self._n_l1, self._n_plane, self._n_tri
        src, sub, div, per, wrap = [], [], [], [], []
        if nxt:
            src += list(self._xt_src.reshape(-1))
        if F:
            src += [n + int(i) for i in self._fr_slots]
        ns = len(src)
        if L1:
            src += list(self._l1_src)
            sub += [0.0] * L1
            div += list(self._l1_div)
            per += list(self._l1_per)
            wrap += list(self._l1_wrap)
        if P:
            src += list(self._pl_src.reshape(-1))
            sub += list(self._pl_s0.reshape(-1))
            div += list(self._pl_iv.reshape(-1))
            per += list(self._pl_per.reshape(-1))
            wrap += list(self._pl_wrap.reshape(-1))
        nw = len(wrap)
        if T:
            src += list(self._tri_src.reshape(-1))
            sub += [0.0] * (3 * T)
            div += [1.0] * (3 * T)
        self._g_src = _i64(src)
        self._G = G = np.zeros(len(src))
        self._g_sign_in = G[:ns]
        self._g_sg = sg = np.zeros(ns)
        self._g_q = G[ns:]
        self._g_sub, self._g_div = _f64(sub), _f64(div)
        self._g_w = G[ns : ns + nw]
        self._g_per, self._g_wrap = _f64(per), np.array(wrap, dtype=bool)
        self._g_any_wrap = bool(self._g_wrap.any())
        self._g_tmp = np.zeros(nw)
        o = ns
        if L1:
            self._l1_raw = G[o : o + L1]
            o += L1
        if P:
            self._pl_u = G[o : o + 2 * P].reshape(2, P)
            o += 2 * P
        if T:
            self._tri_xy1 = G[o : o + 3 * T].reshape(T, 3)
            self._tri_xy1c = self._tri_xy1[:, :, None]
        if F:
            self._fr_s = sg[2 * nxt :]
        if nxt:
            # per sign code: (sign(a)·1/|a_ref|/UNITS_PER_MM, mode-3 region block, 1-D row)
            # so that a·r = |a|/|a_ref| in mm/s² without an abs and a divide
            self._xt_sg2 = sg[: 2 * nxt].reshape(2, nxt)
            self._xt_a = G[nxt : 2 * nxt]
            sa = np.tile(np.array([-1.0, 0.0, 1.0] * 3), nxt)
            tab = np.zeros((nxt * 9, 3))
            tab[:, 0] = sa * self._xt_inv / UNITS_PER_MM
            if T:
                tab[: T * 9, 1] = self._tri_off
            if L1:
                tab[:, 2] = self._lin_rowid
            self._xt_tab = tab
            self._xt_3 = np.zeros((nxt, 3))
            self._xt_r = self._xt_3[:, 0]
            self._tri_off_now = self._xt_3[:T, 1]
            self._xt_lin_now = self._xt_3[T:, 2]
            self._xt_w31 = np.array([3.0, 1.0])
        self._xt_has_lin = bool(L1 and nxt > T)

    # ------------------------------------------------------------------ the cycle

    def step(
        self,
        cmd_pos: np.ndarray,
        cmd_vel: np.ndarray,
        cmd_acc: np.ndarray,
        homed: np.ndarray,
        reversal_in: np.ndarray,
    ) -> None:
        """One GEO cycle for every axis (SPEC §5 step 3).

        Written as one flat sequence of numpy calls on local names (attribute lookups
        and helper calls cost as much as a small numpy call here).
        """
        mul, add, subtract = np.multiply, np.add, np.subtract
        copyto, minimum = np.copyto, np.minimum
        tgt, act, eff, ev = self.target, self.actual, self.effective, self._event
        prev, t1, pos = self._prev, self._t1, self._Spos
        copyto(prev, act)
        if self._first:
            copyto(pos, cmd_pos)
            self._first = False
        dpos = self._dpos
        subtract(cmd_pos, pos, dpos)  # pos still holds the previous cycle's
        np.concatenate((cmd_pos, cmd_vel, cmd_acc, reversal_in), out=self._S4)
        if reversal_in.dtype.kind != "i":
            np.trunc(self._Srev, out=self._Srev)  # the reference's int(): −0.5 → 0

        # direction: sign of the command velocity, last one held at standstill (SPEC §3).
        # d is always ±1, so "s ≠ 0 and s ≠ d" is s·d < 0, and the update is a flip.
        s, rev, d = self._s, self._rev, self._dir
        np.sign(self._Svel, s)
        mul(s, d, t1)
        np.less(t1, 0.0, rev)
        np.negative(d, out=d, where=rev)

        # effective = selected ∧ configured ∧ homing preconditions; events on change
        copyto(self._homed_in, homed)
        hb, ne = self._hb, self._neweff
        self._homed.take(self._h, out=hb)
        np.logical_and(hb[0], hb[1], ne)
        np.logical_and(ne, self.selected, ne)
        np.not_equal(ne, eff, ev)
        copyto(eff, ne)
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
        # temperature: offset_0 + coefficient·1e-6·(s − position_0) (000 §3.1)
        bt = self._bt_t
        subtract(self._dp, self._bt_sub, bt)  # (d − init, s − position_0)
        if self._any_modulo:
            np.mod(pos, self._mod_period, t1)
            copyto(t1, pos, where=self._not_modulo)
            subtract(t1, self._tempc[2], bt[1])
        mul(bt, self._bt_mul, self._tgt_bt)
        add(self._tempc[1], self._tgt_temp, self._tgt_temp)

        # cross, plane, crosstalk, friction base: all into V, then one scatter
        (nxt, n_l1, n_plane, n_tri, any_sign, nq, any_fac) = self._flags
        if nq or any_sign:
            G = self._G
            self._S.take(self._g_src, out=G)
            if any_sign:
                np.sign(self._g_sign_in, self._g_sg)
            if nq:
                q = self._g_q
                if self._g_any_wrap:  # modulo master: position wrapped into [0, period)
                    gw, gt = self._g_w, self._g_tmp
                    np.mod(gw, self._g_per, gt)
                    copyto(gw, gt, where=self._g_wrap)
                subtract(q, self._g_sub, q)
                np.divide(q, self._g_div, q)
        if nxt:
            # crosstalk (000 §4.6 p.84): column by accelerate/decelerate × direction and
            # the clamped ratio |a|/|a_ref|, for every new-model row (modes 1, 2, 3)
            code, idx = self._xt_code, self._xt_idx
            np.dot(self._xt_w31, self._xt_sg2, out=code)
            add(code, self._xt_rowoff, idx, casting="unsafe")
            self._xt_tab.take(idx, axis=0, out=self._xt_3)
            fx = self._fac_xt
            mul(self._xt_a, self._xt_r, fx)
            minimum(fx, 1.0, out=fx)  # clamp beyond the reference (SPEC §12)
            if self._xt_has_lin:
                copyto(self._l1_rowid_lin, self._xt_lin_now)
        if n_l1:
            # cross (000 §4.2), friction base (§4.5), crosstalk modes 1/2 and old model
            # (§4.6) and the friction pre-reversal weight: one merged lookup
            lk = self._l1
            copyto(lk.q, self._l1_raw)
            lk.seg_table.take(lk.keys.searchsorted(lk.qc, "right"), axis=0, out=lk.seg)
            lt = lk.tmp
            subtract(lk.q, lk.x0, lt)
            mul(lt, lk.slope, lt)
            add(lt, lk.y0, self._V_l1)
            if self._fr_n:  # friction: sign(v)·scaling_factor/1000
                mul(self._fr_s, self._fr_scale, self._fac_fr)
        if n_plane:
            # plane (000 §4.3): bilinear on table[j][i] (j master 2, i master 1), clamped
            # u = clamp((q − start)/interval, 0, last); cell = min(floor(u), last − 1)
            u, fl = self._pl_u, self._pl_f
            _clip(u, 0.0, self._pl_last, out=u)
            np.floor(u, fl)
            minimum(fl, self._pl_lim, out=fl)
            subtract(u, fl, self._pl_frac)
            subtract(1.0, self._pl_frac, self._pl_gfrac)
            # weights [j, i] = (1 − fv | fv)_j · (1 − fu | fu)_i
            pw = self._pl_w
            mul(self._pl_V, self._pl_U, pw)
            # corner indices: base + j0·stride + i0 + corner offset
            pt = self._pl_tmp
            mul(fl, self._pl_sw, pt)
            add(pt[0], pt[1], self._pl_k00)
            pk, pc = self._pl_k, self._pl_c
            add(self._pl_k00b, self._pl_base4, pk, casting="unsafe")
            self._pl_tab.take(pk, out=pc)
            mul(pw, pc, pw)
            add.reduce(self._pl_w4, axis=0, out=self._V_plane)
        if n_tri:
            # crosstalk mode 3 (000 §4.6 p.84, SPEC §12): first region containing (x, y),
            # then its affine value in the selected column (× ratio via the factor vector)
            xy1 = self._tri_xy1
            # λ = a·x + b·y + c for every half-plane of every region (rounding may differ
            # from the reference's order by an ulp: the value is continuous across
            # region boundaries, so this moves results by ≪ 1e-9)
            np.matmul(self._tri_H, self._tri_xy1c, out=self._tri_lamm)
            tmin, tin, sel = self._tri_min, self._tri_in, self._tri_sel
            minimum(self._tri_l0, self._tri_l1, out=tmin)  # cheaper than a reduce
            minimum(tmin, self._tri_l2, out=tmin)
            np.greater_equal(tmin, -INSIDE_EPS, tin)
            tin.argmax(axis=1, out=sel)  # first region wins
            add(sel, self._tri_off_now, sel, casting="unsafe")
            coef = self._tri_coef
            self._tri_val.take(sel, axis=0, out=coef)
            np.matmul(self._tri_coef1, self._tri_xy1c, out=self._V_tri11)  # (α, β, γ)·(x, y, 1)
            vt = self._V_tri
            for j, t, cols in self._tri_slow:
                col = int(self._tri_colv[self._xt_idx[j]])
                vt[j] = evaluate(t, cols[col], xy1[j, 0], xy1[j, 1])
        V = self._V
        if any_fac:
            mul(V, self._fac, V)
        self._tflat.put(self._V_flat, self._V_tgt)
        mul(tgt, eff, tgt)

        # sin² filter of every column (LSEC again below, once its target is known):
        # k ← offset(N) on an event, then k ← min(k + 1, offset(N) + N) (one successor
        # table), w = cos²(πk/(2N)); J ← target − out where event; out = target − J·w
        f = self._filter
        kidx, w, jump, t7 = f.kidx, f.w, f.jump, self._t7
        copyto(kidx, f.off, where=ev)
        f.succ.take(kidx, out=kidx)
        f.table.take(kidx, out=w)
        subtract(tgt, prev, t7)
        copyto(jump, t7, where=ev)
        mul(jump, w, t7)
        subtract(tgt, t7, act)

        if self._n_lsec:
            # LSEC (000 §4.4): −Δs at command (+ cross + plane output), pos/neg by
            # direction; then its sin² pass (reversal events were set with the others)
            lk = self._ls
            cp, t = self._ls_cpv, self._ls_t
            self._aflat.take(self._ls_cp, out=cp)
            add(cp[0], cp[1], t)
            if not self._ls_all_wc:  # set_pos_without_comp: command position only
                mul(t, self._ls_wc, t)
            self._S.take(self._ls_src, out=self._ls_g)
            add(self._ls_g, self._ls_add, self._ls_qf)  # (row id, position)
            if self._ls_any_wrap:  # modulo table: wrap into [x0, x0 + period)
                lq, lt = lk.q, self._ls_d
                subtract(lq, self._ls_x0, lt)
                np.mod(lt, self._ls_per, lt)
                add(lt, self._ls_x0, lt)
                copyto(lq, lt, where=self._ls_wrap)
            lk.seg_table.take(lk.keys.searchsorted(lk.qc, "right"), axis=0, out=lk.seg)
            lt = lk.tmp
            subtract(lk.q, lk.x0, lt)
            mul(lt, lk.slope, lt)
            tl = self._tgt_lead
            if self._ls_all:  # every axis has LSEC: straight into the target column
                add(lt, lk.y0, tl)
            else:
                add(lt, lk.y0, self._ls_val)
                self._tflat.put(self._ls_flat, self._ls_val)
            mul(tl, self._eff_lead, tl)
            tld, pl = self._t_lead, self._prev_lead
            subtract(tl, pl, tld)
            copyto(self._f_j_lead, tld, where=self._ev_lead)
            mul(self._f_j_lead, self._f_w_lead, tld)
            subtract(tl, tld, self._act_lead)

        # friction (000 §4.5): reversal weights and the delay line, for every axis (the
        # non-friction rows carry zeros, as in the reference's per-axis delay lines)
        path = self._path
        copyto(path, 0.0, where=rev)  # path since the last reversal
        np.abs(dpos, dpos)
        add(path, dpos, path)
        wpos = self._ring_pos
        self._ring_pos = wpos + 1 if wpos < RING - 1 else 0
        # this cycle's value, into the delay line: sign(v)·scale·table(|v|) (0 when not
        # effective), × the pre-reversal and the post-reversal weight
        cur = self._ring[wpos]
        if self._fr_n:
            # before the reversal: r/(lookahead + 1) while 0 ≤ r ≤ lookahead
            wpre = self._wpre
            wpre.put(self._fr_slots, self._V_wpre)
            mul(self._tgt_fr, wpre, cur)
        else:
            copyto(cur, self._tgt_fr)
        if self._fr_any_pd:  # after the reversal: build-up over position_delay of path
            wp = self._wpost
            np.divide(path, self._fr_pd, wp, where=self._fr_has_pd)
            minimum(wp, 1.0, out=wp)
            mul(cur, wp, cur)
        # delay line: read `delay_cycles` back; output only while effective
        rv = self._fr_rv
        self._ring_flat.take(self._fr_ridx[wpos], out=rv)
        mul(rv, self._eff_fr, self._act_fr)  # = friction_current

        subtract(act, prev, self.delta)
        np.dot(act, self._not_fr, out=self.total_offset)  # Σ columns but friction
