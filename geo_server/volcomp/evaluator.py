"""The volumetric model vectorised: corrections for a batch of positions at once.

The same model as `geo_server.volcomp.reference` (docs/volumetric.md §2), arranged for
the GEO cycle (tests/test_volcomp_kernel.py holds the two together):

- the component errors of every chain axis over its own travel are one merged table (the
  union of the six curves' grid points; a piecewise-linear curve sampled at a finer set
  of points is the same curve), all axes served by one `searchsorted` on keys shifted
  apart per axis; tables over other or several arguments take the general path;
- axis transforms are stacked [batch, axes, 3, 3] and composed with `matmul`;
- the ideal machine's Jacobian is constant without rotary axes (computed once), else
  computed per position from the ideal model;
- two Newton steps (docs/volumetric.md §2 gives the error bound).
"""

from __future__ import annotations

import math
from bisect import bisect_right
from typing import Any

import numpy as np

from geo_server.volcomp.model import VolModel
from geo_server.volcomp.names import ROTARY
from geo_server.volcomp.tables import ParamTable, path_columns

#: keys of different axes are this far apart in the merged table (mm or °; the
#: interpolation itself uses the unshifted grid, so this costs no precision)
_SHIFT = 1e7
#: Newton steps per correction (docs/volumetric.md §2)
STEPS = 2
_COMPONENTS = ("EX", "EY", "EZ", "EA", "EB", "EC")
#: flattened I + [e]× = _EYE + e @ _SKEW
_EYE = np.eye(3).reshape(9)
_SKEW = np.zeros((3, 9))
for _k, (_r, _c, _s) in enumerate(
    [(2, 1, 1), (1, 2, -1), (0, 2, 1), (2, 0, -1), (1, 0, 1), (0, 1, -1)]
):
    # a (about X) at [2,1] = +a, [1,2] = −a; b at [0,2] = +b, [2,0] = −b; c at [1,0], [0,1]
    _SKEW[_k // 2, _r * 3 + _c] = _s


def _merged(tables: list[ParamTable | None]) -> tuple[np.ndarray, np.ndarray] | None:
    """(grid, values [points, 6]) of the 1-D tables of one axis' six components that
    are merged (`None` where a component is not), or None if there are none."""
    own = [t for t in tables if t is not None]
    if not own:
        return None
    grid = np.unique(np.concatenate([t.grid[0] for t in own]))
    values = np.zeros((len(grid), 6))
    for j, t in enumerate(tables):
        if t is not None:
            g = t.grid[0]
            values[:, j] = t.values[0] if len(g) == 1 else np.interp(grid, g, t.values)
    if len(grid) == 1:  # one record: a constant over the whole travel
        grid = np.array([grid[0], grid[0] + 1.0])
        values = np.vstack([values, values])
    return grid, values


class Evaluator:
    """Corrections of one compensation for a batch of programmed positions."""

    def __init__(self, model: VolModel) -> None:
        self.model = model
        chain = model.chain
        self.n = n = len(chain)
        self.w = model.workpiece_axes
        self.linear_idx = np.array([chain.index(a) for a in model.linear])
        self.rotary = [i for i, a in enumerate(chain) if a in ROTARY]
        axes = [model.axes[a] for a in chain]
        self.sign = np.array([ax.sign for ax in axes])
        self.offset = np.array([ax.offset for ax in axes])
        self.u = np.array([ax.direction for ax in axes])
        # linear axes travel along Ω(ε0)·u (squareness)
        self.u_tilted = np.array(
            [ax.direction + np.cross(ax.position_tilt, ax.direction) for ax in axes]
        )
        self.tilt = np.array([ax.position_tilt for ax in axes])
        self.shift = np.array([ax.position_shift for ax in axes])
        self.centre = np.array([ax.centre for ax in axes])
        self.constants = np.zeros((n, 6))  # component errors given as constants
        self.general: list[tuple[int, int, ParamTable, list[int]]] = []
        segments = []
        spliced = []
        for i, a in enumerate(chain):
            tables = [model.tables.get(f"{c}{a}") for c in _COMPONENTS]
            own = [t for t in tables if t is not None and t.arguments == (a,)]
            # the merged table of the axis takes its own 1-D tables when they agree on
            # splicing (one modulo for the key); the rest take the per-table path
            own = [t for t in own if t.mode == "GRID"]
            merge_spliced = bool(own) and all(t.spliced for t in own)
            merged: list[ParamTable | None] = [None] * 6
            for j, t in enumerate(tables):
                if t is None:
                    continue
                if t.arguments == (a,) and t.mode == "GRID" and t.spliced == merge_spliced:
                    merged[j] = t
                elif not t.arguments:
                    self.constants[i, j] = float(t.values)
                else:
                    self.general.append((i, j, t, [chain.index(x) for x in t.arguments]))
            segments.append(_merged(merged))
            spliced.append(merge_spliced)
        self._build_merged(segments)
        self.spliced = np.array(spliced)
        self.any_spliced = bool(self.spliced.any())
        self.const_jac = None if self.rotary else self._jacobian(np.zeros((1, n)))[0]
        self.const_jac_inv = None if self.const_jac is None else np.linalg.inv(self.const_jac)
        self._scalar = self._scalar_tables() if self._scalar_fits() else None
        # one position, any chain without N-D tables (rotary, workpiece side, splicing)
        self._chain1 = self._chain_tables() if not self.general else None
        # the one-position path's constants as Python floats (no numpy scalars)
        self._offset_list = self.offset.tolist()
        self._nominal_su = [tuple((s * u).tolist()) for s, u in zip(self.sign, self.u, strict=True)]
        self._linear_list = self.linear_idx.tolist()
        self._inv_list = None if self.const_jac_inv is None else self.const_jac_inv.tolist()

    # ------------------------------------------------------------------ one position

    def _scalar_fits(self) -> bool:
        """The one-position path: linear axes on the tool side, every component error
        a 1-D table over its own axis or a constant, no splicing."""
        return not self.rotary and self.w == 0 and not self.general and not self.any_spliced

    def _axis_rows(self, i: int) -> tuple[Any, ...]:
        """Chain axis i's merged table in Python floats and lists: (lo, hi, grid, value
        rows, slope rows, constants) — what both one-position paths interpolate."""
        a, b = self.first[i], self.last[i] + 2
        return (
            float(self.lo[i]),
            float(self.hi[i]),
            self.grid_raw[a:b].tolist(),
            [tuple(r) for r in self.values[a:b].tolist()],
            [tuple(r) for r in self.slope[a:b].tolist()],
            tuple(self.constants[i].tolist()),
        )

    def _scalar_tables(self) -> list[tuple[Any, ...]]:
        """Per chain axis: (*`_axis_rows`, s·u′)."""
        return [
            (*self._axis_rows(i), tuple((self.sign[i] * self.u_tilted[i]).tolist()))
            for i in range(self.n)
        ]

    def _chain_tables(self) -> list[tuple[Any, ...]]:
        """Per chain axis, Python floats for `_forward_chain`: (rotary, spliced,
        *`_axis_rows`, s, u, s·u′, (K, K²), (K′, K′²), centre, shift, tilt) with K the
        cross-product matrix of u (Rodrigues) and K′ that of the alternative model's
        tilted axis."""
        out = []
        for i in range(self.n):
            u = self.u[i]
            ut = self.u_tilted[i] / np.linalg.norm(self.u_tilted[i])
            k = _cross_matrix(u)
            k2 = _cross_matrix(ut)
            out.append(
                (
                    i in self.rotary,
                    bool(self.spliced[i]),
                    *self._axis_rows(i),
                    float(self.sign[i]),
                    tuple(u.tolist()),
                    tuple((self.sign[i] * self.u_tilted[i]).tolist()),
                    (tuple(k.reshape(9).tolist()), tuple((k @ k).reshape(9).tolist())),
                    (tuple(k2.reshape(9).tolist()), tuple((k2 @ k2).reshape(9).tolist())),
                    tuple(self.centre[i].tolist()),
                    tuple(self.shift[i].tolist()),
                    tuple(self.tilt[i].tolist()),
                )
            )
        return out

    def _transform1(self, i: int, v: float, errors: bool) -> tuple[tuple[float, ...], ...]:
        """(R as 9 floats row by row, t) of chain axis i at model value v: the table of
        `_transforms` for one position."""
        (rot, spl, lo, hi, grid, vals, slopes, const, s, u, su, kk, kk2, c, sh, tl) = self._chain1[
            i
        ]  # type: ignore[index]
        if errors:
            x = v % 360.0 if spl else v
            key = lo if x < lo else hi if x > hi else x
            j = min(max(bisect_right(grid, key) - 1, 0), len(grid) - 2)
            f = key - grid[j]
            e = [vals[j][m] + f * slopes[j][m] + const[m] for m in range(6)]
        else:
            e = [0.0] * 6
        if not rot:
            if not errors:
                return (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), (
                    s * v * u[0],
                    s * v * u[1],
                    s * v * u[2],
                )
            return _omega(e[3], e[4], e[5]), (v * su[0] + e[0], v * su[1] + e[1], v * su[2] + e[2])
        angle = math.radians(s * v)
        if errors and self.model.alternative:
            r = _mul(_omega(e[3], e[4], e[5]), _rodrigues1(kk2, angle))
            c = (c[0] + sh[0], c[1] + sh[1], c[2] + sh[2])
            d = (e[0], e[1], e[2])
        elif errors:
            r = _mul(_omega(e[3] + tl[0], e[4] + tl[1], e[5] + tl[2]), _rodrigues1(kk, angle))
            d = (sh[0] + e[0], sh[1] + e[1], sh[2] + e[2])
        else:
            r = _rodrigues1(kk, angle)
            d = (0.0, 0.0, 0.0)
        rc = _apply(r, c)
        return r, (c[0] + d[0] - rc[0], c[1] + d[1] - rc[1], c[2] + d[2] - rc[2])

    def _forward_chain(
        self, q: list[float], tip: tuple[float, float, float], errors: bool
    ) -> tuple[float, float, float]:
        """`forward` at one position in Python floats, for any chain (rotary axes,
        workpiece side, splicing): the same model as the vectorised form."""
        p = tip
        for i in range(self.n - 1, self.w - 1, -1):
            r, t = self._transform1(i, q[i], errors)
            rp = _apply(r, p)
            p = (t[0] + rp[0], t[1] + rp[1], t[2] + rp[2])
        for i in range(self.w - 1, -1, -1):
            r, t = self._transform1(i, q[i], errors)
            p = _solve(r, (p[0] - t[0], p[1] - t[1], p[2] - t[2]))
        return p

    def _correction_chain(self, q: list[float], tip: tuple[float, float, float]) -> list[float]:
        qs = [v + o for v, o in zip(q, self._offset_list, strict=True)]
        n0 = self._forward_chain(qs, tip, False)
        lin = self._linear_list
        cols = []
        for i in lin:  # the ideal machine is affine in its linear axes
            moved = list(qs)
            moved[i] += 1.0
            p = self._forward_chain(moved, tip, False)
            cols.append((p[0] - n0[0], p[1] - n0[1], p[2] - n0[2]))
        jac = (
            cols[0][0], cols[1][0], cols[2][0],
            cols[0][1], cols[1][1], cols[2][1],
            cols[0][2], cols[1][2], cols[2][2],
        )  # fmt: skip
        d = [0.0, 0.0, 0.0]
        moved = list(qs)
        for _ in range(STEPS):
            for k, i in enumerate(lin):
                moved[i] = qs[i] + d[k]
            a = self._forward_chain(moved, tip, True)
            step = _solve(jac, (n0[0] - a[0], n0[1] - a[1], n0[2] - a[2]))
            d = [d[0] + step[0], d[1] + step[1], d[2] + step[2]]
        return d

    def _forward_scalar(
        self, q: list[float], tip: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        """`forward` at one position, in Python floats: the same operations as the
        vectorised form (interpolate, then p ← t + Ω·p from the tool inwards), without
        a numpy call, which costs more than the arithmetic at this size."""
        px, py, pz = tip
        for i in range(self.n - 1, -1, -1):
            lo, hi, grid, vals, slopes, const, su = self._scalar[i]  # type: ignore[index]
            x = q[i]
            key = lo if x < lo else hi if x > hi else x
            j = min(max(bisect_right(grid, key) - 1, 0), len(grid) - 2)
            f = key - grid[j]
            v, sl = vals[j], slopes[j]
            dx = v[0] + f * sl[0] + const[0]
            dy = v[1] + f * sl[1] + const[1]
            dz = v[2] + f * sl[2] + const[2]
            ea = v[3] + f * sl[3] + const[3]
            eb = v[4] + f * sl[4] + const[4]
            ec = v[5] + f * sl[5] + const[5]
            px, py, pz = (
                x * su[0] + dx + px + (eb * pz - ec * py),
                x * su[1] + dy + py + (ec * px - ea * pz),
                x * su[2] + dz + pz + (ea * py - eb * px),
            )
        return px, py, pz

    def _correction_scalar(self, q: np.ndarray, tip: np.ndarray) -> np.ndarray:
        t = (float(tip[0]), float(tip[1]), float(tip[2]))
        return np.array([self.correction_one(q[0].tolist(), t)])

    def correction_one(self, q: list[float], tip: tuple[float, float, float]) -> list[float]:
        """[Δx, Δy, Δz] (mm) at one programmed position (chain order, mm and °): the
        GEO cycle's path, in Python floats where the model allows (`_scalar_fits`)."""
        if self._scalar is None:
            if self._chain1 is not None:
                return self._correction_chain(q, tip)
            out: list[float] = self.correction(np.array([q]), np.array(tip))[0].tolist()
            return out
        qs = [v + o for v, o in zip(q, self._offset_list, strict=True)]
        n0x, n0y, n0z = tip
        for v, (ux, uy, uz) in zip(qs, self._nominal_su, strict=True):
            n0x, n0y, n0z = n0x + v * ux, n0y + v * uy, n0z + v * uz
        inv = self._inv_list
        assert inv is not None  # (no rotary axis: the Jacobian is constant)
        lin = self._linear_list
        d = [0.0, 0.0, 0.0]
        moved = list(qs)
        for _ in range(STEPS):
            for k, i in enumerate(lin):
                moved[i] = qs[i] + d[k]
            ax, ay, az = self._forward_scalar(moved, tip)
            mx, my, mz = n0x - ax, n0y - ay, n0z - az
            for k in range(3):
                r = inv[k]
                d[k] += r[0] * mx + r[1] * my + r[2] * mz
        return d

    def _build_merged(self, segments: list[tuple[np.ndarray, np.ndarray] | None]) -> None:
        grids, raw, values, lo, hi, first, last = [], [], [], [], [], [], []
        start = 0
        for i, s in enumerate(segments):
            g, v = s if s is not None else (np.array([0.0, 1.0]), np.zeros((2, 6)))
            grids.append(g + i * _SHIFT)
            raw.append(g)
            values.append(v)
            lo.append(g[0])
            hi.append(g[-1])
            first.append(start)
            last.append(start + len(g) - 2)  # the last segment's left index
            start += len(g)
        self.grid = np.concatenate(grids)
        self.grid_raw = np.concatenate(raw)
        self.values = np.concatenate(values)
        self.slope = np.zeros_like(self.values)
        span = np.diff(self.grid_raw)
        with np.errstate(divide="ignore", invalid="ignore"):
            self.slope[:-1] = np.diff(self.values, axis=0) / span[:, None]
        self.lo, self.hi = np.array(lo), np.array(hi)
        self.key_shift = np.arange(self.n) * _SHIFT
        self.first, self.last = np.array(first), np.array(last)

    # ------------------------------------------------------------------ the model

    def errors(self, q: np.ndarray) -> np.ndarray:
        """[b, n, 6] component errors (δ mm, ε rad) at model positions q [b, n]."""
        x = np.mod(q, 360.0, where=self.spliced, out=q.copy()) if self.any_spliced else q
        key = np.clip(x, self.lo, self.hi)
        idx = np.searchsorted(self.grid, key + self.key_shift, side="right") - 1
        np.clip(idx, self.first, self.last, out=idx)
        frac = key - self.grid_raw[idx]
        err = self.values[idx] + frac[..., None] * self.slope[idx]
        err += self.constants
        for i, j, t, cols in self.general:
            err[:, i, j] += _multilinear(t, q[:, cols])
        return err

    def _transforms(self, q: np.ndarray, err: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(R [b, n, 3, 3], t [b, n, 3]) of every axis at model positions q [b, n]."""
        b = q.shape[0]
        if err is None:
            rot = np.broadcast_to(np.eye(3), (b, self.n, 3, 3)).copy()
            trans = (self.sign * q)[..., None] * self.u
        else:
            rot = (_EYE + err[..., 3:] @ _SKEW).reshape(b, self.n, 3, 3)
            trans = (self.sign * q)[..., None] * self.u_tilted + err[..., :3]
        for i in self.rotary:
            angle = np.radians(self.sign[i] * q[:, i])
            c = self.centre[i]
            if err is not None and self.model.alternative:
                u = self.u_tilted[i] / np.linalg.norm(self.u_tilted[i])
                c = c + self.shift[i]
                r = rot[:, i] @ _rodrigues(u, angle)
                t = c + err[:, i, :3] - r @ c
            elif err is not None:
                tilt = _EYE + (err[:, i, 3:] + self.tilt[i]) @ _SKEW
                r = tilt.reshape(b, 3, 3) @ _rodrigues(self.u[i], angle)
                t = c + self.shift[i] + err[:, i, :3] - r @ c
            else:
                r = _rodrigues(self.u[i], angle)
                t = c - r @ c
            rot[:, i] = r
            trans[:, i] = t
        return rot, trans

    def forward(self, q: np.ndarray, tip: np.ndarray, errors: bool = True) -> np.ndarray:
        """[b, 3] tool tip relative to the workpiece at model positions q [b, n]."""
        rot, trans = self._transforms(q, self.errors(q) if errors else None)
        p = np.broadcast_to(tip, (q.shape[0], 3))
        for i in range(self.n - 1, self.w - 1, -1):  # tool side, from the tool inwards
            p = trans[:, i] + (rot[:, i] @ p[..., None])[..., 0]
        for i in range(self.w - 1, -1, -1):  # workpiece side: T_wp⁻¹, base outwards
            p = np.linalg.solve(rot[:, i], (p - trans[:, i])[..., None])[..., 0]
        return p

    def _jacobian(self, q: np.ndarray) -> np.ndarray:
        """[b, 3, 3] ∂p_nom/∂(x, y, z): the ideal machine is affine in its linear axes."""
        tip = np.zeros(3)
        base = self.forward(q, tip, errors=False)
        jac = np.empty((q.shape[0], 3, 3))
        for k, i in enumerate(self.linear_idx):
            moved = q.copy()
            moved[:, i] += 1.0
            jac[:, :, k] = self.forward(moved, tip, errors=False) - base
        return jac

    def correction(self, q: np.ndarray, tip: np.ndarray) -> np.ndarray:
        """[b, 3] Δx, Δy, Δz (mm) at programmed positions q [b, n] (mm, °)."""
        if self._scalar is not None and q.shape[0] == 1:
            return self._correction_scalar(q, tip)
        q = q + self.offset
        target = self.forward(q, tip, errors=False)
        inv = self.const_jac_inv
        if inv is None:
            inv = np.linalg.inv(self._jacobian(q))
        delta = np.zeros((q.shape[0], 3))
        moved = q.copy()
        for _ in range(STEPS):
            moved[:, self.linear_idx] = q[:, self.linear_idx] + delta
            miss = target - self.forward(moved, tip)
            delta += (inv @ miss[..., None])[..., 0]
        return delta


def _cross_matrix(u: np.ndarray) -> np.ndarray:
    x, y, z = u
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _omega(a: float, b: float, c: float) -> tuple[float, ...]:
    """I + [(a, b, c)]× as 9 floats, row by row."""
    return (1.0, -c, b, c, 1.0, -a, -b, a, 1.0)


def _rodrigues1(kk: tuple[tuple[float, ...], tuple[float, ...]], angle: float) -> tuple[float, ...]:
    """I + sin·K + (1 − cos)·K² as 9 floats."""
    k, k2 = kk
    s, c = math.sin(angle), 1.0 - math.cos(angle)
    eye = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    return tuple(eye[m] + s * k[m] + c * k2[m] for m in range(9))


def _mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(
        a[3 * r] * b[c] + a[3 * r + 1] * b[3 + c] + a[3 * r + 2] * b[6 + c]
        for r in range(3)
        for c in range(3)
    )


def _apply(r: tuple[float, ...], p: tuple[float, ...]) -> tuple[float, float, float]:
    return (
        r[0] * p[0] + r[1] * p[1] + r[2] * p[2],
        r[3] * p[0] + r[4] * p[1] + r[5] * p[2],
        r[6] * p[0] + r[7] * p[1] + r[8] * p[2],
    )


def _solve(r: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float]:
    """r⁻¹·b by Cramer's rule (3×3)."""
    a, bb, c, d, e, f, g, h, k = r
    det = a * (e * k - f * h) - bb * (d * k - f * g) + c * (d * h - e * g)
    x = (b[0] * (e * k - f * h) - bb * (b[1] * k - f * b[2]) + c * (b[1] * h - e * b[2])) / det
    y = (a * (b[1] * k - f * b[2]) - b[0] * (d * k - f * g) + c * (d * b[2] - b[1] * g)) / det
    z = (a * (e * b[2] - b[1] * h) - bb * (d * b[2] - b[1] * g) + b[0] * (d * h - e * g)) / det
    return x, y, z


def _rodrigues(u: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """[b, 3, 3] rotations by `angle` (rad, [b]) about the unit vector u."""
    x, y, z = u
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s = np.sin(angle)[:, None, None]
    c = (1.0 - np.cos(angle))[:, None, None]
    return np.eye(3) + s * k + c * (k @ k)


def _points(t: ParamTable, x: np.ndarray) -> np.ndarray:
    """[b] values of a SCATTER or PATH table at points x [b, k] (`tables.evaluate`)."""
    assert t.points is not None and t.point_values is not None
    pts, vals = t.points, t.point_values
    if t.mode == "SCATTER":
        d2 = ((x[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2)  # [b, m]
        exact = d2 == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            w = 1.0 / d2
            out = (w * vals).sum(axis=1) / w.sum(axis=1)
        hit = exact.any(axis=1)
        if hit.any():
            out[hit] = vals[exact[hit].argmax(axis=1)]
        return out
    cols = path_columns(t)
    p, xx = pts[:, cols], x[:, cols]
    if len(p) == 1:
        return np.full(x.shape[0], vals[0])
    a, ab = p[:-1], p[1:] - p[:-1]  # [s, k]
    ll = (ab**2).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = ((xx[:, None, :] - a[None]) * ab[None]).sum(axis=2) / ll
    tt = np.clip(np.nan_to_num(tt, nan=0.0), 0.0, 1.0)  # [b, s]
    d2 = ((a[None] + tt[..., None] * ab[None] - xx[:, None, :]) ** 2).sum(axis=2)
    best = d2.argmin(axis=1)  # the first section wins a tie, as in the reference
    rows = np.arange(x.shape[0])
    tb = tt[rows, best]
    return vals[best] + tb * (vals[best + 1] - vals[best])


def _multilinear(t: ParamTable, x: np.ndarray) -> np.ndarray:
    """[b] values of an N-D table at points x [b, k]: multi-linear, edges held."""
    if t.mode != "GRID":
        return _points(t, x)
    b = x.shape[0]
    out = np.zeros(b)
    idx: list[np.ndarray] = []
    fr: list[np.ndarray] = []
    for d, g in enumerate(t.grid):
        v = x[:, d] % 360.0 if t.spliced else x[:, d]
        v = np.clip(v, g[0], g[-1])
        if len(g) == 1:
            idx.append(np.zeros(b, dtype=np.intp))
            fr.append(np.zeros(b))
            continue
        i = np.minimum(np.searchsorted(g, v, side="right") - 1, len(g) - 2)
        idx.append(i)
        fr.append((v - g[i]) / (g[i + 1] - g[i]))
    k = len(t.grid)
    for corner in range(1 << k):
        w = np.ones(b)
        at = []
        for d in range(k):
            up = (corner >> d) & 1
            if up and len(t.grid[d]) == 1:
                w = w * 0.0
            w = w * (fr[d] if up else 1.0 - fr[d])
            at.append(np.minimum(idx[d] + up, len(t.grid[d]) - 1))
        out += w * t.values[tuple(at)]
    return out


__all__ = ["STEPS", "Evaluator"]
