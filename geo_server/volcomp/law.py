"""The volumetric model's law, compiled: the correction of one compensation at one
programmed position (docs/volumetric.md §2, §3, §6), written once.

The same model as `geo_server.volcomp.reference` (the readable oracle, tested against it
in tests/test_volcomp*.py), arranged for the GEO cycle:

- `pack` turns a `VolModel` into two flat arrays at load: floats `tf` and integers `ti`.
  Per chain axis the component errors over its own travel are one merged table (the
  union of the six curves' grid points, values and slopes per interval; a
  piecewise-linear curve sampled at a finer set of points is the same curve), its
  constants, direction, tilted direction, centre, shift, tilt, sign, offset (IDk) and
  the rotary and spliced flags; the tables over other or several arguments ("general":
  multi-linear GRID, SCATTER, PATH, PATH_XY) each with their records; the ideal
  machine's Jacobian when it is constant (no rotary axis);
- `errors`, `transform`, `forward`, `jacobian`, `correction` evaluate it with plain
  floats (compiled: `geo_server.jit`); a model is read at the offsets `fb` (floats) and
  `ib` (integers), so the models of all compensations of a machine live in one pair of
  arrays (`geo_server.volcomp.step`);
- two Newton steps (docs/volumetric.md §2 gives the error bound).

`corrections` and `forwards` are the same functions in a loop over many positions.
"""

from __future__ import annotations

import math

import numpy as np

from geo_server.jit import compiled
from geo_server.volcomp.model import VolModel
from geo_server.volcomp.names import ROTARY
from geo_server.volcomp.tables import ParamTable, path_columns

#: Newton steps per correction (docs/volumetric.md §2)
STEPS = 2
#: the most arguments a table has (the chain's axes X Y Z A B C)
MAXARGS = 6
_COMPONENTS = ("EX", "EY", "EZ", "EA", "EB", "EC")
#: position errors over arguments add to these (004 p.32), after the components
_POSITIONS = ("X0", "Y0", "Z0", "A0", "B0", "C0")

# ---- ti: the model's integers, from its base `ib`
(
    N,  # chain length
    W,  # workpiece axes
    ALT,  # alternative rotary model
    ROT_ANY,  # a rotary axis: the Jacobian per position
    NGEN,  # general tables: how many, where their descriptors start (relative to ib)
    GEN,
    LIN,  # chain indices of X, Y, Z (3)
) = range(7)
IHDR = LIN + 3
# per chain axis, AXI integers from IHDR: rotary, spliced, merged table (float offset
# relative to fb) and its points, position errors over arguments (general tables)
A_ROT, A_SPL, A_TAB, A_PTS, A_VPOS = range(5)
AXI = 5
# per general table, GENI integers: chain axis and what it adds to (0-5: the component
# errors EX? … EC?, 6-11: the position errors X0? … C0?), mode, number of
# arguments, spliced, float offset of its data (relative to fb), records (SCATTER, PATH),
# the arguments' chain indices (MAXARGS), the grid's size per argument (GRID, MAXARGS),
# the columns a PATH measures distance in (how many, which: MAXARGS)
G_AXIS, G_COMP, G_MODE, G_K, G_SPL, G_TAB, G_M = range(7)
G_ARG = 7
G_DIM = G_ARG + MAXARGS
G_NPC = G_DIM + MAXARGS
G_PC = G_NPC + 1
GENI = G_PC + MAXARGS
GRID, SCATTER, PATH = range(3)

# ---- tf: the model's floats, from its base `fb`
JAC = 0  # the constant Jacobian (9, row by row), without rotary axes
P0 = 9  # tool point at zero length (3) and the scaled orientation N0 (3), 004 p.15
N0 = 12
FHDR = 15
# per chain axis, AXF floats from FHDR
F_SIGN = 0  # s: +1 tool side, −1 workpiece side
F_OFF = 1  # IDk
F_U = 2  # nominal direction u (3)
F_SU = 5  # s·u′: the linear axis' direction of travel tilted by ε0 (3)
F_UT = 8  # u′ normalised: the alternative model's axis (3)
F_C = 11  # centre (3)
F_SH = 14  # position shift δ0 (3)
F_TL = 17  # position tilt ε0 (3)
F_CONST = 20  # component errors given as constants (6)
F_K = 26  # cross-product matrix K of u and K² (9 + 9); K′ and K′² of u′ (9 + 9)
F_K2 = 35
F_KT = 44
F_KT2 = 53
AXF = 62


