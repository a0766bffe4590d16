"""Plane compensation (000 §4.3 p.38–43; docs/design.md §6.4): its tables and its law.

Bilinear on table[j][i], j along master 2, i along master 1, positions clamped to the grid:
u = clamp((q − start)/interval, 0, last) (the kernel's gather gives (q − start)/interval),
cell = min(floor(u), last − 1); all tables are concatenated into `tab`, and the four
corners of the cell are gathered with one `take` at base + j0·stride + i0 + corner offset.

The law (`bilinear`) is written once and runs on a `PlaneWork` of any leading shape: `[2,
P]` for a single cycle (`Kernel.step`), `[B, 2, P]` for a pass of B steady cycles
(`KernelBatch.run`), so both compute the same IEEE operations in the same order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from geo_server.kernel.common import POS
from geo_server.model import AxisConfig

if TYPE_CHECKING:
    from geo_server.kernel.inputs import Gather, SourceVector

#: (is modulo, period) of the axis in a slot: a table over a modulo master wraps with it.
MasterWrap = Callable[[int], tuple[bool, float]]


def _f64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=float).reshape(-1)


@dataclass(frozen=True, slots=True, eq=False)
class PlaneTables:
    """The plane tables of one load, for the P axes that have one (`build`)."""

    P: int
    last: np.ndarray  # [2, P] last index along each master
    lim: np.ndarray  # max(last − 1, 0)
    sw: np.ndarray  # [2, P] (1, stride): flat cell index = i0 + j0·stride
    base4: np.ndarray  # [2, 2, P] corner offsets in `tab`
    tab: np.ndarray
    u: np.ndarray  # [2, P] (u, v) of this cycle: a view of the kernel's gather G

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
    ) -> PlaneTables | None:
        """The tables of the axes in `rows`; fills the gather's part with the masters'
        positions and their scaling (start, interval, modulo wrap: 000 p.31)."""
        P = len(rows)
        if not P:
            return None
        ps = [axes[i].comp.plane for i in rows]
        m = np.array([[slot[x.master1_ax_nr] for x in ps], [slot[x.master2_ax_nr] for x in ps]])
        w = [[master_wrap(int(s)) for s in row] for row in m]
        g.src[part] = np.asarray(src.index(POS, m)).reshape(-1)
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
        return cls(
            P=P,
            last=last,
            lim=np.maximum(last - 1, 0),
            sw=np.stack([np.ones(P), stride]),
            base4=base4,
            tab=np.concatenate([t.ravel() for t in tabs]),
            u=g.G[part].reshape(2, P),
        )


@dataclass(frozen=True, slots=True, eq=False)
class PlaneWork:
    """Buffers of `bilinear` for a leading shape `lead` (() for one cycle, (B,) for a pass),
    with the views it needs made once."""

    u: np.ndarray  # [*lead, 2, P] (u, v), clamped in place
    fl: np.ndarray  # [*lead, 2, P] floor, then cell
    frac: np.ndarray  # [*lead, 2, P] fractions (u − cell)
    gfrac: np.ndarray  # [*lead, 2, P] 1 − fraction
    wv: np.ndarray  # (1 − fv | fv) as [*lead, 2, 1, P]
    wu: np.ndarray  # (1 − fu | fu) as [*lead, 1, 2, P]
    w: np.ndarray  # [*lead, 2, 2, P] corner weights [j, i]
    w00: np.ndarray  # its corners [*lead, P]
    w01: np.ndarray
    w10: np.ndarray
    w11: np.ndarray
    tmp0: np.ndarray  # [*lead, P] cell index along master 1
    tmp1: np.ndarray  # [*lead, P] along master 2, times the stride
    tmp: np.ndarray  # [*lead, 2, P]
    k00: np.ndarray  # [*lead, P] flat cell index
    k00b: np.ndarray  # k00 as [*lead, 1, 1, P]
    k: np.ndarray  # [*lead, 2, 2, P] corner indices
    c: np.ndarray  # [*lead, 2, 2, P] corner values
    out: np.ndarray  # [*lead, P] the targets

    @classmethod
    def create(cls, P: int, u: np.ndarray, out: np.ndarray) -> PlaneWork:
        """`u` and `out` are the caller's views (of its gather and its target vector)."""
        lead = u.shape[:-2]
        uv = np.zeros((*lead, 2, 2, P))  # [axis u/v][1 − frac, frac]
        tmp = np.zeros((*lead, 2, P))
        k00 = np.zeros((*lead, P))
        wts = np.zeros((*lead, 2, 2, P))
        return cls(
            u=u,
            fl=np.zeros((*lead, 2, P)),
            frac=uv[..., 1, :],
            gfrac=uv[..., 0, :],
            wv=uv[..., 1, :, None, :],
            wu=uv[..., 0, None, :, :],
            w=wts,
            w00=wts[..., 0, 0, :],
            w01=wts[..., 0, 1, :],
            w10=wts[..., 1, 0, :],
            w11=wts[..., 1, 1, :],
            tmp0=tmp[..., 0, :],
            tmp1=tmp[..., 1, :],
            tmp=tmp,
            k00=k00,
            k00b=k00[..., None, None, :],
            k=np.zeros((*lead, 2, 2, P), dtype=np.int64),
            c=np.zeros((*lead, 2, 2, P)),
            out=out,
        )


def bilinear(t: PlaneTables, w: PlaneWork) -> None:
    """The plane targets (000 §4.3) from the scaled positions `w.u` into `w.out`."""
    mul, add, minimum = np.multiply, np.add, np.minimum
    u, fl = w.u, w.fl
    np.maximum(u, 0.0, out=u)
    minimum(u, t.last, out=u)
    np.floor(u, fl)
    minimum(fl, t.lim, out=fl)
    np.subtract(u, fl, w.frac)
    np.subtract(1.0, w.frac, w.gfrac)
    # weights [j, i] = (1 − fv | fv)_j · (1 − fu | fu)_i
    pw = w.w
    mul(w.wv, w.wu, pw)
    # corner indices: base + j0·stride + i0 + corner offset
    mul(fl, t.sw, w.tmp)
    add(w.tmp0, w.tmp1, w.k00)
    add(w.k00b, t.base4, w.k, casting="unsafe")
    t.tab.take(w.k, out=w.c)
    mul(pw, w.c, pw)
    po = w.out  # the corners in a fixed order
    add(w.w00, w.w01, po)
    add(po, w.w10, po)
    add(po, w.w11, po)
