"""Plane compensation (000 §4.3 p.38–43; docs/design.md §6.4): its law and its tables.

Bilinear on table[j][i], j along master 2, i along master 1 (row-major in the kernel's
table array), positions clamped to the grid: u = clamp((q − start)/interval, 0, last),
cell = min(floor(u), last − 1), fractions u − cell; the four corners weighed
(1 − fu)(1 − fv), fu(1 − fv), (1 − fu)fv, fu·fv, in that order.
"""

from __future__ import annotations

import math

import numpy as np

from geo_server.jit import compiled


@compiled
def bilinear(
    tab: np.ndarray,
    off: int,
    ni: int,
    nj: int,
    q1: float,
    q2: float,
    start1: float,
    start2: float,
    interval1: float,
    interval2: float,
) -> float:
    """The plane value (000 §4.3) of the ni × nj table at `off` (nj rows along master 2,
    ni columns along master 1) at the master positions (q1, q2)."""
    last1, last2 = float(ni - 1), float(nj - 1)
    u = min(max((q1 - start1) / interval1, 0.0), last1)
    v = min(max((q2 - start2) / interval2, 0.0), last2)
    i0 = min(math.floor(u), max(ni - 2, 0))
    j0 = min(math.floor(v), max(nj - 2, 0))
    fu, fv = u - i0, v - j0
    i1 = i0 + (1 if ni > 1 else 0)
    j1 = j0 + (1 if nj > 1 else 0)
    r0, r1 = off + j0 * ni, off + j1 * ni
    return (
        (1.0 - fu) * (1.0 - fv) * tab[r0 + i0]
        + fu * (1.0 - fv) * tab[r0 + i1]
        + (1.0 - fu) * fv * tab[r1 + i0]
        + fu * fv * tab[r1 + i1]
    )
