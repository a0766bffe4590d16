"""Delaunay triangulation for crosstalk mode 3 (000 §4.6 p.84; docs/design.md §12)."""

from __future__ import annotations

import itertools
import os
import random
import subprocess
import sys

import pytest

from geo_server.kernel.triangulation import evaluate, triangulate


def _area2(p: tuple[float, float], q: tuple[float, float], r: tuple[float, float]) -> float:
    return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])


def _hull_size(points: list[tuple[float, float]]) -> int:
    """Points on the convex hull (collinear boundary points included), by brute force."""
    count = 0
    for p in points:
        others = [q for q in points if q != p]
        on_hull = False
        for q in others:  # p is on the hull iff some line through p has all points on one side
            for sign in (1, -1):
                if all(sign * _area2(p, q, r) >= 0 for r in others):
                    on_hull = True
        count += on_hull
    return count


def test_manual_mode3_grid() -> None:
    # 000 p.92: 9 measuring points, ax_1/ax_2 from (0, 0) to (3000, 3000)
    pts = tuple((float(x), float(y)) for y in (0, 1500, 3000) for x in (0, 1500, 3000))
    t = triangulate(pts)
    assert len(t.triangles) == 8  # 2n − 2 − h with n 9, h 8
    assert len(t.edges) == 8
    for tri in t.triangles:
        assert _area2(*(pts[v] for v in tri)) > 0  # counter-clockwise, non-degenerate
    # a plane is reproduced exactly, whatever the diagonals
    vals = [2 * x - y / 3 + 7 for x, y in pts]
    assert evaluate(t, vals, 1234.0, 2345.0) == pytest.approx(2 * 1234 - 2345 / 3 + 7)


@pytest.mark.parametrize("seed", range(5))
def test_random_points_are_delaunay(seed: int) -> None:
    rng = random.Random(seed)
    pts = [(float(rng.randint(0, 10000)), float(rng.randint(0, 10000))) for _ in range(15)]
    t = triangulate(tuple(pts))
    h = _hull_size(pts)
    assert len(t.triangles) == 2 * len(pts) - 2 - h
    assert len(t.edges) == h
    # empty circumcircle property, checked with the explicit formula
    for a, b, c in t.triangles:
        (ax, ay), (bx, by), (cx, cy) = pts[a], pts[b], pts[c]
        d = 2 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
        ux = (
            (ax**2 + ay**2) * (by - cy) + (bx**2 + by**2) * (cy - ay) + (cx**2 + cy**2) * (ay - by)
        ) / d
        uy = (
            (ax**2 + ay**2) * (cx - bx) + (bx**2 + by**2) * (ax - cx) + (cx**2 + cy**2) * (bx - ax)
        ) / d
        r2 = (ax - ux) ** 2 + (ay - uy) ** 2
        for i, (px, py) in enumerate(pts):
            if i not in (a, b, c):
                assert (px - ux) ** 2 + (py - uy) ** 2 >= r2 * (1 - 1e-9)
    # triangles do not overlap: their areas add up to the hull area
    total = sum(_area2(*(pts[v] for v in tri)) for tri in t.triangles)
    hull_area = max(
        abs(_area2(p, q, r)) for p, q, r in itertools.combinations(pts, 3)
    )  # a lower bound sanity check only
    assert total >= hull_area


def test_degenerate_sets() -> None:
    one = triangulate(((5.0, 5.0),))
    assert evaluate(one, [42.0], 100.0, -3.0) == 42.0
    line = triangulate(((0.0, 0.0), (2000.0, 0.0), (1000.0, 0.0)))
    assert not line.triangles
    # values 0 at x 0, 10 at x 1000, 30 at x 2000: projected onto the line
    assert evaluate(line, [0.0, 30.0, 10.0], 1500.0, 800.0) == pytest.approx(20.0)
    dup = triangulate(((0.0, 0.0), (0.0, 0.0), (10.0, 0.0), (0.0, 10.0)))
    assert len(dup.triangles) == 1


def test_manual_grid_tie_break_is_fixed_across_runs() -> None:
    """docs/design.md §12 "mode 3": on the manual's co-circular 9-point grid (000 p.92)
    every cell is cut from its (ax_1 max, ax_2 min) to its (ax_1 min, ax_2 max) corner,
    decided by the record order only: the same triangles in fresh interpreters with
    different hash seeds."""
    want = [(0, 1, 3), (1, 2, 4), (1, 4, 3), (2, 5, 4), (3, 4, 6), (4, 5, 7), (4, 7, 6), (5, 8, 7)]
    pts = tuple((float(x), float(y)) for y in (0, 1500, 3000) for x in (0, 1500, 3000))
    assert [tuple(t) for t in triangulate(pts).triangles] == want
    code = (
        "from geo_server.kernel.triangulation import triangulate\n"
        f"print(list(triangulate({pts!r}).triangles))"
    )
    for seed in ("0", "1", "12345"):
        env = {**os.environ, "PYTHONHASHSEED": seed}
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60
        )
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == str(want)
