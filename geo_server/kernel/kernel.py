"""Fast, data-oriented compensation kernel (SPEC §3, §6, §11).

Same semantics as `geo_server.kernel.reference.ReferenceKernel` (the readable statement
and the test oracle), computed for all axes at once with numpy:

* every table is preloaded at construction into flat arrays (`tables.BatchedInterp`:
  one `np.searchsorted` per table kind serves every axis);
* each compensation kind works on the *rows* (axes) that have it: slot index arrays
  gather inputs and scatter results through flat indices of the `[n, 7]` outputs;
* all scratch arrays are preallocated; `step` uses `out=` arguments throughout. The only
  per-cycle allocations are the few index arrays numpy returns from `searchsorted`.

Column order (`COMP_ORDER`): BACKLASH, TEMP, CROSS, PLANE, LEAD, FRICT, CROSSTALK.
"""

from __future__ import annotations

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
from geo_server.kernel.sin2 import Sin2Filter
from geo_server.kernel.tables import BatchedInterp
from geo_server.kernel.triangulation import INSIDE_EPS, triangulate

UNITS_PER_MM = 10_000.0
UNITS_PER_UM = 10.0
RING = 249  # friction delay line length: delay_cycles < 249 (000 p.79)


class _Rows:
    """Gather/scatter helpers for the axes (rows) that use one compensation kind."""

    def __init__(self, slots: list[int], col: int) -> None:
        self.slots = np.array(slots, dtype=np.int64)
        self.flat = self.slots * 7 + col  # index into the raveled [n, 7] arrays
        self.n = len(slots)