# ------------------------------------------------------------------ packing (Python)


def _cross_matrix(u: np.ndarray) -> np.ndarray:
    x, y, z = u
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _merged(tables: list[ParamTable | None]) -> tuple[np.ndarray, np.ndarray]:
    """(grid, values [points, 6]) of an axis' merged 1-D component-error tables (`None`
    where a component is not merged); two points at least (one record: a constant over
    the whole travel; none: zero)."""
    own = [t for t in tables if t is not None]
    if not own:
        return np.array([0.0, 1.0]), np.zeros((2, 6))
    grid = np.unique(np.concatenate([t.grid[0] for t in own]))
    values = np.zeros((len(grid), 6))
    for j, t in enumerate(tables):
        if t is not None:
            g = t.grid[0]
            values[:, j] = t.values[0] if len(g) == 1 else np.interp(grid, g, t.values)
    if len(grid) == 1:
        grid = np.array([grid[0], grid[0] + 1.0])
        values = np.vstack([values, values])
    return grid, values


class _Arrays:
    """Floats and integers appended, each part at a known offset."""

    def __init__(self, floats: int, ints: int) -> None:
        self.f: list[np.ndarray] = [np.zeros(floats)]
        self.i: list[np.ndarray] = [np.zeros(ints, dtype=np.int64)]
        self.nf, self.ni = floats, ints

    def floats(self, values: np.ndarray) -> int:
        a = np.asarray(values, dtype=float).ravel()
        off = self.nf
        self.f.append(a)
        self.nf += len(a)
        return off

    def ints(self, values: list[int]) -> int:
        off = self.ni
        self.i.append(np.array(values, dtype=np.int64))
        self.ni += len(values)
        return off


def _general(
    out: _Arrays, axis: int, comp: int, t: ParamTable, chain: tuple[str, ...]
) -> list[int]:
    """The descriptor of a general table (over other or several arguments), its data
    appended to `out`."""
    d = [0] * GENI
    d[G_AXIS], d[G_COMP], d[G_K], d[G_SPL] = axis, comp, len(t.arguments), int(t.spliced)
    for k, a in enumerate(t.arguments):
        d[G_ARG + k] = chain.index(a)
    if t.mode == "GRID":
        d[G_MODE] = GRID
        d[G_TAB] = out.floats(np.concatenate(t.grid))
        out.floats(np.asarray(t.values, dtype=float))
        for k, g in enumerate(t.grid):
            d[G_DIM + k] = len(g)
        return d
    assert t.points is not None and t.point_values is not None
    d[G_MODE] = SCATTER if t.mode == "SCATTER" else PATH
    d[G_M] = len(t.points)
    d[G_TAB] = out.floats(t.points)
    out.floats(t.point_values)
    cols = path_columns(t) if d[G_MODE] == PATH else []
    d[G_NPC] = len(cols)
    for k, c in enumerate(cols):
        d[G_PC + k] = c
    return d


