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

from geo_server.kernel.common import FRICT, LEAD, TEMP
from geo_server.kernel.kernel import RING, Kernel
from geo_server.kernel.triangulation import INSIDE_EPS


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
        self.GB = np.zeros((B, len(g.G)))
        ns = len(g.sign)
        self.ns = ns
        self.SGN = np.zeros((B, ns))
        nw = len(g.w)
        self.WT = np.zeros((B, nw))
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
            self.CODE = np.zeros((B, nx))
            self.IDX = np.zeros((B, nx), dtype=np.int64)
            self.NOW = np.zeros((B, nx, 3))
            self.FXT = np.zeros((B, nx))
            self.o_xt = _offset(vec.fac_xt, vec.fac)
        l1 = k._l1
        if l1 is not None:
            lk = l1.lookup
            m = len(lk.qc)
            self.o_l1g = _offset(l1.raw, g.G)
            self.o_l1v = _offset(l1.out, V)
            self.QC1 = np.zeros((B, m), dtype=complex)
            self.QC1.real = lk.qc.real  # fixed row ids; crosstalk variants set per run
            self.SEG1 = np.zeros((B, m, 3))
            self.L1T = np.zeros((B, m))
            self.nlin = len(l1.lin_rowid)
        pl = k._plane
        if pl is not None:
            P = pl.u.shape[1]
            self.P = P
            self.o_pl = _offset(pl.u, g.G)
            self.FL = np.zeros((B, 2, P))
            self.UV = np.zeros((B, 2, 2, P))
            self.PW = np.zeros((B, 2, 2, P))
            self.PT = np.zeros((B, 2, P))
            self.K00 = np.zeros((B, P))
            self.PK = np.zeros((B, 2, 2, P), dtype=np.int64)
            self.PC = np.zeros((B, 2, 2, P))
        tri = k._tri
        if tri is not None:
            T, G3 = tri.H.shape[0], tri.H.shape[1]
            G = G3 // 3
            self.T = T
            self.o_trig = _offset(tri.xy1, g.G)
            self.LAMM = np.zeros((B, T, G3, 1))
            self.TMIN = np.zeros((B, T, G))
            self.TIN = np.zeros((B, T, G), dtype=bool)
            self.SEL = np.zeros((B, T), dtype=np.int64)
            self.COEF = np.zeros((B, T, 3))
        ls = k._lsec
        if ls is not None:
            L = len(ls.d)
            self.CPV = np.zeros((B, 2, L))
            self.ADD = np.zeros((B, L, 2))
            self.ADD[:, :, 0] = ls.add[:, 0]
            self.LG = np.zeros((B, L, 2))
            self.QCL = np.zeros((B, L), dtype=complex)
            self.QF = self.QCL.view(float).reshape(B, L, 2)
            self.LD = np.zeros((B, L))
            self.SEGL = np.zeros((B, L, 3))
            self.LT = np.zeros((B, L))
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

    def run(self, homed: np.ndarray) -> bool:
        """`size` cycles of `Kernel.step` with the commands in `pos`/`vel`/`acc`/`rev`
        and the homing flags `homed` (unchanged throughout). False, with nothing
        changed, when the stretch is not steady (see the module docstring)."""
        k = self.k
        if not self.ready():
            return False
        mul, add, subtract = np.multiply, np.add, np.subtract
        copyto, minimum, maximum = np.copyto, np.minimum, np.maximum
        B = self.size
        src, fs = k._src, k._fr_state
        d = src.dir
        # no reversal: the sign of every velocity is 0 or the held direction
        sv = self.sgn_v
        np.sign(self.vel, sv)
        mul(sv, d, sv)
        np.less(sv, 0.0, self.flip)
        if np.count_nonzero(self.flip):
            return False
        # the effective flags are those of the last cycle: the selection only changes
        # in a cycle that applies an operation or a program block (never in a steady
        # stretch), so they stay as long as the homing flags do
        et = k._eff
        if np.count_nonzero(np.not_equal(homed, et.homed_in)):
            return False
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
        mul(TT, bt.tc6, TT)
        add(bt.off0, TT, TG[:, :, TEMP])

        # the gather
        g = k._gather
        GB, ns = self.GB, self.ns
        if g.any:
            SB.take(g.src, axis=1, out=GB)
            if g.any_sign:
                np.sign(GB[:, :ns], self.SGN)
            if g.any_q:
                if g.any_wrap:
                    gw = GB[:, ns : ns + len(g.w)]
                    np.mod(gw, g.w_per, self.WT)
                    copyto(gw, self.WT, where=g.w_wrap)
                q = GB[:, ns:]
                subtract(q, g.q_sub, q)
                np.divide(q, g.q_div, q)
        FAC = self.FAC
        xt = k._xt
        if xt is not None:
            nx = self.nx
            code, idx = self.CODE, self.IDX
            mul(self.SGN[:, :nx], 3.0, code)  # (3, 1)·(sign(v), sign(a)): exact
            add(code, self.SGN[:, nx : 2 * nx], code)
            add(code, xt.rowoff, idx, casting="unsafe")
            xt.tab.take(idx, axis=0, out=self.NOW)
            fx = self.FXT
            mul(GB[:, nx : 2 * nx], self.NOW[:, :, 0], fx)
            minimum(fx, 1.0, out=fx)
            copyto(FAC[:, self.o_xt : self.o_xt + nx], fx)
        V = self.V
        l1 = k._l1
        if l1 is not None:
            lk = l1.lookup
            m = len(lk.qc)
            QC1 = self.QC1
            if l1.has_lin:
                QC1.real[:, : self.nlin] = self.NOW[:, self.nx - self.nlin :, 2]
            QC1.imag = GB[:, self.o_l1g : self.o_l1g + m]
            lk.seg_table.take(lk.keys.searchsorted(QC1, "right"), axis=0, out=self.SEG1)
            lt = self.L1T
            subtract(QC1.imag, self.SEG1[:, :, 0], lt)
            mul(lt, self.SEG1[:, :, 2], lt)
            add(lt, self.SEG1[:, :, 1], V[:, self.o_l1v : self.o_l1v + m])
        pl = k._plane
        if pl is not None:
            P = self.P
            u = GB[:, self.o_pl : self.o_pl + 2 * P].reshape(B, 2, P)
            fl = self.FL
            maximum(u, 0.0, out=u)
            minimum(u, pl.last, out=u)
            np.floor(u, fl)
            minimum(fl, pl.lim, out=fl)
            UV = self.UV
            subtract(u, fl, UV[:, :, 1])
            subtract(1.0, UV[:, :, 1], UV[:, :, 0])
            pw = self.PW
            mul(UV[:, 1][:, :, None, :], UV[:, 0][:, None, :, :], pw)
            mul(fl, pl.sw, self.PT)
            add(self.PT[:, 0], self.PT[:, 1], self.K00)
            add(self.K00[:, None, None, :], pl.base4, self.PK, casting="unsafe")
            pl.tab.take(self.PK, out=self.PC)
            mul(pw, self.PC, pw)
            out = V[:, :P]  # corners added in `step`'s order
            add(pw[:, 0, 0], pw[:, 0, 1], out)
            add(out, pw[:, 1, 0], out)
            add(out, pw[:, 1, 1], out)
        tri = k._tri
        if tri is not None:
            T = self.T
            xy1 = GB[:, self.o_trig : self.o_trig + 3 * T].reshape(B, T, 3, 1)
            lamm = self.LAMM
            np.matmul(tri.H, xy1, out=lamm)  # per cycle the product `step` computes
            lam = lamm.reshape(B, T, 3, -1)
            tmin, tin, sel = self.TMIN, self.TIN, self.SEL
            minimum(lam[:, :, 0], lam[:, :, 1], out=tmin)
            minimum(tmin, lam[:, :, 2], out=tmin)
            np.greater_equal(tmin, -INSIDE_EPS, tin)
            tin.argmax(axis=2, out=sel)
            add(sel, self.NOW[:, :T, 1], sel, casting="unsafe")
            coef = self.COEF
            tri.val.take(sel, axis=0, out=coef)
            out11 = V[:, self.o_tri : self.o_tri + T].reshape(B, T, 1, 1)
            np.matmul(coef[:, :, None, :], xy1, out=out11)
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
        mul(f.jump, W, T7)
        subtract(TG, T7, ACT)

        ls = k._lsec
        if ls is not None:
            ACTf = self.ACTf
            ACTf.take(ls.cp, axis=1, out=self.CPV)
            t = self.ADD[:, :, 1]
            add(self.CPV[:, 0], self.CPV[:, 1], t)
            if not ls.all_wc:
                mul(t, ls.wc, t)
            SB.take(ls.src, axis=1, out=self.LG)
            add(self.LG, self.ADD, self.QF)
            lq = self.QCL.imag
            if ls.any_wrap:
                ld = self.LD
                subtract(lq, ls.x0, ld)
                np.mod(ld, ls.per, ld)
                add(ld, ls.x0, ld)
                copyto(lq, ld, where=ls.wrap)
            lk = ls.lookup
            lk.seg_table.take(lk.keys.searchsorted(self.QCL, "right"), axis=0, out=self.SEGL)
            lt = self.LT
            subtract(lq, self.SEGL[:, :, 0], lt)
            mul(lt, self.SEGL[:, :, 2], lt)
            tl = TG[:, :, LEAD]
            if ls.all:
                add(lt, self.SEGL[:, :, 1], tl)
            else:
                add(lt, self.SEGL[:, :, 1], self.VALL)
                TGf[:, ls.flat] = self.VALL
            mul(tl, eff[:, LEAD], tl)
            tld = T7[:, :, LEAD]
            mul(f.jump[:, LEAD], W[:, :, LEAD], tld)
            subtract(tl, tld, ACT[:, :, LEAD])

        # friction (000 §4.5): path, weights, the delay line
        C, PATH = self.C, self.PATH
        C[0] = fs.path
        np.abs(D, C[1:])
        np.add.accumulate(C, axis=0, out=PATH)
        cur = self.CUR
        if fr.any:
            wpre = self.WPRE
            wpre[:, fr.slots] = V[:, self.o_wpre :]
            mul(TG[:, :, FRICT], wpre, cur)
        else:
            copyto(cur, TG[:, :, FRICT])
        if fr.any_pd:
            wp = self.WPOST
            np.divide(PATH[1:], fr.pd, wp, where=fr.has_pd)
            minimum(wp, 1.0, out=wp)
            mul(cur, wp, cur)
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
