"""Delaunay triangulation of the crosstalk mode-3 test points (000 §4.6, p.84).

The manual only says "surface interpolation" over up to 15 measurement tests;
docs/design.md §12 fixes it as piecewise-linear interpolation over the Delaunay
triangulation, and outside the convex hull the value at the nearest hull point.

For ≤ 15 points an exact brute-force construction is both small and robust, so this is
used instead of an incremental Bowyer–Watson (whose finite super-triangle can drop
triangles at the convex hull): every non-degenerate triple whose circumcircle contains no
other point strictly inside is a Delaunay candidate; co-circular points (a regular grid,
like the manual's 9-point mode-3 example) give overlapping candidates, which are
resolved greedily in a fixed order (first non-overlapping wins). All predicates run on
exact Python integers (the float coordinates are scaled by a common power of two).

`Triangulation` holds, per triangle, affine barycentric coefficients λ_v = a·x + b·y + c
and, per hull edge, the data for projecting a point onto it; both kernels evaluate the
same coefficients.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import lru_cache

#: A point counts as inside a triangle when every barycentric coordinate ≥ −INSIDE_EPS.
INSIDE_EPS = 1e-12


@dataclass(frozen=True)
class Triangulation:
    """Triangles and hull edges of a point set (indices into the input points)."""

    points: tuple[tuple[float, float], ...]
    triangles: tuple[tuple[int, int, int], ...]  # counter-clockwise vertex indices
    #: per triangle: ((a0, b0, c0), (a1, b1, c1), (a2, b2, c2)), λ_v = a_v·x + b_v·y + c_v
    bary: tuple[tuple[tuple[float, float, float], ...], ...]
    edges: tuple[tuple[int, int], ...]  # hull edges (collinear sets: consecutive points)
    #: per edge: (ax, ay, dx, dy, inv_len2) with inv_len2 = 0 for a degenerate edge
    edge_geom: tuple[tuple[float, float, float, float, float], ...]


def _to_ints(points: list[tuple[float, float]]) -> list[tuple[int, int]]:
    """Exact integer images of float coordinates (common power-of-two scale)."""
    ratios = [(float(x).as_integer_ratio(), float(y).as_integer_ratio()) for x, y in points]
    den = 1
    for (_, dx), (_, dy) in ratios:
        den = max(den, dx, dy)  # denominators are powers of two: the max is a multiple
    return [(nx * (den // dx), ny * (den // dy)) for (nx, dx), (ny, dy) in ratios]


def _orient(a: tuple[int, int], b: tuple[int, int], c: tuple[int, int]) -> int:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _in_circle(
    a: tuple[int, int], b: tuple[int, int], c: tuple[int, int], d: tuple[int, int]
) -> int:
    """> 0 when d lies strictly inside the circumcircle of the CCW triangle abc."""
    rows = []
    for p in (a, b, c):
        dx, dy = p[0] - d[0], p[1] - d[1]
        rows.append((dx, dy, dx * dx + dy * dy))
    (a1, a2, a3), (b1, b2, b3), (c1, c2, c3) = rows
    return a1 * (b2 * c3 - b3 * c2) - a2 * (b1 * c3 - b3 * c1) + a3 * (b1 * c2 - b2 * c1)


def _overlap(t: tuple[int, int, int], u: tuple[int, int, int], p: list[tuple[int, int]]) -> bool:
    """Do the interiors of two CCW triangles intersect? (separating-axis test, exact)"""
    for s, o in ((t, u), (u, t)):
        for k in range(3):
            a, b = p[s[k]], p[s[(k + 1) % 3]]
            if all(_orient(a, b, p[v]) <= 0 for v in o):
                return False
    return True


@lru_cache(maxsize=256)
def triangulate(points: tuple[tuple[float, float], ...]) -> Triangulation:
    """Delaunay triangulation with hull edges and evaluation coefficients.

    Duplicate points keep their first occurrence (the later ones are unreachable).
    Fewer than three non-collinear points give no triangles; the "hull" is then the chain
    of consecutive points along the line (a single point: one degenerate edge).
    """
    pts = [(float(x), float(y)) for x, y in points]
    ip = _to_ints(pts)
    uniq: list[int] = []
    seen: set[tuple[int, int]] = set()
    for i, q in enumerate(ip):
        if q not in seen:
            seen.add(q)
            uniq.append(i)
    tris: list[tuple[int, int, int]] = []
    for i, j, k in itertools.combinations(uniq, 3):
        o = _orient(ip[i], ip[j], ip[k])
        if o == 0:
            continue
        tri = (i, j, k) if o > 0 else (i, k, j)
        if any(
            _in_circle(ip[tri[0]], ip[tri[1]], ip[tri[2]], ip[m]) > 0 for m in uniq if m not in tri
        ):
            continue
        if any(_overlap(tri, t, ip) for t in tris):
            continue
        tris.append(tri)
    if tris:
        count: dict[tuple[int, int], int] = {}
        for t in tris:
            for k in range(3):
                e = (t[k], t[(k + 1) % 3])
                key = (min(e), max(e))
                count[key] = count.get(key, 0) + 1
        edges = []
        for t in tris:  # keep the CCW orientation of the owning triangle
            for k in range(3):
                e = (t[k], t[(k + 1) % 3])
                if count[(min(e), max(e))] == 1:
                    edges.append(e)
    else:
        order = sorted(uniq, key=lambda i: ip[i])
        edges = list(itertools.pairwise(order)) if len(order) > 1 else [(order[0], order[0])]
    bary = tuple(_bary(pts, t) for t in tris)
    geom = []
    for a, b in edges:
        ax, ay = pts[a]
        dx, dy = pts[b][0] - ax, pts[b][1] - ay
        len2 = dx * dx + dy * dy
        geom.append((ax, ay, dx, dy, 1.0 / len2 if len2 > 0 else 0.0))
    return Triangulation(tuple(pts), tuple(tris), bary, tuple(edges), tuple(geom))


def _bary(
    pts: list[tuple[float, float]], t: tuple[int, int, int]
) -> tuple[tuple[float, float, float], ...]:
    (ax, ay), (bx, by), (cx, cy) = (pts[v] for v in t)
    det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
    a1, b1 = (cy - ay) / det, -(cx - ax) / det  # λ of vertex 1
    a2, b2 = -(by - ay) / det, (bx - ax) / det  # λ of vertex 2
    c1 = -(a1 * ax + b1 * ay)
    c2 = -(a2 * ax + b2 * ay)
    return ((-a1 - a2, -b1 - b2, 1.0 - c1 - c2), (a1, b1, c1), (a2, b2, c2))


def evaluate(tri: Triangulation, values: list[float], x: float, y: float) -> float:
    """Piecewise-linear value at (x, y); outside the hull the nearest hull point's value.

    Readable scalar version (the reference kernel and tests use it).
    """
    for t, coef in zip(tri.triangles, tri.bary, strict=True):
        lam = [a * x + b * y + c for a, b, c in coef]
        if min(lam) >= -INSIDE_EPS:
            return lam[0] * values[t[0]] + lam[1] * values[t[1]] + lam[2] * values[t[2]]
    best = math.inf
    result = 0.0
    for (a, b), (ax, ay, dx, dy, inv) in zip(tri.edges, tri.edge_geom, strict=True):
        s = ((x - ax) * dx + (y - ay) * dy) * inv
        s = min(max(s, 0.0), 1.0)
        ex, ey = x - (ax + s * dx), y - (ay + s * dy)
        d2 = ex * ex + ey * ey
        if d2 < best:
            best = d2
            result = values[a] + s * (values[b] - values[a])
    return result