def pack(model: VolModel) -> tuple[np.ndarray, np.ndarray]:
    """(tf, ti): the model as the compiled law reads it at bases 0 (the layout above)."""
    chain = model.chain
    n = len(chain)
    out = _Arrays(FHDR + AXF * n, IHDR + AXI * n)
    head_i, head_f = out.i[0], out.f[0]
    head_i[N], head_i[W], head_i[ALT] = n, model.workpiece_axes, int(model.alternative)
    head_i[ROT_ANY] = int(any(a in ROTARY for a in chain))
    for k, a in enumerate(model.linear):
        head_i[LIN + k] = chain.index(a)
    head_f[P0 : P0 + 3] = model.tool_zero
    head_f[N0 : N0 + 3] = model.tool_orientation
    general: list[list[int]] = []
    for i, a in enumerate(chain):
        ax = model.axes[a]
        f = head_f[FHDR + AXF * i : FHDR + AXF * (i + 1)]
        u = np.asarray(ax.direction, dtype=float)
        tilted = u + np.cross(ax.position_tilt, u)  # Ω(ε0)·u
        f[F_SIGN], f[F_OFF] = ax.sign, ax.offset
        f[F_U : F_U + 3] = u
        f[F_SU : F_SU + 3] = ax.sign * tilted
        ut = tilted / np.linalg.norm(tilted)
        f[F_UT : F_UT + 3] = ut
        f[F_C : F_C + 3] = ax.centre
        f[F_SH : F_SH + 3] = ax.position_shift
        f[F_TL : F_TL + 3] = ax.position_tilt
        km, kt = _cross_matrix(u), _cross_matrix(ut)
        f[F_K : F_K + 9], f[F_K2 : F_K2 + 9] = km.ravel(), (km @ km).ravel()
        f[F_KT : F_KT + 9], f[F_KT2 : F_KT2 + 9] = kt.ravel(), (kt @ kt).ravel()
        tables = [model.tables.get(f"{c}{a}") for c in _COMPONENTS]
        # the merged table takes the axis' own GRID tables when they agree on splicing
        # (one modulo for the key); the rest are general tables
        own = [t for t in tables if t is not None and t.arguments == (a,) and t.mode == "GRID"]
        spliced = bool(own) and all(t.spliced for t in own)
        merged: list[ParamTable | None] = [None] * 6
        for j, t in enumerate(tables):
            if t is None:
                continue
            if t.arguments == (a,) and t.mode == "GRID" and t.spliced == spliced:
                merged[j] = t
            elif not t.arguments:
                f[F_CONST + j] = float(t.values)
            else:
                general.append(_general(out, i, j, t, chain))
        varying = False
        for j, c in enumerate(_POSITIONS):
            t = model.tables.get(f"{c}{a}")
            if t is not None and t.arguments:  # (the constant part is in F_SH, F_TL)
                general.append(_general(out, i, 6 + j, t, chain))
                varying = True
        grid, values = _merged(merged)
        slope = np.zeros_like(values)
        with np.errstate(divide="ignore", invalid="ignore"):
            slope[:-1] = np.diff(values, axis=0) / np.diff(grid)[:, None]
        ai = out.i[0][IHDR + AXI * i : IHDR + AXI * (i + 1)]
        ai[A_ROT], ai[A_SPL], ai[A_VPOS] = int(a in ROTARY), int(spliced), int(varying)
        ai[A_TAB], ai[A_PTS] = out.floats(grid), len(grid)
        out.floats(values)
        out.floats(slope)
    head_i[NGEN] = len(general)
    head_i[GEN] = out.ints([v for d in general for v in d]) if general else out.ni
    tf = np.concatenate(out.f)
    ti = np.concatenate(out.i)
    if not head_i[ROT_ANY]:  # the ideal machine's Jacobian is the same everywhere
        jac = jacobian(tf, ti, 0, 0, np.zeros(n), 0.0, 0.0, 0.0)
        tf[JAC : JAC + 9] = jac
    return tf, ti


# ------------------------------------------------------------------ 3 × 3 (compiled)


@compiled
def omega(a: float, b: float, c: float) -> tuple[float, ...]:
    """I + [(a, b, c)]× as 9 floats, row by row: the small rotation of docs/volumetric.md
    §2."""
    return (1.0, -c, b, c, 1.0, -a, -b, a, 1.0)


@compiled
def mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, ...]:
    """The product of two 3 × 3 matrices (9 floats, row by row)."""
    return (
        a[0] * b[0] + a[1] * b[3] + a[2] * b[6],
        a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
        a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
        a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
        a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
        a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
        a[6] * b[0] + a[7] * b[3] + a[8] * b[6],
        a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
        a[6] * b[2] + a[7] * b[5] + a[8] * b[8],
    )


@compiled
def apply(r: tuple[float, ...], x: float, y: float, z: float) -> tuple[float, float, float]:
    """r·(x, y, z)."""
    return (
        r[0] * x + r[1] * y + r[2] * z,
        r[3] * x + r[4] * y + r[5] * z,
        r[6] * x + r[7] * y + r[8] * z,
    )


@compiled
def solve(r: tuple[float, ...], x: float, y: float, z: float) -> tuple[float, float, float]:
    """r⁻¹·(x, y, z) by Cramer's rule."""
    a, b, c, d, e, f, g, h, k = r
    det = a * (e * k - f * h) - b * (d * k - f * g) + c * (d * h - e * g)
    return (
        (x * (e * k - f * h) - b * (y * k - f * z) + c * (y * h - e * z)) / det,
        (a * (y * k - f * z) - x * (d * k - f * g) + c * (d * z - y * g)) / det,
        (a * (e * z - y * h) - b * (d * z - y * g) + x * (d * h - e * g)) / det,
    )