def _wrap(
    q: np.ndarray, start: np.ndarray | float, period: np.ndarray, mask: np.ndarray, tmp: np.ndarray
) -> None:
    """q ← start + (q − start) mod period where mask (in place)."""
    np.subtract(q, start, out=tmp)
    np.mod(tmp, period, out=tmp)
    np.add(tmp, start, out=tmp)
    np.copyto(q, tmp, where=mask)


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
        self.target = np.zeros((n, 7))
        self.actual = np.zeros((n, 7))
        self.delta = np.zeros((n, 7))
        self.effective = np.zeros((n, 7), dtype=bool)
        self.friction_current = np.zeros(n)
        self.total_offset = np.zeros(n)
        self._prev = np.zeros((n, 7))
        self._prev_eff = np.zeros((n, 7), dtype=bool)
        self._pending = np.zeros((n, 7), dtype=bool)
        self._event = np.zeros((n, 7), dtype=bool)
        self._tempc = np.zeros((3, n))
        p = [cfg.axes[int(a)].params for a in self.axis_numbers]
        self._tempc[0] = [x.temp_comp_coefficient for x in p]
        self._tempc[1] = [x.temp_comp_offset_0 for x in p]
        self._tempc[2] = [x.temp_comp_position_0 for x in p]
        self._dir = np.array([initial_direction(x.anwahl_losekomp) for x in p])
        self._path = np.full(n, np.inf)
        self._prev_pos = np.zeros(n)
        self._first = True
        # scratch [n]
        self._s = np.zeros(n)
        self._t1 = np.zeros(n)
        self._t2 = np.zeros(n)
        self._b1 = np.zeros(n, dtype=bool)
        self._rev = np.zeros(n, dtype=bool)
        self._homed = np.ones(n + 1, dtype=bool)  # slot n = "no homing needed"
        self._hb1 = np.zeros((n, 7), dtype=bool)
        self._hb2 = np.zeros((n, 7), dtype=bool)
        self._ring_pos = 0
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
        ncyc = np.array([filter_cycles(ax) for ax in axes], dtype=float).reshape(n, 7)
        if hasattr(self, "_fa"):
            self._fa.set_n(ncyc[:, 0:4])
            self._fb.set_n(ncyc[:, 4:7])
        else:
            self._fa = Sin2Filter(ncyc[:, 0:4])
            self._fb = Sin2Filter(ncyc[:, 4:7])
        self._init_dir = np.array([initial_direction(x.anwahl_losekomp) for x in p])
        self._lose = np.array([float(x.lose) for x in p])
        self._modulo = np.array([x.modulo for x in p], dtype=bool)
        self._period = np.array([x.modulo_period for x in p], dtype=float)
        ok = np.zeros((n, 7), dtype=bool)
        ok[:, BC] = [x.anwahl_losekomp != 0 and x.lose != 0 for x in p]
        ok[:, TEMP] = True
        # homing requirements as indices into self._homed (n = none)
        h1 = np.full((n, 7), n, dtype=np.int64)
        h2 = np.full((n, 7), n, dtype=np.int64)
        h1[:, TEMP] = np.arange(n)  # 000 §3.2: homed
        h1[:, LEAD] = np.arange(n)  # 000 §5.3 item 2
        cross, plane, lsec, frict, lin, tri, old = [], [], [], [], [], [], []
        for i, ax in enumerate(axes):
            comp = ax.comp
            if comp is None:
                continue
            c = comp.cross
            if c is not None and c.valid and c.master_ax_nr in slot and len(c.setpoint):
                ok[i, CROSS] = True
                h1[i, CROSS] = slot[c.master_ax_nr]
                cross.append(i)
            pl = comp.plane
            if (
                pl is not None
                and pl.valid
                and pl.master1_ax_nr in slot
                and pl.master2_ax_nr in slot
                and pl.table.size
            ):
                ok[i, PLANE] = True
                h1[i, PLANE] = slot[pl.master1_ax_nr]
                h2[i, PLANE] = slot[pl.master2_ax_nr]
                plane.append(i)
            ls = comp.lsec
            if ls is not None and ls.valid and len(ls.setpoint):
                ok[i, LEAD] = True
                lsec.append(i)
            f = comp.frict
            if f is not None and f.valid and f.mode == 3 and len(f.vin):
                ok[i, FRICT] = True
                frict.append(i)
            x = comp.crosstalk
            if x is not None and x.valid and x.master_dyn_ax_nr in slot:
                if x.dialect == "old":
                    if len(x.acc_table):
                        old.append(i)
                        ok[i, CROSSTALK] = True
                else:
                    corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
                    if corr.shape[0] == 0:
                        continue
                    if x.mode == 3:
                        if x.master_pos1_ax_nr in slot and x.master_pos2_ax_nr in slot:
                            tri.append(i)
                            ok[i, CROSSTALK] = True
                    elif x.mode != 2 or x.master_pos1_ax_nr in slot:
                        lin.append(i)
                        ok[i, CROSSTALK] = True
        self._ok, self._h1, self._h2 = ok, h1, h2
        self._build_cross(axes, cross)
        self._build_plane(axes, plane)
        self._build_lsec(axes, lsec)
        self._build_frict(axes, frict)
        self._build_xt_lin(axes, lin)
        self._build_xt_tri(axes, tri)
        self._build_xt_old(axes, old)

    def _master_wrap(self, masters: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._modulo[masters].copy(), self._period[masters].copy()

    def _build_cross(self, axes: list, rows: list[int]) -> None:
        r = self._cross = _Rows(rows, CROSS)
        if not r.n:
            return
        cs = [axes[i].comp.cross for i in rows]
        r.master = np.array([self._slot[c.master_ax_nr] for c in cs], dtype=np.int64)
        r.mod, r.period = self._master_wrap(r.master)
        r.table = BatchedInterp([c.setpoint for c in cs], [[c.correction] for c in cs])
        r.q, r.tmp, r.val = np.zeros(r.n), np.zeros(r.n), np.zeros(r.n)

    def _build_plane(self, axes: list, rows: list[int]) -> None:
        r = self._plane = _Rows(rows, PLANE)
        if not r.n:
            return
        ps = [axes[i].comp.plane for i in rows]
        r.m1 = np.array([self._slot[x.master1_ax_nr] for x in ps], dtype=np.int64)
        r.m2 = np.array([self._slot[x.master2_ax_nr] for x in ps], dtype=np.int64)
        r.mod1, r.per1 = self._master_wrap(r.m1)
        r.mod2, r.per2 = self._master_wrap(r.m2)
        r.s1 = np.array([x.start_position_master1 for x in ps], dtype=float)
        r.s2 = np.array([x.start_position_master2 for x in ps], dtype=float)
        r.i1 = np.array([x.interval1 for x in ps], dtype=float)
        r.i2 = np.array([x.interval2 for x in ps], dtype=float)
        tabs = [np.atleast_2d(np.asarray(x.table, dtype=float)) for x in ps]
        r.last1 = np.array([t.shape[1] - 1 for t in tabs], dtype=float)
        r.last2 = np.array([t.shape[0] - 1 for t in tabs], dtype=float)
        r.lim1 = np.maximum(r.last1 - 1, 0)
        r.lim2 = np.maximum(r.last2 - 1, 0)
        r.step1 = (r.last1 > 0).astype(np.int64)
        r.step2 = (r.last2 > 0).astype(np.int64) * np.array([t.shape[1] for t in tabs])
        r.stride = np.array([t.shape[1] for t in tabs], dtype=np.int64)
        sizes = np.array([t.size for t in tabs], dtype=np.int64)
        r.base = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        r.flat_t = np.concatenate([t.ravel() for t in tabs])
        z = lambda: np.zeros(r.n)  # noqa: E731
        r.q1, r.q2, r.tmp, r.u, r.v, r.fu, r.fv, r.gu, r.gv = (z() for _ in range(9))
        r.c, r.w, r.val = z(), z(), z()
        zi = lambda: np.zeros(r.n, dtype=np.int64)  # noqa: E731
        r.ii, r.jj, r.k00, r.k = zi(), zi(), zi(), zi()

    def _build_lsec(self, axes: list, rows: list[int]) -> None:
        r = self._lsec = _Rows(rows, LEAD)
        if not r.n:
            return
        ls = [axes[i].comp.lsec for i in rows]
        r.bilateral = np.array([x.bilateral for x in ls], dtype=bool)
        r.with_comp = np.array([not x.set_pos_without_comp for x in ls], dtype=bool)
        r.modulo = np.array([x.modulo for x in ls], dtype=bool)
        r.x0 = np.array([float(x.setpoint[0]) for x in ls])
        spans = np.array([float(x.setpoint[-1] - x.setpoint[0]) for x in ls])
        r.period = np.where(self._modulo[r.slots], self._period[r.slots], spans)
        r.modulo &= r.period > 0
        r.period = np.where(r.period > 0, r.period, 1.0)
        r.table = BatchedInterp(
            [x.setpoint for x in ls],
            [[x.pos, x.neg if x.bilateral else x.pos] for x in ls],
        )
        r.q, r.tmp, r.val = np.zeros(r.n), np.zeros(r.n), np.zeros(r.n)
        r.var = np.zeros(r.n, dtype=np.int64)
        r.b = np.zeros(r.n, dtype=bool)
        r.eff = np.zeros(r.n, dtype=bool)
        r.flat_c = r.slots * 7 + CROSS
        r.flat_p = r.slots * 7 + PLANE

    def _build_frict(self, axes: list, rows: list[int]) -> None:
        r = self._frict = _Rows(rows, FRICT)
        fs = [axes[i].comp.frict for i in rows]
        delays = [min(int(f.delay_cycles), RING - 1) for f in fs]
        # one delay line of the manual's maximum length (delay_cycles < 249, P-COMP-00058)
        # for every axis: it survives a reload that changes delay_cycles unchanged
        if not hasattr(self, "_ring"):
            self._ring = np.zeros((self.n, RING))
        self._ring_size = RING
        if not r.n:
            return
        r.scale = np.array([f.scaling_factor / 1000.0 for f in fs])
        r.look = np.array([f.reversal_lookahead for f in fs], dtype=float)
        r.look_div = r.look + 1.0
        r.pd = np.array([float(f.position_delay) for f in fs])
        r.has_pd = r.pd > 0
        r.pd_safe = np.where(r.has_pd, r.pd, 1.0)
        r.delay = np.array(delays, dtype=np.int64)
        r.table = BatchedInterp([f.vin for f in fs], [[f.out] for f in fs])
        z = lambda: np.zeros(r.n)  # noqa: E731
        r.v, r.q, r.val, r.w, r.tmp, r.cur = (z() for _ in range(6))
        r.b, r.b2, r.eff = (np.zeros(r.n, dtype=bool) for _ in range(3))
        r.rev = np.zeros(r.n)
        r.ridx = np.zeros(r.n, dtype=np.int64)
        r.widx = np.zeros(r.n, dtype=np.int64)

    def _xt_common(self, r: _Rows, xs: list) -> None:
        r.dyn = np.array([self._slot[x.master_dyn_ax_nr] for x in xs], dtype=np.int64)
        r.veldep = np.array([x.velocity_dependent for x in xs], dtype=np.int64)
        r.inv_acc = np.array([1.0 / abs(x.acceleration) if x.acceleration else 0.0 for x in xs])
        r.inv_dec = np.array([1.0 / abs(x.deceleration) if x.deceleration else 0.0 for x in xs])
        z = lambda: np.zeros(r.n)  # noqa: E731
        r.a, r.v, r.ratio, r.inv, r.val = (z() for _ in range(5))
        r.col = np.zeros(r.n, dtype=np.int64)
        r.acc_b, r.neg_b, r.tb = (np.zeros(r.n, dtype=bool) for _ in range(3))

    def _build_xt_lin(self, axes: list, rows: list[int]) -> None:
        """Crosstalk modes 1 and 2: reference correction over ax_1 (mode 1: one point)."""
        r = self._xt_lin = _Rows(rows, CROSSTALK)
        if not r.n:
            return
        xs = [axes[i].comp.crosstalk for i in rows]
        self._xt_common(r, xs)
        keys, vals = [], []
        for x in xs:
            corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
            if x.mode == 1:
                keys.append(np.zeros(1))
                vals.append([corr[:1, c] for c in range(4)])
            else:
                ax1 = np.asarray(x.ax_1, dtype=float)[: corr.shape[0]]
                order = np.argsort(ax1, kind="stable")
                keys.append(ax1[order])
                vals.append([corr[order, c] for c in range(4)])
        r.table = BatchedInterp(keys, vals)
        r.mode2 = np.array([x.mode == 2 for x in xs], dtype=bool)
        r.p1 = np.array([self._slot.get(x.master_pos1_ax_nr, 0) for x in xs], dtype=np.int64)
        r.q = np.zeros(r.n)

    def _build_xt_tri(self, axes: list, rows: list[int]) -> None:
        """Crosstalk mode 3: Delaunay piecewise-linear, nearest hull point outside."""
        r = self._xt_tri = _Rows(rows, CROSSTALK)
        if not r.n:
            return
        xs = [axes[i].comp.crosstalk for i in rows]
        self._xt_common(r, xs)
        r.p1 = np.array([self._slot[x.master_pos1_ax_nr] for x in xs], dtype=np.int64)
        r.p2 = np.array([self._slot[x.master_pos2_ax_nr] for x in xs], dtype=np.int64)
        tris = []
        npts = 1
        for x in xs:
            corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
            m = min(len(x.ax_1), len(x.ax_2), corr.shape[0])
            pts = tuple((float(x.ax_1[i]), float(x.ax_2[i])) for i in range(m))
            tris.append((triangulate(pts), corr[:m]))
            npts = max(npts, m)
        nt = max(1, max(len(t.triangles) for t, _ in tris))
        ne = max(len(t.edges) for t, _ in tris)
        R = r.n
        r.npts = npts
        r.A = np.zeros((R, nt, 3))
        r.B = np.zeros((R, nt, 3))
        r.C = np.full((R, nt, 3), -1.0)  # rows without triangles: never inside
        r.V = np.zeros((R, nt, 3), dtype=np.int64)
        r.ex = np.zeros((5, R, ne))
        r.ea = np.zeros((R, ne), dtype=np.int64)
        r.eb = np.zeros((R, ne), dtype=np.int64)
        r.vals = np.zeros((R, npts, 4))
        for k, (t, corr) in enumerate(tris):
            r.vals[k, : len(corr)] = corr
            for j in range(nt):  # pad by repeating triangle 0 (first match wins)
                if not t.triangles:
                    break
                jj = j if j < len(t.triangles) else 0
                for v in range(3):
                    r.A[k, j, v], r.B[k, j, v], r.C[k, j, v] = t.bary[jj][v]
                    r.V[k, j, v] = t.triangles[jj][v]
            for j in range(ne):  # pad by repeating edge 0 (first minimum wins)
                jj = j if j < len(t.edges) else 0
                for q in range(5):
                    r.ex[q, k, j] = t.edge_geom[jj][q]
                r.ea[k, j], r.eb[k, j] = t.edges[jj]
        r.vals_flat = r.vals.ravel()
        r.row_base = np.arange(R, dtype=np.int64) * npts
        r.rowT = np.arange(R, dtype=np.int64) * nt
        r.rowE = np.arange(R, dtype=np.int64) * ne
        r.x, r.y = np.zeros(R), np.zeros(R)
        r.lam = np.zeros((R, nt, 3))
        r.lam2 = np.zeros((R, nt, 3))
        r.minl = np.zeros((R, nt))
        r.inside = np.zeros((R, nt), dtype=bool)
        r.tsel = np.zeros(R, dtype=np.int64)
        r.anyin = np.zeros(R, dtype=bool)
        r.es = np.zeros((R, ne))
        r.et = np.zeros((R, ne))
        r.ed = np.zeros((R, ne))
        r.esel = np.zeros(R, dtype=np.int64)
        r.idx = np.zeros(R, dtype=np.int64)
        r.vidx = np.zeros(R, dtype=np.int64)
        r.l, r.g, r.acc1, r.s_e, r.va = (np.zeros(R) for _ in range(5))

    def _build_xt_old(self, axes: list, rows: list[int]) -> None:
        r = self._xt_old = _Rows(rows, CROSSTALK)
        if not r.n:
            return
        xs = [axes[i].comp.crosstalk for i in rows]
        r.dyn = np.array([self._slot[x.master_dyn_ax_nr] for x in xs], dtype=np.int64)
        keys, vals = [], []
        for x in xs:
            a = np.asarray(x.acc_table, dtype=float)
            order = np.argsort(a, kind="stable")
            keys.append(a[order])
            vals.append([np.asarray(x.corr_table, dtype=float)[order]])
        r.table = BatchedInterp(keys, vals)
        r.a, r.val = np.zeros(r.n), np.zeros(r.n)

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
        self._pending[slot, TEMP] = True

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
        self._pending[:] = True

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
        pos, vel = cmd_pos, cmd_vel
        tgt, act, eff, ev = self.target, self.actual, self.effective, self._event
        s, t1, t2, b1, rev = self._s, self._t1, self._t2, self._b1, self._rev
        np.copyto(self._prev, act)
        np.copyto(self._prev_eff, eff)
        if self._first:
            np.copyto(self._prev_pos, pos)
            self._first = False

        # direction: sign of the command velocity, last one held at standstill (SPEC §3)
        np.sign(vel, out=s)
        np.not_equal(s, 0.0, out=b1)
        np.not_equal(s, self._dir, out=rev)
        np.logical_and(rev, b1, out=rev)
        np.copyto(self._dir, s, where=b1)
        d = self._dir

        # effective = selected ∧ configured ∧ homing preconditions
        self._homed[: self.n] = homed
        self._homed.take(self._h1, out=self._hb1)
        self._homed.take(self._h2, out=self._hb2)
        np.logical_and(self.selected, self._ok, out=eff)
        np.logical_and(eff, self._hb1, out=eff)
        np.logical_and(eff, self._hb2, out=eff)
        np.not_equal(eff, self._prev_eff, out=ev)
        np.logical_or(ev, self._pending, out=ev)
        self._pending[:] = False

        tgt[:] = 0.0
        tflat = tgt.reshape(-1)
        # backlash: 0 in the start-up direction, d·lose after a reversal (000 §2, SPEC §6)
        np.not_equal(d, self._init_dir, out=b1)
        np.multiply(d, self._lose, out=t1)
        np.multiply(t1, b1, out=tgt[:, BC])
        np.logical_and(rev, eff[:, BC], out=b1)
        np.logical_or(ev[:, BC], b1, out=ev[:, BC])
        # temperature: offset_0 + coefficient·1e-6·(s − position_0) (000 §3.1)
        np.copyto(t2, pos)
        _wrap(t2, 0.0, self._period, self._modulo, t1)
        np.subtract(t2, self._tempc[2], out=t2)
        np.multiply(self._tempc[0], 1e-6, out=t1)
        np.multiply(t1, t2, out=t1)
        np.add(self._tempc[1], t1, out=tgt[:, TEMP])
        # cross, plane, crosstalk targets
        self._step_cross(pos, tflat)
        self._step_plane(pos, tflat)
        self._step_xt_lin(pos, vel, cmd_acc, tflat)
        self._step_xt_tri(pos, vel, cmd_acc, tflat)
        self._step_xt_old(cmd_acc, tflat)
        np.multiply(tgt, eff, out=tgt)
        # sin² filter of BC, TEMP, CROSS, PLANE (LSEC needs cross/plane outputs first)
        self._fa.step(tgt[:, 0:4], self._prev[:, 0:4], ev[:, 0:4], act[:, 0:4])
        self._step_lsec(pos, d, rev, tflat)
        self._fb.step(tgt[:, 4:7], self._prev[:, 4:7], ev[:, 4:7], act[:, 4:7])
        self._step_frict(pos, vel, reversal_in, rev)

        np.subtract(act, self._prev, out=self.delta)
        np.add.reduce(act, axis=1, out=self.total_offset)
        np.subtract(self.total_offset, act[:, FRICT], out=self.total_offset)
        np.copyto(self.friction_current, act[:, FRICT])
        np.copyto(self._prev_pos, pos)

    def _step_cross(self, pos: np.ndarray, tflat: np.ndarray) -> None:
        """Cross (000 §4.2): slave offset over the (wrapped) master command position."""
        r = self._cross
        if not r.n:
            return
        pos.take(r.master, out=r.q)
        _wrap(r.q, 0.0, r.period, r.mod, r.tmp)
        r.table.lookup(r.q, r.val)
        tflat[r.flat] = r.val

    def _step_plane(self, pos: np.ndarray, tflat: np.ndarray) -> None:
        """Plane (000 §4.3): bilinear on table[j][i] (j master 2, i master 1), clamped."""
        r = self._plane
        if not r.n:
            return
        pos.take(r.m1, out=r.q1)
        pos.take(r.m2, out=r.q2)
        _wrap(r.q1, 0.0, r.per1, r.mod1, r.tmp)
        _wrap(r.q2, 0.0, r.per2, r.mod2, r.tmp)
        for q, s0, iv, last, lim, cell, frac in (
            (r.q1, r.s1, r.i1, r.last1, r.lim1, r.ii, r.fu),
            (r.q2, r.s2, r.i2, r.last2, r.lim2, r.jj, r.fv),
        ):
            np.subtract(q, s0, out=r.u)
            np.divide(r.u, iv, out=r.u)
            np.maximum(r.u, 0.0, out=r.u)
            np.minimum(r.u, last, out=r.u)
            np.floor(r.u, out=r.v)
            np.minimum(r.v, lim, out=r.v)
            np.subtract(r.u, r.v, out=frac)
            np.copyto(cell, r.v, casting="unsafe")
        # corner (j0, i0) = base + j0·stride + i0
        np.multiply(r.jj, r.stride, out=r.k00)
        np.add(r.k00, r.base, out=r.k00)
        np.add(r.k00, r.ii, out=r.k00)
        np.subtract(1.0, r.fu, out=r.gu)
        np.subtract(1.0, r.fv, out=r.gv)
        # (1−fu)(1−fv)·T00 + fu(1−fv)·T01 + (1−fu)fv·T10 + fu·fv·T11 (reference order)
        r.flat_t.take(r.k00, out=r.c)
        np.multiply(r.gu, r.gv, out=r.w)
        np.multiply(r.w, r.c, out=r.val)
        np.add(r.k00, r.step1, out=r.k)
        r.flat_t.take(r.k, out=r.c)
        np.multiply(r.fu, r.gv, out=r.w)
        np.multiply(r.w, r.c, out=r.w)
        np.add(r.val, r.w, out=r.val)
        np.add(r.k00, r.step2, out=r.k)
        r.flat_t.take(r.k, out=r.c)
        np.multiply(r.gu, r.fv, out=r.w)
        np.multiply(r.w, r.c, out=r.w)
        np.add(r.val, r.w, out=r.val)
        np.add(r.k, r.step1, out=r.k)
        r.flat_t.take(r.k, out=r.c)
        np.multiply(r.fu, r.fv, out=r.w)
        np.multiply(r.w, r.c, out=r.w)
        np.add(r.val, r.w, out=r.val)
        tflat[r.flat] = r.val

    def _step_lsec(
        self, pos: np.ndarray, d: np.ndarray, rev: np.ndarray, tflat: np.ndarray
    ) -> None:
        """LSEC (000 §4.4): −Δs at command (+ cross + plane output), pos/neg by direction."""
        r = self._lsec
        if not r.n:
            return
        aflat = self.actual.reshape(-1)
        pos.take(r.slots, out=r.q)
        aflat.take(r.flat_c, out=r.tmp)
        np.add(r.q, r.tmp, out=r.tmp)
        aflat.take(r.flat_p, out=r.val)
        np.add(r.tmp, r.val, out=r.tmp)
        np.copyto(r.q, r.tmp, where=r.with_comp)
        _wrap(r.q, r.x0, r.period, r.modulo, r.tmp)
        d.take(r.slots, out=r.tmp)
        np.less(r.tmp, 0.0, out=r.b)
        np.logical_and(r.b, r.bilateral, out=r.b)
        np.copyto(r.var, r.b)
        r.table.lookup(r.q, r.val, r.var)
        np.negative(r.val, out=r.val)
        # unfiltered target only where effective; reversal event when bilateral
        self.effective.reshape(-1).take(r.flat, out=r.eff)
        np.multiply(r.val, r.eff, out=r.val)
        tflat[r.flat] = r.val
        rev.take(r.slots, out=r.b)
        np.logical_and(r.b, r.bilateral, out=r.b)
        np.logical_and(r.b, r.eff, out=r.b)
        evflat = self._event.reshape(-1)
        evflat.take(r.flat, out=r.eff)
        np.logical_or(r.eff, r.b, out=r.eff)
        evflat[r.flat] = r.eff

    def _step_frict(
        self, pos: np.ndarray, vel: np.ndarray, reversal_in: np.ndarray, rev: np.ndarray
    ) -> None:
        """Friction (000 §4.5): sign(v)·scale·table(|v|), reversal weights, delay line."""
        # path since the last reversal (all axes; cheap and keeps the state uniform)
        np.copyto(self._path, 0.0, where=rev)
        np.subtract(pos, self._prev_pos, out=self._t1)
        np.abs(self._t1, out=self._t1)
        np.add(self._path, self._t1, out=self._path)
        size = self._ring_size
        wpos = self._ring_pos
        self._ring_pos = (wpos + 1) % size
        self.actual[:, FRICT] = 0.0
        r = self._frict
        if not r.n:
            return
        tflat, aflat = self.target.reshape(-1), self.actual.reshape(-1)
        self.effective.reshape(-1).take(r.flat, out=r.eff)
        vel.take(r.slots, out=r.v)
        np.abs(r.v, out=r.q)
        np.divide(r.q, UNITS_PER_UM, out=r.q)
        r.table.lookup(r.q, r.val)
        np.sign(r.v, out=r.tmp)
        np.multiply(r.tmp, r.scale, out=r.tmp)
        np.multiply(r.tmp, r.val, out=r.cur)
        np.multiply(r.cur, r.eff, out=r.cur)
        tflat[r.flat] = r.cur
        # before the reversal: weight r/(lookahead+1) while 0 ≤ r ≤ lookahead
        np.copyto(self._t2, reversal_in, casting="unsafe")  # int or float input
        self._t2.take(r.slots, out=r.rev)
        np.greater_equal(r.rev, 0.0, out=r.b)
        np.less_equal(r.rev, r.look, out=r.b2)
        np.logical_and(r.b, r.b2, out=r.b)
        np.greater(r.look, 0.0, out=r.b2)
        np.logical_and(r.b, r.b2, out=r.b)
        np.divide(r.rev, r.look_div, out=r.w)
        np.copyto(r.tmp, r.cur)
        np.multiply(r.tmp, r.w, out=r.tmp)
        np.copyto(r.cur, r.tmp, where=r.b)
        # after the reversal: build-up over position_delay of path
        self._path.take(r.slots, out=r.w)
        np.divide(r.w, r.pd_safe, out=r.w)
        np.minimum(r.w, 1.0, out=r.w)
        np.multiply(r.cur, r.w, out=r.tmp)
        np.copyto(r.cur, r.tmp, where=r.has_pd)
        # delay line: write now, read `delay_cycles` back
        np.multiply(r.slots, size, out=r.widx)
        np.subtract(wpos, r.delay, out=r.ridx)
        np.mod(r.ridx, size, out=r.ridx)
        np.add(r.ridx, r.widx, out=r.ridx)
        np.add(r.widx, wpos, out=r.widx)
        ring = self._ring.reshape(-1)
        ring[r.widx] = r.cur
        ring.take(r.ridx, out=r.val)
        np.multiply(r.val, r.eff, out=r.val)
        aflat[r.flat] = r.val

    def _xt_scale(self, r: _Rows, vel: np.ndarray, acc: np.ndarray) -> None:
        """Column (accelerate/decelerate × direction) and clamped ratio |a|/|a_ref|."""
        acc.take(r.dyn, out=r.a)
        np.divide(r.a, UNITS_PER_MM, out=r.a)
        vel.take(r.dyn, out=r.v)
        np.multiply(r.a, r.v, out=r.ratio)
        np.greater_equal(r.ratio, 0.0, out=r.acc_b)  # accelerating: a·v ≥ 0
        np.less(r.v, 0.0, out=r.neg_b)
        np.equal(r.v, 0.0, out=r.tb)
        np.logical_and(r.tb, np.less(r.a, 0.0, out=self._xt_tmp_b(r)), out=r.tb)
        np.logical_or(r.neg_b, r.tb, out=r.neg_b)
        np.multiply(r.neg_b, r.veldep, out=r.col)
        np.logical_not(r.acc_b, out=r.tb)
        np.add(r.col, r.tb, out=r.col)
        np.add(r.col, r.tb, out=r.col)  # decelerate columns are 2 and 3
        np.copyto(r.inv, r.inv_dec)
        np.copyto(r.inv, r.inv_acc, where=r.acc_b)
        np.abs(r.a, out=r.ratio)
        np.multiply(r.ratio, r.inv, out=r.ratio)
        np.minimum(r.ratio, 1.0, out=r.ratio)

    @staticmethod
    def _xt_tmp_b(r: _Rows) -> np.ndarray:
        if not hasattr(r, "tmp_b"):
            r.tmp_b = np.zeros(r.n, dtype=bool)
        return r.tmp_b

    def _step_xt_lin(
        self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, tflat: np.ndarray
    ) -> None:
        """Crosstalk modes 1/2 (000 §4.6 p.84): c_ref (over ax_1) · clamp(|a|/|a_ref|)."""
        r = self._xt_lin
        if not r.n:
            return
        self._xt_scale(r, vel, acc)
        r.q[:] = 0.0
        pos.take(r.p1, out=r.val)
        np.copyto(r.q, r.val, where=r.mode2)
        r.table.lookup(r.q, r.val, r.col)
        np.multiply(r.val, r.ratio, out=r.val)
        tflat[r.flat] = r.val

    def _step_xt_tri(
        self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, tflat: np.ndarray
    ) -> None:
        """Crosstalk mode 3 (000 §4.6 p.84, SPEC §12): Delaunay piecewise-linear."""
        r = self._xt_tri
        if not r.n:
            return
        self._xt_scale(r, vel, acc)
        pos.take(r.p1, out=r.x)
        pos.take(r.p2, out=r.y)
        x3, y3 = r.x[:, None, None], r.y[:, None, None]
        # λ = a·x + b·y + c for every triangle vertex
        np.multiply(r.A, x3, out=r.lam)
        np.multiply(r.B, y3, out=r.lam2)
        np.add(r.lam, r.lam2, out=r.lam)
        np.add(r.lam, r.C, out=r.lam)
        np.minimum.reduce(r.lam, axis=2, out=r.minl)
        np.greater_equal(r.minl, -INSIDE_EPS, out=r.inside)
        r.inside.argmax(axis=1, out=r.tsel)
        np.add(r.tsel, r.rowT, out=r.tsel)
        r.inside.reshape(-1).take(r.tsel, out=r.anyin)
        # value inside: Σ λ_v · value(vertex v, column)
        lamf, vf = r.lam.reshape(-1), r.V.reshape(-1)
        r.val[:] = 0.0
        for v in range(3):
            np.multiply(r.tsel, 3, out=r.idx)
            np.add(r.idx, v, out=r.idx)
            lamf.take(r.idx, out=r.l)
            vf.take(r.idx, out=r.vidx)
            self._xt_value(r, r.vidx, r.g)
            np.multiply(r.l, r.g, out=r.l)
            np.add(r.val, r.l, out=r.val)
        # outside the hull: the value at the closest point of the hull boundary
        ax, ay, dx, dy, inv = r.ex
        x2, y2 = r.x[:, None], r.y[:, None]
        np.subtract(x2, ax, out=r.es)
        np.multiply(r.es, dx, out=r.es)
        np.subtract(y2, ay, out=r.et)
        np.multiply(r.et, dy, out=r.et)
        np.add(r.es, r.et, out=r.es)
        np.multiply(r.es, inv, out=r.es)
        np.maximum(r.es, 0.0, out=r.es)
        np.minimum(r.es, 1.0, out=r.es)  # s along each edge
        np.multiply(r.es, dx, out=r.et)
        np.add(ax, r.et, out=r.et)
        np.subtract(x2, r.et, out=r.et)
        np.multiply(r.et, r.et, out=r.ed)
        np.multiply(r.es, dy, out=r.et)
        np.add(ay, r.et, out=r.et)
        np.subtract(y2, r.et, out=r.et)
        np.multiply(r.et, r.et, out=r.et)
        np.add(r.ed, r.et, out=r.ed)
        r.ed.argmin(axis=1, out=r.esel)
        np.add(r.esel, r.rowE, out=r.esel)
        r.es.reshape(-1).take(r.esel, out=r.s_e)
        r.ea.reshape(-1).take(r.esel, out=r.vidx)
        self._xt_value(r, r.vidx, r.va)
        r.eb.reshape(-1).take(r.esel, out=r.vidx)
        self._xt_value(r, r.vidx, r.g)
        np.subtract(r.g, r.va, out=r.g)
        np.multiply(r.s_e, r.g, out=r.g)
        np.add(r.va, r.g, out=r.g)
        np.logical_not(r.anyin, out=r.tb)
        np.copyto(r.val, r.g, where=r.tb)
        np.multiply(r.val, r.ratio, out=r.val)
        tflat[r.flat] = r.val

    @staticmethod
    def _xt_value(r: _Rows, vertex: np.ndarray, out: np.ndarray) -> None:
        """out = correction of `vertex` in each row's selected column."""
        np.add(vertex, r.row_base, out=r.idx)
        np.multiply(r.idx, 4, out=r.idx)
        np.add(r.idx, r.col, out=r.idx)
        r.vals_flat.take(r.idx, out=out)

    def _step_xt_old(self, acc: np.ndarray, tflat: np.ndarray) -> None:
        """Old crosstalk model (001 §4.5, 003 §3.5): table over the signed acceleration."""
        r = self._xt_old
        if not r.n:
            return
        acc.take(r.dyn, out=r.a)
        np.divide(r.a, UNITS_PER_MM, out=r.a)
        r.table.lookup(r.a, r.val)
        tflat[r.flat] = r.val
