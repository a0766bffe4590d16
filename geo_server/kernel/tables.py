"""Batched table lookups for the fast kernel (SPEC §6: linear, edges held).

`BatchedInterp` serves every axis that uses one kind of 1-D table with a single
`np.searchsorted`: the per-row tables are concatenated and row r's keys are shifted by
r·2^33 so that the rows occupy disjoint key ranges of one ascending array. Because the
shifted query `q + r·2^33` is rounded (ulp 2^-12 at 128 rows), the index is checked and
corrected by one step against the *unshifted* keys, so results equal a per-row bisect
exactly. Table values may come in several variants (LSEC pos/neg, crosstalk's four
correction columns): variant v of row r lives at `v·L + index` in one flat value array.

Everything is allocated at construction; `lookup` only writes into preallocated
scratch arrays and the caller's `out`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Row key offset: tables of internal-unit positions stay below 2^32 in magnitude.
ROW_SHIFT = float(2**33)


class BatchedInterp:
    """Linear interpolation with held edges for many small tables at once."""

    def __init__(self, keys: Sequence[np.ndarray], values: Sequence[Sequence[np.ndarray]]):
        """`keys[r]` ascending x of row r; `values[r][v]` the y of variant v (same length).

        Rows with a single point get a second point one unit further with the same value,
        so that every row has at least one segment (a constant).
        """
        self.rows = len(keys)
        nvar = len(values[0]) if self.rows else 1
        xs, ys = [], [[] for _ in range(nvar)]
        for k, vs in zip(keys, values, strict=True):
            k = np.asarray(k, dtype=float)
            vs = [np.asarray(v, dtype=float) for v in vs]
            if len(k) == 1:
                k = np.array([k[0], k[0] + 1.0])
                vs = [np.array([v[0], v[0]]) for v in vs]
            xs.append(k)
            for i, v in enumerate(vs):
                ys[i].append(v)
        lens = np.array([len(k) for k in xs], dtype=np.int64)
        self.start = np.concatenate([[0], np.cumsum(lens)[:-1]]).astype(np.int64)
        self.last_seg = self.start + lens - 2  # last valid segment start per row
        self.x = np.concatenate(xs) if xs else np.zeros(2)
        total = len(self.x)
        self.y = np.concatenate([np.concatenate(v) for v in ys]) if xs else np.zeros(2)
        self.var_stride = total
        shift = np.repeat(np.arange(self.rows, dtype=float) * ROW_SHIFT, lens)
        self.keys = self.x + shift
        self.row_shift = np.arange(self.rows, dtype=float) * ROW_SHIFT
        self.xmin = self.x[self.start] if self.rows else np.zeros(0)
        self.xmax = self.x[self.start + lens - 1] if self.rows else np.zeros(0)
        n = self.rows
        self._q = np.zeros(n)
        self._qs = np.zeros(n)
        self._i = np.zeros(n, dtype=np.int64)
        self._i1 = np.zeros(n, dtype=np.int64)
        self._b = np.zeros(n, dtype=bool)
        self._x0 = np.zeros(n)
        self._x1 = np.zeros(n)
        self._y0 = np.zeros(n)
        self._y1 = np.zeros(n)
        self._t = np.zeros(n)

    def lookup(self, q: np.ndarray, out: np.ndarray, variant: np.ndarray | None = None) -> None:
        """out[r] = table_r(q[r]) (variant[r] when given), edges held."""
        x, qq, i, i1, b = self.x, self._q, self._i, self._i1, self._b
        np.maximum(q, self.xmin, out=qq)
        np.minimum(qq, self.xmax, out=qq)
        np.add(qq, self.row_shift, out=self._qs)
        np.copyto(i, np.searchsorted(self.keys, self._qs, side="right"))
        i -= 1
        np.maximum(i, self.start, out=i)
        np.minimum(i, self.last_seg, out=i)
        # one-step correction against the exact keys (see module docstring)
        np.add(i, 1, out=i1)
        x.take(i1, out=self._x1)
        np.greater_equal(qq, self._x1, out=b)
        np.add(i, b, out=i)
        x.take(i, out=self._x0)
        np.less(qq, self._x0, out=b)
        np.subtract(i, b, out=i)
        np.maximum(i, self.start, out=i)
        np.minimum(i, self.last_seg, out=i)
        x.take(i, out=self._x0)
        np.add(i, 1, out=i1)
        x.take(i1, out=self._x1)
        if variant is not None:
            # variant offsets into the flat value array
            np.multiply(variant, self.var_stride, out=self._i1)
            np.add(i, self._i1, out=i)
            np.add(i, 1, out=i1)
        self.y.take(i, out=self._y0)
        self.y.take(i1, out=self._y1)
        # t = (q − x0)/(x1 − x0); value = y0 + t·(y1 − y0) (same formula as the reference)
        np.subtract(qq, self._x0, out=self._t)
        np.subtract(self._x1, self._x0, out=self._x1)
        np.divide(self._t, self._x1, out=self._t)
        np.subtract(self._y1, self._y0, out=self._y1)
        np.multiply(self._t, self._y1, out=out)
        np.add(self._y0, out, out=out)