@compiled
def rodrigues(tf: np.ndarray, k: int, k2: int, angle: float) -> tuple[float, ...]:
    """I + sin·K + (1 − cos)·K², K and K² the 9 floats at `k` and `k2`."""
    s, c = math.sin(angle), 1.0 - math.cos(angle)
    return (
        1.0 + s * tf[k] + c * tf[k2],
        s * tf[k + 1] + c * tf[k2 + 1],
        s * tf[k + 2] + c * tf[k2 + 2],
        s * tf[k + 3] + c * tf[k2 + 3],
        1.0 + s * tf[k + 4] + c * tf[k2 + 4],
        s * tf[k + 5] + c * tf[k2 + 5],
        s * tf[k + 6] + c * tf[k2 + 6],
        s * tf[k + 7] + c * tf[k2 + 7],
        1.0 + s * tf[k + 8] + c * tf[k2 + 8],
    )


# ------------------------------------------------------------------ tables (compiled)


@compiled
def _right(tf: np.ndarray, off: int, m: int, x: float) -> int:
    """bisect_right of x in the m ascending floats at `off`, minus 1, kept in
    [0, m − 2]: the interval x lies in."""
    lo, hi = 0, m
    while lo < hi:
        mid = (lo + hi) >> 1
        if x < tf[off + mid]:
            hi = mid
        else:
            lo = mid + 1
    return min(max(lo - 1, 0), m - 2)


@compiled
def multilinear(tf: np.ndarray, ti: np.ndarray, fb: int, gi: int, q: np.ndarray) -> float:
    """A GRID table over k arguments at the model positions q: multi-linear over the
    rectilinear grid, the edge values held (docs/volumetric.md §3)."""
    k = ti[gi + G_K]
    off = fb + ti[gi + G_TAB]
    idx = np.zeros(MAXARGS, dtype=np.int64)
    fr = np.zeros(MAXARGS)
    at = off  # where the grid of argument d starts
    for d in range(k):
        m = ti[gi + G_DIM + d]
        v = q[ti[gi + G_ARG + d]]
        if ti[gi + G_SPL]:
            v = v % 360.0
        v = min(max(v, tf[at]), tf[at + m - 1])
        if m > 1:
            i = _right(tf, at, m, v)
            idx[d] = i
            fr[d] = (v - tf[at + i]) / (tf[at + i + 1] - tf[at + i])
        at += m
    values = at  # the values follow the grids, C order
    out = 0.0
    for corner in range(1 << k):
        w = 1.0
        flat = 0
        for d in range(k):
            m = ti[gi + G_DIM + d]
            up = (corner >> d) & 1
            if up and m == 1:
                w = w * 0.0
            w = w * (fr[d] if up else 1.0 - fr[d])
            flat = flat * m + min(idx[d] + up, m - 1)
        out += w * tf[values + flat]
    return out


@compiled
def scatter(tf: np.ndarray, ti: np.ndarray, fb: int, gi: int, q: np.ndarray) -> float:
    """SCATTER: inverse distance weighting, w = 1/d² over the arguments (mm, °); a
    record's own value at the record (docs/volumetric.md §6)."""
    k, m = ti[gi + G_K], ti[gi + G_M]
    pts = fb + ti[gi + G_TAB]
    vals = pts + m * k
    num = den = 0.0
    for r in range(m):
        d2 = 0.0
        for d in range(k):
            e = tf[pts + r * k + d] - q[ti[gi + G_ARG + d]]
            d2 += e * e
        if d2 == 0.0:
            return tf[vals + r]
        num += tf[vals + r] / d2
        den += 1.0 / d2
    return num / den


