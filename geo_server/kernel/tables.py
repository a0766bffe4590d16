"""The 1-D table law (docs/design.md §6.0: linear between the points, edges held): cross
(000 §4.2), friction (§4.5), crosstalk modes 1/2 and old model (§4.6, 001 §4.5), LSEC
(§4.4) — `interp`, compiled, used by the kernel for every such table.

The tables of a load are packed into one float array (`Packer`), each as its points x
(ascending) followed by its values y; a compensation keeps the offset of its table.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from geo_server.jit import compiled


class Packer:
    """The tables of one load, concatenated into one float array (`done`)."""

    def __init__(self) -> None:
        self._parts: list[np.ndarray] = []
        self._size = 0

    def add(self, values: npt.ArrayLike) -> int:
        """Append `values`; returns their offset."""
        a = np.asarray(values, dtype=float).ravel()
        off = self._size
        self._parts.append(a)
        self._size += len(a)
        return off

    def table(self, x: npt.ArrayLike, y: npt.ArrayLike) -> int:
        """Append a 1-D table (points `x` ascending, values `y`); returns the offset of
        its points (its values follow them: `interp`)."""
        off = self.add(x)
        self.add(y)
        return off

    def done(self) -> np.ndarray:
        return np.concatenate(self._parts) if self._parts else np.zeros(1)


@compiled
def interp(tab: np.ndarray, off: int, m: int, q: float) -> float:
    """The value at `q` of the table of `m` points at `off` (points, then values):
    linear between the points, the first and last value held outside (docs/design.md
    §6.0). With equal neighbouring points the later one wins (`bisect_right`)."""
    y = off + m
    if m == 1 or q <= tab[off]:
        return tab[y]
    if q >= tab[off + m - 1]:
        return tab[y + m - 1]
    lo, hi = 0, m - 1  # tab[off + lo] <= q < tab[off + hi]
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if tab[off + mid] <= q:
            lo = mid
        else:
            hi = mid
    x0 = tab[off + lo]
    t = (q - x0) / (tab[off + lo + 1] - x0)
    return tab[y + lo] + t * (tab[y + lo + 1] - tab[y + lo])


@compiled
def wrap(q: float, start: float, period: float) -> float:
    """A position on a modulo axis (or a modulo table) in [start, start + period)
    (docs/design.md §3.8; 000 p.31)."""
    return start + (q - start) % period
