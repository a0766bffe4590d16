"""Several GEO cycles of the compensation kernel in one pass (docs/design.md §13.2).

`Kernel.step` costs about 70 numpy calls per cycle whatever the number of axes, so a
machine in motion pays the calls, not the arithmetic. Between two events — a move that
starts or ends, a reversal, a write, a reload, a homing, a COMP switch — a stretch of
cycles only samples running profiles, and every cycle of it is a function of its own
commands and of state that changes in simple ways:

* the direction does not flip, so there is no reversal event, and with the selection,
  the homing flags and the pending events unchanged, no step event either: the sin²
  index of every column advances as k_b = min(k + b, end) and the jumps stay;
* the friction path since the last reversal is a running sum (`np.add.accumulate`
  adds in order: the same sums as cycle by cycle), and the delay line is written
  before it is read, for every cycle of the stretch at once;
* everything else (backlash, temperature, the gathers, crosstalk, the 1-D lookups,
  plane, crosstalk mode 3, LSEC) is elementwise over the cycle's own inputs.

`KernelBatch.run` computes B such cycles with the cycles as a leading axis: the same
IEEE operations in the same order as `Kernel.step`, so the numbers are bit-identical
(tests/test_batch.py compares them). Where numpy could change the order of a reduction
for a different shape (the plane's corner sum, the mode-3 matrix products, the total
offset) it is called once per cycle with the shape `step` uses. A stretch the batch
cannot prove steady is refused before anything changes (`run` returns False) and the
caller runs single cycles.
"""

from __future__ import annotations

import numpy as np

from geo_server.kernel import crosstalk, friction, sin2, temperature
from geo_server.kernel.common import FRICT, LEAD, TEMP
from geo_server.kernel.friction import RING
from geo_server.kernel.inputs import GatherWork, gather
from geo_server.kernel.kernel import Kernel
from geo_server.kernel.lsec import LsecTables
from geo_server.kernel.plane import PlaneWork, bilinear
from geo_server.kernel.tables import interpolate


def _offset(view: np.ndarray, base: np.ndarray) -> int:
    """Index of `view`'s first element in the 1-D array `base` it is a view of."""
    return (view.__array_interface__["data"][0] - base.__array_interface__["data"][0]) // 8