@compiled
def path(tf: np.ndarray, ti: np.ndarray, fb: int, gi: int, q: np.ndarray) -> float:
    """PATH, PATH_XY: the records in file order are the corners of a polygon; the value
    at its point nearest to the position (in the columns `G_PC`), linear along its
    section, the first section winning a tie, the end values beyond the ends (docs/
    volumetric.md §6)."""
    k, m, npc = ti[gi + G_K], ti[gi + G_M], ti[gi + G_NPC]
    pts = fb + ti[gi + G_TAB]
    vals = pts + m * k
    if m == 1:
        return tf[vals]
    best, value = math.inf, 0.0
    for s in range(m - 1):
        a, b = pts + s * k, pts + (s + 1) * k
        ll = 0.0
        dot = 0.0
        for j in range(npc):
            c = ti[gi + G_PC + j]
            ab = tf[b + c] - tf[a + c]
            ll += ab * ab
            dot += (q[ti[gi + G_ARG + c]] - tf[a + c]) * ab
        t = 0.0 if ll == 0.0 else dot / ll
        t = min(max(t, 0.0), 1.0)
        d2 = 0.0
        for j in range(npc):
            c = ti[gi + G_PC + j]
            e = tf[a + c] + t * (tf[b + c] - tf[a + c]) - q[ti[gi + G_ARG + c]]
            d2 += e * e
        if d2 < best:
            best, value = d2, tf[vals + s] + t * (tf[vals + s + 1] - tf[vals + s])
    return value


@compiled
def general(tf: np.ndarray, ti: np.ndarray, fb: int, gi: int, q: np.ndarray) -> float:
    """The value of the general table described at `gi` at the model positions q."""
    mode = ti[gi + G_MODE]
    if mode == GRID:
        return multilinear(tf, ti, fb, gi, q)
    if mode == SCATTER:
        return scatter(tf, ti, fb, gi, q)
    return path(tf, ti, fb, gi, q)


# ------------------------------------------------------------------ the model (compiled)


@compiled
def errors(
    tf: np.ndarray, ti: np.ndarray, fb: int, ib: int, i: int, q: np.ndarray
) -> tuple[float, ...]:
    """(δx, δy, δz, εa, εb, εc) (mm, rad) of chain axis i at the model positions q: its
    merged table (linear between the points, the edge values held; its argument modulo
    360° when spliced), its constants, then its general tables in their order; and
    (δ0x … ε0c), its position errors over arguments (004 p.32; 0 without: the
    constant ones are F_SH and F_TL)."""
    ai = ib + IHDR + AXI * i
    c = fb + FHDR + AXF * i + F_CONST
    off, m = fb + ti[ai + A_TAB], ti[ai + A_PTS]
    x = q[i]
    if ti[ai + A_SPL]:
        x = x % 360.0
    lo, hi = tf[off], tf[off + m - 1]
    key = lo if x < lo else hi if x > hi else x
    j = _right(tf, off, m, key)
    f = key - tf[off + j]
    v = off + m + 6 * j
    s = v + 6 * m
    e0 = tf[v] + f * tf[s] + tf[c]
    e1 = tf[v + 1] + f * tf[s + 1] + tf[c + 1]
    e2 = tf[v + 2] + f * tf[s + 2] + tf[c + 2]
    e3 = tf[v + 3] + f * tf[s + 3] + tf[c + 3]
    e4 = tf[v + 4] + f * tf[s + 4] + tf[c + 4]
    e5 = tf[v + 5] + f * tf[s + 5] + tf[c + 5]
    if ti[ib + NGEN] == 0:  # (no general table: nothing to allocate in the cycle)
        return e0, e1, e2, e3, e4, e5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    p = np.zeros(12)
    gi = ib + ti[ib + GEN]
    for _ in range(ti[ib + NGEN]):
        if ti[gi + G_AXIS] == i:
            p[ti[gi + G_COMP]] += general(tf, ti, fb, gi, q)
        gi += GENI
    return (
        e0 + p[0], e1 + p[1], e2 + p[2], e3 + p[3], e4 + p[4], e5 + p[5],
        p[6], p[7], p[8], p[9], p[10], p[11],
    )  # fmt: skip


@compiled
def rodrigues_of(x: float, y: float, z: float, angle: float) -> tuple[float, ...]:
    """I + sin·K + (1 − cos)·K² for the unit vector (x, y, z): K its cross-product
    matrix, K² = u·uᵀ − I."""
    s, c = math.sin(angle), 1.0 - math.cos(angle)
    return (
        1.0 + c * (x * x - 1.0), -s * z + c * x * y, s * y + c * x * z,
        s * z + c * x * y, 1.0 + c * (y * y - 1.0), -s * x + c * y * z,
        -s * y + c * x * z, s * x + c * y * z, 1.0 + c * (z * z - 1.0),
    )  # fmt: skip


