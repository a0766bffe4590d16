"""Crosstalk compensation (000 §4.6 p.80–93, old model 001 §4.5 / 003 §3.5; docs/design.md
§6.7, §12): its law and its tables.

New model: the slave's offset is a correction value times min(|a|/|a_ref|, 1), a the
dynamic master's acceleration in mm/s² (°/s²), clamped beyond a_ref (§12). The
correction column: accelerating (a·v ≥ 0) or decelerating, and with
`velocity_dependent` the negative direction (v < 0, or v = 0 and a < 0) in its own
column. The correction value: mode 1 the first test's, mode 2 linear over the position
of one master (`tables.interp`), mode 3 piecewise linear over the Delaunay triangulation
of the tests' positions of two masters, outside the hull the nearest hull point's value
(`evaluate`, over `triangulation.triangulate`). Old model: a table over the signed
acceleration.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from geo_server.jit import compiled
from geo_server.kernel.tables import Packer, interp
from geo_server.kernel.triangulation import INSIDE_EPS, triangulate
from geo_server.model import CrosstalkComp
from geo_server.units import UNITS_PER_MM

#: `layout.XT_KIND`: how the correction value is found (0: no crosstalk)
MODE1, MODE2, MODE3, OLD = 1, 2, 3, 4
#: floats per packed triangle (vertices, then λ = a·x + b·y + c of each vertex) and per
#: packed hull edge (end points, then a point, the direction and 1/length²)
TRI_SIZE, EDGE_SIZE = 12, 7


def pack(x: CrosstalkComp, tab: Packer) -> tuple[int, int, int, int, int, int, int]:
    """The crosstalk list's tables into `tab`: (kind, table offset, points, triangles'
    offset, triangles, edges' offset, edges). Modes 1/2: four tables (one per
    correction column), mode 1 a single point each; mode 3: the values of every test in
    four columns, then the triangles and the hull edges; old model: one table."""
    if x.dialect == "old":
        a = np.asarray(x.acc_table, dtype=float)
        order = np.argsort(a, kind="stable")
        off = tab.table(a[order], np.asarray(x.corr_table, dtype=float)[order])
        return OLD, off, len(a), 0, 0, 0, 0
    corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
    ax1 = [float(v) for v in x.ax_1] or [0.0]
    if x.mode == 3:
        ax2 = [float(v) for v in x.ax_2] or [0.0] * len(ax1)
        m = min(len(ax1), len(ax2), corr.shape[0])
        tri = triangulate(tuple((ax1[i], ax2[i]) for i in range(m)))
        off = tab.add(corr[:m].T)  # column c of test v at off + c·m + v
        t_off = tab.add(
            [
                [*map(float, t), *(v for co in coef for v in co)]
                for t, coef in zip(tri.triangles, tri.bary, strict=True)
            ]
            or [0.0]
        )
        e_off = tab.add([[a, b, *g] for (a, b), g in zip(tri.edges, tri.edge_geom, strict=True)])
        return MODE3, off, m, t_off, len(tri.triangles), e_off, len(tri.edges)
    if x.mode == 1:  # the first test's value (its position does not matter)
        keys, vals = np.zeros(1), corr[:1]
    else:
        first = np.asarray(ax1[: corr.shape[0]])
        order = np.argsort(first, kind="stable")
        keys, vals = first[order], corr[order]
    off = tab.table(keys, vals[:, 0])
    for c in range(1, 4):
        tab.table(keys, vals[:, c])
    return (MODE1 if x.mode == 1 else MODE2), off, len(keys), 0, 0, 0, 0


@compiled
def evaluate(
    tab: np.ndarray,
    vals: int,
    tri: int,
    ntri: int,
    edge: int,
    nedge: int,
    x: float,
    y: float,
) -> float:
    """Mode 3 (docs/design.md §12): the value at (x, y) of the values at `vals` (one per
    test) — in the first triangle containing the point (every barycentric coordinate ≥
    −INSIDE_EPS) the barycentric blend, outside the hull the value at the nearest point of
    the nearest hull edge (the first of equally near ones)."""
    for k in range(ntri):
        t = tri + k * TRI_SIZE
        l0 = tab[t + 3] * x + tab[t + 4] * y + tab[t + 5]
        l1 = tab[t + 6] * x + tab[t + 7] * y + tab[t + 8]
        l2 = tab[t + 9] * x + tab[t + 10] * y + tab[t + 11]
        if min(l0, l1, l2) >= -INSIDE_EPS:
            v0, v1, v2 = (
                tab[vals + int(tab[t])],
                tab[vals + int(tab[t + 1])],
                tab[vals + int(tab[t + 2])],
            )
            return l0 * v0 + l1 * v1 + l2 * v2
    best = np.inf
    result = 0.0
    for k in range(nedge):
        e = edge + k * EDGE_SIZE
        ax, ay, dx, dy, inv = tab[e + 2], tab[e + 3], tab[e + 4], tab[e + 5], tab[e + 6]
        s = ((x - ax) * dx + (y - ay) * dy) * inv
        s = min(max(s, 0.0), 1.0)
        ex, ey = x - (ax + s * dx), y - (ay + s * dy)
        d2 = ex * ex + ey * ey
        if d2 < best:
            best = d2
            va, vb = tab[vals + int(tab[e])], tab[vals + int(tab[e + 1])]
            result = va + s * (vb - va)
    return result


class CrosstalkTable(NamedTuple):
    """One slave's crosstalk table in the kernel's `tab` (000 §4.6): its kind (`OLD`, a
    mode), where its values start and their count `m`, mode 3's triangles and edges,
    whether it depends on the direction of motion, and 1/the limits of acceleration and
    deceleration (the ratio's denominators)."""

    kind: int
    off: int
    m: int
    tri: int
    ntri: int
    edge: int
    nedge: int
    veldep: bool
    inv_acc: float
    inv_dec: float


@compiled
def value(
    tab: np.ndarray, table: CrosstalkTable, acc: float, vel: float, x: float, y: float
) -> float:
    """The slave's offset (000 §4.6 p.84) of its `table` for the dynamic master's
    acceleration `acc` (units/s²) and velocity `vel`, and the position masters at
    (x, y)."""
    kind, off, m, tri, ntri, edge, nedge, veldep, inv_acc, inv_dec = table
    a = acc / UNITS_PER_MM  # mm/s² (°/s²)
    if kind == OLD:  # a table over the signed acceleration (001 §4.5)
        return interp(tab, off, m, a)
    accelerating = a * vel >= 0.0
    neg = vel < 0.0 or (vel == 0.0 and a < 0.0)
    col = (0 if accelerating else 2) + (1 if neg and veldep else 0)
    ratio = min(abs(a) * (inv_acc if accelerating else inv_dec), 1.0)
    if kind == MODE3:
        c_ref = evaluate(tab, off + col * m, tri, ntri, edge, nedge, x, y)
    else:  # modes 1 (a single point) and 2: column col's table
        c_ref = interp(tab, off + col * 2 * m, m, x)
    return c_ref * ratio
