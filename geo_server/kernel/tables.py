"""Merged table lookups for the fast kernel (docs/design.md §6.0: linear, edges held).

Per GEO cycle the kernel's cost is dominated by the *number* of numpy calls, not by the
work, so every 1-D table of every axis and kind (cross, friction, crosstalk modes 1/2
and old model, the friction pre-reversal weight) lives in ONE `MergedTable` and is served
by one `searchsorted`, one gather and three arithmetic calls.

Exact row separation without rounding: the keys are complex numbers `row + 1j·x`. numpy
orders complex values lexicographically (real part first), so the concatenated rows form
one ascending array while every x stays an unshifted float64. (Shifting x by
`row·2^33` instead rounds the query by up to 2^-12 units, which moves results by more
than the kernel's 1e-9 equivalence tolerance.)

Held edges without clipping: each row starts with a `-inf` key, and the segment table
has one entry per `searchsorted` result: "before the first point" (constant y0), each
inner segment (x_i, y_i, slope_i), and "at or after the last point" (constant y_last).
A lookup is then `y_i + (q − x_i)·slope_i` for every query, whatever its position.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class MergedTable:
    """Linear interpolation with held edges for many small 1-D tables at once.

    `rows[r] = (x, y)`, x ascending (ties allowed, as in `bisect_right`). A query is a
    complex number `r + 1j·q`: the caller writes the row id into the real part (fixed
    rows, or a per-cycle choice between variant rows such as LSEC pos/neg) and the
    position into the imaginary part.
    """

    def __init__(self, rows: Sequence[tuple[np.ndarray, np.ndarray]]) -> None:
        keys, segs = [], [np.zeros((1, 3))]  # segs[0]: never selected (ss ≥ 1)
        for r, (x, y) in enumerate(rows):
            x = np.asarray(x, dtype=float).ravel()
            y = np.asarray(y, dtype=float).ravel()
            m = len(x)
            k = np.empty(m + 1, dtype=complex)
            k.real = r
            k.imag[0] = -np.inf
            k.imag[1:] = x
            keys.append(k)
            seg = np.zeros((m + 1, 3))  # columns: x_i, y_i, slope_i
            seg[0] = (x[0], y[0], 0.0)  # q < x0: held first value
            if m > 1:
                with np.errstate(divide="ignore", invalid="ignore"):
                    slope = np.diff(y) / np.diff(x)
                seg[1:m, 0], seg[1:m, 1], seg[1:m, 2] = x[:-1], y[:-1], slope
            seg[m] = (x[-1], y[-1], 0.0)  # q ≥ x_last: held last value
            segs.append(seg)
        self.keys = np.concatenate(keys) if keys else np.zeros(1, dtype=complex)
        self.seg = np.concatenate(segs)


class Lookup:
    """Preallocated query/result buffers of one `MergedTable` for a fixed row count, for
    one cycle (`lead` = ()) or a pass of B cycles (`lead` = (B,), `batch`)."""

    def __init__(self, table: MergedTable, row_ids: np.ndarray, lead: tuple[int, ...] = ()) -> None:
        n = len(row_ids)
        self.table, self.row_ids = table, row_ids
        self.keys, self.seg_table = table.keys, table.seg
        self.qc = np.zeros((*lead, n), dtype=complex)
        self.qc.real = row_ids
        self.pairs = self.qc.view(float).reshape(*lead, n, 2)  # (row id, position) pairs
        self.q = self.qc.imag  # view: write the query positions here
        self.rowid = self.qc.real  # view: write per-cycle variant row ids here
        self.seg = np.zeros((*lead, n, 3))
        self.x0, self.y0, self.slope = self.seg[..., 0], self.seg[..., 1], self.seg[..., 2]
        self.tmp = np.zeros((*lead, n))

    def batch(self, size: int) -> Lookup:
        """The same lookup for a pass of `size` cycles (the cycles a leading axis)."""
        return Lookup(self.table, self.row_ids, (size,))

    def __call__(self, out: np.ndarray) -> None:
        """`interpolate`."""
        interpolate(self, out)


def interpolate(lk: Lookup, out: np.ndarray) -> None:
    """out = table_row(q) for the queries in `lk.qc` (5 numpy calls): the 1-D law of every
    table (linear, edges held: docs/design.md §6.0) — cross, friction, crosstalk modes 1/2
    and old model, LSEC — for a single cycle and a pass alike."""
    lk.seg_table.take(lk.keys.searchsorted(lk.qc, "right"), axis=0, out=lk.seg)
    t = lk.tmp
    np.subtract(lk.q, lk.x0, t)
    np.multiply(t, lk.slope, t)
    np.add(t, lk.y0, out)