@compiled
def transform(
    tf: np.ndarray, ti: np.ndarray, fb: int, ib: int, i: int, q: np.ndarray, with_errors: bool
) -> tuple[tuple[float, ...], tuple[float, float, float]]:
    """(R as 9 floats, t) of chain axis i at the model positions q, on the imperfect
    machine (`with_errors`) or the ideal one (docs/volumetric.md §2's table)."""
    a = fb + FHDR + AXF * i
    v, s = q[i], tf[a + F_SIGN]
    u = a + F_U
    if with_errors:
        e0, e1, e2, e3, e4, e5, p0, p1, p2, p3, p4, p5 = errors(tf, ti, fb, ib, i, q)
    else:
        e0 = e1 = e2 = e3 = e4 = e5 = p0 = p1 = p2 = p3 = p4 = p5 = 0.0
    if not ti[ib + IHDR + AXI * i + A_ROT]:
        if not with_errors:
            eye = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
            return eye, (s * v * tf[u], s * v * tf[u + 1], s * v * tf[u + 2])
        # s·Ω(ε0 + ε0(q))·u = s·Ω(ε0)·u + s·ε0(q) × u: the tilt over arguments added
        su, sv = a + F_SU, s * v
        return omega(e3, e4, e5), (
            v * tf[su] + sv * (p4 * tf[u + 2] - p5 * tf[u + 1]) + e0,
            v * tf[su + 1] + sv * (p5 * tf[u] - p3 * tf[u + 2]) + e1,
            v * tf[su + 2] + sv * (p3 * tf[u + 1] - p4 * tf[u]) + e2,
        )
    angle = math.radians(s * v)
    cx, cy, cz = tf[a + F_C], tf[a + F_C + 1], tf[a + F_C + 2]
    sh, tl = a + F_SH, a + F_TL
    if not with_errors:
        r = rodrigues(tf, a + F_K, a + F_K2, angle)
        dx = dy = dz = 0.0
    elif ti[ib + ALT]:
        if ti[ib + IHDR + AXI * i + A_VPOS]:  # the distorted axis here: Ω(ε0)·u, normalised
            ux, uy, uz = apply(
                omega(tf[tl] + p3, tf[tl + 1] + p4, tf[tl + 2] + p5), tf[u], tf[u + 1], tf[u + 2]
            )
            n = math.sqrt(ux * ux + uy * uy + uz * uz)
            r = mul(omega(e3, e4, e5), rodrigues_of(ux / n, uy / n, uz / n, angle))
        else:
            r = mul(omega(e3, e4, e5), rodrigues(tf, a + F_KT, a + F_KT2, angle))
        cx, cy, cz = cx + tf[sh] + p0, cy + tf[sh + 1] + p1, cz + tf[sh + 2] + p2
        dx, dy, dz = e0, e1, e2
    else:
        r = mul(
            omega(e3 + tf[tl] + p3, e4 + tf[tl + 1] + p4, e5 + tf[tl + 2] + p5),
            rodrigues(tf, a + F_K, a + F_K2, angle),
        )
        dx, dy, dz = tf[sh] + p0 + e0, tf[sh + 1] + p1 + e1, tf[sh + 2] + p2 + e2
    rx, ry, rz = apply(r, cx, cy, cz)
    return r, (cx + dx - rx, cy + dy - ry, cz + dz - rz)


@compiled
def forward(
    tf: np.ndarray,
    ti: np.ndarray,
    fb: int,
    ib: int,
    q: np.ndarray,
    x: float,
    y: float,
    z: float,
    with_errors: bool,
) -> tuple[float, float, float]:
    """The tool tip (x, y, z in the frame of the last axis) relative to the workpiece
    at the model positions q: the tool side from the tool inwards, then T_wp⁻¹ from the
    base outwards (docs/volumetric.md §2)."""
    n, w = ti[ib + N], ti[ib + W]
    for i in range(n - 1, w - 1, -1):
        r, t = transform(tf, ti, fb, ib, i, q, with_errors)
        rx, ry, rz = apply(r, x, y, z)
        x, y, z = t[0] + rx, t[1] + ry, t[2] + rz
    for i in range(w - 1, -1, -1):
        r, t = transform(tf, ti, fb, ib, i, q, with_errors)
        x, y, z = solve(r, x - t[0], y - t[1], z - t[2])
    return x, y, z