def batch_limit(kernel: Kernel) -> int:
    """The most cycles of one pass the kernel's tables allow: 0 with crosstalk mode-3
    rows on the scalar evaluation; else the friction delay line's length minus the
    longest delay (a longer pass would read a row it writes later)."""
    tri = kernel._tri
    if tri is not None and tri.slow:
        return 0
    ridx = np.array(kernel._frict.ridx_rows[0], dtype=np.int64)
    delay = (-(ridx // kernel.n)) % RING
    return RING - int(delay.max(initial=0))


class KernelBatch:
    """Buffers for `size` cycles of one `Kernel`, rebuilt when its tables change.

    The machine writes the commands of the stretch into `pos`, `vel`, `acc` and `rev`
    ([size, n] views of the batched source vector), then calls `run`. Afterwards `total`
    holds every cycle's total offset ([size, n]) and the kernel is in the state after
    the last cycle, as if `Kernel.step` had run `size` times."""

    def __init__(self, kernel: Kernel, size: int) -> None:
        if size < 1:
            raise ValueError("a batch has at least one cycle")
        self.k = kernel
        self.size = size
        n = kernel.n
        self.SB = np.zeros((size, 5 * n + 2))
        self.SB[:, 4 * n + 1] = 1.0
        self.pos = self.SB[:, :n]
        self.vel = self.SB[:, n : 2 * n]
        self.acc = self.SB[:, 2 * n : 3 * n]
        self.rev = self.SB[:, 3 * n : 4 * n]
        self.dir = self.SB[:, 4 * n + 2 :]
        self.total = np.zeros((size, n))
        self._generation = -1

    # ------------------------------------------------------------------ buffers

    def _build(self) -> None:
        k, B, n = self.k, self.size, self.k.n
        self._generation = k.generation
        self.sgn_v = np.zeros((B, n))
        self.flip = np.zeros((B, n), dtype=bool)
        self.D = np.zeros((B, n))
        self.C = np.zeros((B + 1, n))  # (path, |Δpos| of every cycle)
        self.PATH = np.zeros((B + 1, n))
        self.TG = np.zeros((B, n, 7))
        self.TGf = self.TG.reshape(B, n * 7)
        self.ACT = np.zeros((B, n, 7))
        self.ACTf = self.ACT.reshape(B, n * 7)
        self.T7 = np.zeros((B, n, 7))
        self.KI = np.zeros((B, n, 7), dtype=np.int64)
        self.AR = np.arange(1, B + 1, dtype=np.int64)[:, None, None]
        self.W = np.zeros((B, n, 7))
        self.MW = np.zeros((B, n))
        self.TT = np.zeros((B, n))
        g = k._gather
        self.gather = gw = GatherWork.batch(g, self.SB)  # `inputs.gather` over the pass
        self.GB, self.SGN = gw.G, gw.sign
        self.ns = len(g.sign)
        vec = k._vec
        V = vec.V
        self.V = np.zeros((B, len(V)))
        self.FAC = np.ones((B, len(V)))
        self.o_wpre = _offset(vec.wpre, V) if len(vec.wpre) else len(V)
        self.o_tri = _offset(vec.tri, V) if len(vec.tri) else 0
        self.o_fr = _offset(vec.fac_fr, vec.fac) if len(vec.fac_fr) else 0
        self.n_fr = len(vec.fac_fr)
        xt = k._xt
        if xt is not None:
            nx = len(xt.code)
            self.nx = nx
            o_xt = _offset(vec.fac_xt, vec.fac)
            self.xt = crosstalk.StateWork.create(
                self.SGN[:, :nx],
                self.SGN[:, nx : 2 * nx],
                self.GB[:, nx : 2 * nx],
                self.FAC[:, o_xt : o_xt + nx],
            )
            self.NOW = self.xt.now
        l1 = k._l1
        if l1 is not None:
            self.o_l1g = _offset(l1.raw, g.G)
            self.o_l1v = _offset(l1.out, V)
            self.LK1 = l1.lookup.batch(B)  # fixed row ids; crosstalk variants set per run
            self.nlin = len(l1.lin_rowid)
        pl = k._plane
        self.plane: PlaneWork | None = None
        if pl is not None:  # `plane.bilinear` over the pass: the cycles a leading axis
            o_pl = _offset(pl.u, g.G)
            u = self.GB[:, o_pl : o_pl + 2 * pl.P].reshape(B, 2, pl.P)
            assert np.shares_memory(u, self.GB), "a view of the gather"
            self.plane = PlaneWork.create(pl.P, u, self.V[:, : pl.P])
        tri = k._tri
        if tri is not None:
            T, G = tri.H.shape[0], tri.H.shape[1] // 3
            o_trig = _offset(tri.xy1, g.G)
            xy1 = self.GB[:, o_trig : o_trig + 3 * T].reshape(B, T, 3, 1)
            out11 = self.V[:, self.o_tri : self.o_tri + T].reshape(B, T, 1, 1)
            assert np.shares_memory(xy1, self.GB) and np.shares_memory(out11, self.V)
            self.tri = crosstalk.Mode3Work.create(xy1, G, self.NOW[:, :T, 1], out11)
        ls = k._lsec
        if ls is not None:
            L = len(ls.d)
            self.CPV = np.zeros((B, 2, L))
            self.ADD = np.zeros((B, L, 2))
            self.ADD[:, :, 0] = ls.add[:, 0]
            self.LG = np.zeros((B, L, 2))
            self.LKL = ls.lookup.batch(B)
            self.LD = np.zeros((B, L))
            self.VALL = np.zeros((B, L))
        fr = k._frict
        self.WPRE = np.ones((B, n))
        self.WPOST = np.ones((B, n))
        self.CUR = np.zeros((B, n))
        self.ridx = np.array(fr.ridx_rows, dtype=np.int64)  # [RING, n]
        self.RIDX = np.zeros((B, n), dtype=np.int64)
        self.RV = np.zeros((B, n))

    # ------------------------------------------------------------------ the stretch

    def ready(self) -> bool:
        """The kernel's state allows a stretch (no pending event, no held output):
        checked before the commands are sampled. The caller keeps the stretch within
        `batch_limit` of the tables (`Machine.run_batch`)."""
        k = self.k
        if k._first or k._pending_any or k._any_held:
            return False
        if self._generation != k.generation:
            self._build()
        return True

    def _steady(self, homed: np.ndarray) -> bool:
        """The stretch is steady (see the module docstring): no reversal, and the
        effective flags stay those of the last cycle. Changes nothing but scratch."""
        k = self.k
        # no reversal: the sign of every velocity is 0 or the held direction
        sv = self.sgn_v
        np.sign(self.vel, sv)
        np.multiply(sv, k._src.dir, sv)
        np.less(sv, 0.0, self.flip)
        if np.count_nonzero(self.flip):
            return False
        # the effective flags are those of the last cycle: the selection only changes
        # in a cycle that applies an operation or a program block (never in a steady
        # stretch), so they stay as long as the homing flags do
        return not np.count_nonzero(np.not_equal(homed, k._eff.homed_in))

    def _lsec(self, ls: LsecTables, eff: np.ndarray, jump: np.ndarray) -> None:
        """LSEC (000 §4.4) over the pass, as `Kernel._lsec_cycle` does for one cycle:
        looked up at the command position plus each cycle's filtered cross and plane
        outputs, then through its own sin² column (no events in a steady stretch)."""
        mul, add, subtract = np.multiply, np.add, np.subtract
        self.ACTf.take(ls.cp, axis=1, out=self.CPV)
        t = self.ADD[:, :, 1]
        add(self.CPV[:, 0], self.CPV[:, 1], t)
        if not ls.all_wc:
            mul(t, ls.wc, t)
        self.SB.take(ls.src, axis=1, out=self.LG)
        lkb = self.LKL
        add(self.LG, self.ADD, lkb.pairs)
        lq = lkb.q
        if ls.any_wrap:
            ld = self.LD
            subtract(lq, ls.x0, ld)
            np.mod(ld, ls.per, ld)
            add(ld, ls.x0, ld)
            np.copyto(lq, ld, where=ls.wrap)
        tl = self.TG[:, :, LEAD]
        if ls.all:
            interpolate(lkb, tl)
        else:
            interpolate(lkb, self.VALL)
            self.TGf[:, ls.flat] = self.VALL
        mul(tl, eff[:, LEAD], tl)
        sin2.output(
            tl, jump[:, LEAD], self.W[:, :, LEAD], self.T7[:, :, LEAD], self.ACT[:, :, LEAD]
        )

    def run(self, homed: np.ndarray) -> bool:
        """`size` cycles of `Kernel.step` with the commands in `pos`/`vel`/`acc`/`rev`
        and the homing flags `homed` (unchanged throughout). False, with nothing
        changed, when the stretch is not steady (see the module docstring)."""
        k = self.k
        if not self.ready() or not self._steady(homed):
            return False
        mul, add, subtract = np.multiply, np.add, np.subtract
        copyto, minimum = np.copyto, np.minimum
        B = self.size
        src, fs = k._src, k._fr_state
        d = src.dir
        eff = k.effective

        # ---- from here on the stretch is steady: compute it
        SB = self.SB
        copyto(self.dir, d)
        D = self.D
        subtract(self.pos[0], src.pos, D[0])
        subtract(self.pos[1:], self.pos[:-1], D[1:])

        # backlash: the last cycle's (the direction holds); temperature (000 §3.1 p.15)
        TG = self.TG
        copyto(TG, k.target)
        bt = k._bt
        TT = self.TT
        if bt.any_modulo:
            MW = self.MW
            np.mod(self.pos, bt.period, MW)
            copyto(MW, self.pos, where=bt.not_modulo)
            subtract(MW, bt.pos0, TT)
        else:
            subtract(self.pos, bt.pos0, TT)
        temperature.offset_into(bt.off0, bt.tc6, TT, TG[:, :, TEMP])

        # the gather
        g = k._gather
        GB, ns = self.GB, self.ns
        if g.any:
            gather(g, self.gather)
        FAC = self.FAC
        xt = k._xt
        if xt is not None:
            crosstalk.state(xt.rowoff, xt.tab, self.xt)
        V = self.V
        l1 = k._l1
        if l1 is not None:
            lkb = self.LK1
            m = lkb.q.shape[1]
            if l1.has_lin:
                lkb.rowid[:, : self.nlin] = self.NOW[:, self.nx - self.nlin :, 2]
            copyto(lkb.q, GB[:, self.o_l1g : self.o_l1g + m])
            interpolate(lkb, V[:, self.o_l1v : self.o_l1v + m])
        pl, pw = k._plane, self.plane
        if pl is not None and pw is not None:
            bilinear(pl, pw)
        tri = k._tri
        if tri is not None:
            crosstalk.mode3(tri.H, tri.val, self.tri)
        fr = k._frict
        if fr.any:
            nfr = self.n_fr
            mul(self.SGN[:, ns - nfr : ns], fr.scale, FAC[:, self.o_fr : self.o_fr + nfr])
        vec = k._vec
        if vec.any_fac:
            mul(V, FAC, V)
        TGf = self.TGf
        TGf[:, vec.flat] = V[:, : self.o_wpre]
        mul(TG, eff, TG)

        # sin² filter without events: k_b = min(k + b, end), the jumps stay
        f = k._filter
        KI, W, T7, ACT = self.KI, self.W, self.T7, self.ACT
        add(f.kidx, self.AR, KI)
        minimum(KI, f.end, out=KI)
        f.table.take(KI, out=W)
        sin2.output(TG, f.jump, W, T7, ACT)

        ls = k._lsec
        if ls is not None:  # LSEC (000 §4.4)
            self._lsec(ls, eff, f.jump)

        # friction (000 §4.5): path, weights, the delay line
        C, PATH = self.C, self.PATH
        C[0] = fs.path
        np.abs(D, C[1:])
        np.add.accumulate(C, axis=0, out=PATH)
        cur = self.CUR
        wpre = None
        if fr.any:
            wpre = self.WPRE
            wpre[:, fr.slots] = V[:, self.o_wpre :]
        pd = fr.pd if fr.any_pd else None
        friction.weigh(TG[:, :, FRICT], wpre, PATH[1:], pd, fr.has_pd, self.WPOST, cur)
        wpos = fs.ring_pos
        rows = (wpos + np.arange(B)) % RING
        fs.ring[rows] = cur
        self.ridx.take(rows, axis=0, out=self.RIDX)
        fs.ring_flat.take(self.RIDX, out=self.RV)
        mul(self.RV, fs.effective, ACT[:, :, FRICT])

        np.matmul(ACT, k._not_fr, out=self.total)  # per cycle `step`'s product

        # ---- the state after the last cycle
        copyto(k._prev, ACT[B - 2] if B > 1 else k.actual)
        copyto(k.actual, ACT[B - 1])
        copyto(k.target, TG[B - 1])
        subtract(k.actual, k._prev, k.delta)
        copyto(k.total_offset, self.total[B - 1])
        k._event.fill(False)
        copyto(f.kidx, KI[B - 1])
        copyto(f.w, W[B - 1])
        copyto(src.S, SB[B - 1])
        np.sign(src.vel, k._s)
        k._rev.fill(False)
        copyto(fs.path, PATH[B])
        copyto(fs.dpos, C[B])
        fs.ring_pos = (wpos + B) % RING
        return True
