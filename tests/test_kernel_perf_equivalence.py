"""Pieces of the fast kernel's optimisations against their readable counterparts.

`test_kernel_equivalence.py` compares whole kernels; these tests aim at the places where
the fast kernel computes something differently: crosstalk mode 3 as convex regions with
affine values (vs `triangulation.evaluate`), its scalar fallback for unusual hulls, the
merged complex-keyed table (vs the reference `interp`) and the sin² weight table.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.machines import Motion, random_machine
from support.reference import ReferenceKernel, interp

from geo_server.kernel import Kernel
from geo_server.kernel import crosstalk as kmod
from geo_server.kernel.sin2 import Sin2Filter
from geo_server.kernel.tables import Lookup, MergedTable
from geo_server.kernel.triangulation import INSIDE_EPS, evaluate, triangulate


def region_value(regions: list, x: float, y: float, col: int) -> float:
    for halves, value in regions:
        if min(a * x + b * y + c for a, b, c in halves) >= -INSIDE_EPS:
            a, b, c = value[col]
            return a * x + b * y + c
    raise AssertionError("point in no region")


POINT_SETS = {
    "random": lambda rng: rng.uniform(-4e6, 4e6, (15, 2)).round(),
    "grid": lambda rng: np.array([(x, y) for y in (0, 1.5e6, 3e6) for x in (0, 1.5e6, 3e6)]),
    "collinear": lambda rng: np.array([(0.0, 0.0), (2e6, 1e6), (-2e6, -1e6), (4e6, 2e6)]),
    "single": lambda rng: np.array([(1e6, -1e6)]),
    "triangle": lambda rng: np.array([(0.0, 0.0), (1e6, 0.0), (0.0, 1e6)]),
}


@pytest.mark.parametrize("kind", sorted(POINT_SETS))
@pytest.mark.parametrize("seed", range(4))
def test_mode3_regions_equal_evaluate(kind: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = POINT_SETS[kind](rng)
    vals = rng.normal(0, 40, (len(pts), 4)).round()
    tri = triangulate(tuple((float(x), float(y)) for x, y in pts))
    regions = kmod._regions(tri, vals)
    assert regions is not None
    queries = np.concatenate(
        [
            rng.uniform(-1e7, 1e7, (400, 2)),
            pts + rng.normal(0, 1.0, pts.shape),  # near the test points
            pts,  # on them
        ]
    )
    for x, y in queries:
        for col in range(4):
            want = evaluate(tri, list(vals[:, col]), float(x), float(y))
            assert region_value(regions, float(x), float(y), col) == pytest.approx(want, abs=1e-9)


def test_mode3_scalar_fallback_equals_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rows whose hull is not a plain convex cycle use the scalar `evaluate`."""
    monkeypatch.setattr(kmod, "_hull_cycle", lambda tri: None)
    n = 6
    for seed in range(3):
        cfg = random_machine(n, seed)
        fast, ref = Kernel(cfg), ReferenceKernel(cfg)
        m = Motion(n, seed)
        for _ in range(300):
            m.step()
            fast.step(m.pos, m.vel, m.acc, m.homed, m.reversal)
            ref.step(m.pos, m.vel, m.acc, m.homed, m.reversal)
            np.testing.assert_allclose(fast.actual, ref.actual, rtol=0, atol=1e-9)
            np.testing.assert_allclose(fast.target, ref.target, rtol=0, atol=1e-9)


def test_merged_table_equals_interp() -> None:
    rng = np.random.default_rng(7)
    rows = []
    for _ in range(30):
        m = int(rng.integers(1, 12))
        x = np.sort(rng.uniform(-1e6, 1e6, m)).round()
        x = np.unique(x)
        rows.append((x, rng.normal(0, 50, len(x))))
    table = MergedTable(rows)
    r = np.repeat(np.arange(len(rows)), 50)
    lk = Lookup(table, r.astype(float))
    lk.q[:] = rng.uniform(-1.5e6, 1.5e6, len(r))
    # exact knots, their neighbours and the edges
    for j, (x, _) in enumerate(rows):
        lk.q[j * 50 : j * 50 + len(x)] = x
        lk.q[j * 50 + 20] = np.nextafter(x[0], -np.inf)
        lk.q[j * 50 + 21] = np.nextafter(x[-1], np.inf)
    out = np.zeros(len(r))
    lk(out)
    for i, (row, q) in enumerate(zip(r, lk.q, strict=True)):
        x, y = rows[row]
        assert out[i] == pytest.approx(interp(list(x), list(y), float(q)), abs=1e-9)


def test_sin2_weight_table_is_bit_identical() -> None:
    ns = np.array([[0, 1, 2, 7, 20]])
    f = Sin2Filter(ns)
    ev = np.ones(ns.shape, dtype=bool)
    for k in range(1, 25):
        f.advance(ev if k == 1 else ~ev)
        for j, n in enumerate(ns[0]):
            want = 0.0 if n == 0 else math.cos(math.pi * min(k, n) / (2 * n)) ** 2
            assert f.w[0, j] == want


def test_sin2_successor_table_restarts_and_reloads() -> None:
    """The successor table (k ← min(k + 1, N) in one gather) against the plain rule,
    with events at random cycles and a reload to new lengths mid-ramp."""
    rng = np.random.default_rng(3)
    ns = np.array([[0, 1, 2, 3, 7, 20, 20]])
    f = Sin2Filter(ns)
    k = ns.copy()  # idle: saturated
    for cycle in range(120):
        if cycle == 60:
            ns = np.array([[5, 0, 2, 1, 30, 7, 20]])
            f.set_n(ns)
            k = np.minimum(k, np.maximum(ns, 0))
        ev = rng.random(ns.shape) < 0.1
        f.advance(ev)
        k = np.minimum(np.where(ev, 0, k) + 1, np.maximum(ns, 0))
        want = [
            0.0 if n == 0 else math.cos(math.pi * kk / (2 * n)) ** 2
            for kk, n in zip(k[0], ns[0], strict=True)
        ]
        assert list(f.w[0]) == want


def test_lsec_rows_follow_direction_without_dneg() -> None:
    """LSEC picks its pos/neg row from the direction gathered out of S (row 3j + 1 ± 1):
    a bilateral table must follow every reversal like the reference."""
    cfg = random_machine(6, 11)
    fast, ref = Kernel(cfg), ReferenceKernel(cfg)
    m = Motion(6, seed=5)
    for _ in range(400):
        m.step()
        for k in (fast, ref):
            k.step(m.pos, m.vel, m.acc, m.homed, m.reversal)
        np.testing.assert_allclose(fast.actual, ref.actual, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fast.total_offset, ref.total_offset, rtol=0, atol=1e-9)