@compiled
def jacobian(
    tf: np.ndarray, ti: np.ndarray, fb: int, ib: int, q: np.ndarray, x: float, y: float, z: float
) -> tuple[float, ...]:
    """∂p_nom/∂(x, y, z) at the model positions q (9 floats, row by row): the ideal
    machine is affine in its linear axes, so a unit step of each is exact."""
    bx, by, bz = forward(tf, ti, fb, ib, q, x, y, z, False)
    moved = q.copy()
    i = ti[ib + LIN]
    moved[i] += 1.0
    ax, ay, az = forward(tf, ti, fb, ib, moved, x, y, z, False)
    moved[i] = q[i]
    i = ti[ib + LIN + 1]
    moved[i] += 1.0
    bx2, by2, bz2 = forward(tf, ti, fb, ib, moved, x, y, z, False)
    moved[i] = q[i]
    i = ti[ib + LIN + 2]
    moved[i] += 1.0
    cx, cy, cz = forward(tf, ti, fb, ib, moved, x, y, z, False)
    return (
        ax - bx, bx2 - bx, cx - bx,
        ay - by, by2 - by, cy - by,
        az - bz, bz2 - bz, cz - bz,
    )  # fmt: skip


@compiled
def correction(
    tf: np.ndarray,
    ti: np.ndarray,
    fb: int,
    ib: int,
    q: np.ndarray,
    x: float,
    y: float,
    z: float,
    out: np.ndarray,
) -> None:
    """`out` [Δx, Δy, Δz] (mm): the correction of the linear axes at the programmed
    positions q (chain order, mm and °) for the tool point (x, y, z), such that
    p_act(q + Δ) = p_nom(q) (docs/volumetric.md §2): two Newton steps with the ideal
    machine's Jacobian (constant without rotary axes), the tables looked up at the
    corrected positions."""
    n = ti[ib + N]
    qs = np.empty(n)
    for i in range(n):
        qs[i] = q[i] + tf[fb + FHDR + AXF * i + F_OFF]
    nx, ny, nz = forward(tf, ti, fb, ib, qs, x, y, z, False)
    if ti[ib + ROT_ANY]:
        jac = jacobian(tf, ti, fb, ib, qs, x, y, z)
    else:
        j = fb + JAC
        jac = (
            tf[j], tf[j + 1], tf[j + 2], tf[j + 3], tf[j + 4], tf[j + 5], tf[j + 6],
            tf[j + 7], tf[j + 8],
        )  # fmt: skip
    lx, ly, lz = ti[ib + LIN], ti[ib + LIN + 1], ti[ib + LIN + 2]
    moved = qs.copy()
    dx = dy = dz = 0.0
    for _ in range(STEPS):
        moved[lx], moved[ly], moved[lz] = qs[lx] + dx, qs[ly] + dy, qs[lz] + dz
        ax, ay, az = forward(tf, ti, fb, ib, moved, x, y, z, True)
        sx, sy, sz = solve(jac, nx - ax, ny - ay, nz - az)
        dx, dy, dz = dx + sx, dy + sy, dz + sz
    out[0], out[1], out[2] = dx, dy, dz


@compiled
def corrections(
    tf: np.ndarray, ti: np.ndarray, q: np.ndarray, tip: np.ndarray, out: np.ndarray
) -> None:
    """`correction` at every row of q [b, n] (programmed positions) into out [b, 3]."""
    for r in range(q.shape[0]):
        correction(tf, ti, 0, 0, q[r], tip[0], tip[1], tip[2], out[r])


@compiled
def forwards(
    tf: np.ndarray,
    ti: np.ndarray,
    q: np.ndarray,
    tip: np.ndarray,
    with_errors: bool,
    out: np.ndarray,
) -> None:
    """`forward` at every row of q [b, n] (model positions) into out [b, 3]."""
    for r in range(q.shape[0]):
        out[r, 0], out[r, 1], out[r, 2] = forward(
            tf, ti, 0, 0, q[r], tip[0], tip[1], tip[2], with_errors
        )


__all__ = ["STEPS", "correction", "corrections", "forward", "forwards", "pack"]
