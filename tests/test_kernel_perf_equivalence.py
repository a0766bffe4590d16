"""Pieces of the compiled kernel against their readable counterparts.

`test_kernel_equivalence.py` compares whole kernels; these tests aim at the pieces the
compiled cycle computes its own way: the mode-3 evaluation over packed triangles and
edges (vs `triangulation.evaluate`), the 1-D table law with its binary search (vs the
reference `interp`), the sin² weight table (vs the cosine) and LSEC's table per
direction.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.machines import Motion, random_machine
from support.reference import ReferenceKernel, interp

from geo_server.kernel import Kernel, crosstalk, sin2, step
from geo_server.kernel.tables import Packer
from geo_server.kernel.tables import interp as compiled_interp
from geo_server.kernel.triangulation import evaluate, triangulate
from geo_server.model import CrosstalkComp

POINT_SETS = {
    "random": lambda rng: rng.uniform(-4e6, 4e6, (15, 2)).round(),
    "grid": lambda rng: np.array([(x, y) for y in (0, 1.5e6, 3e6) for x in (0, 1.5e6, 3e6)]),
    "collinear": lambda rng: np.array([(0.0, 0.0), (2e6, 1e6), (-2e6, -1e6), (4e6, 2e6)]),
    "single": lambda rng: np.array([(1e6, -1e6)]),
    "triangle": lambda rng: np.array([(0.0, 0.0), (1e6, 0.0), (0.0, 1e6)]),
    "concave": lambda rng: np.array([(0.0, 0.0), (4e6, 0.0), (4e6, 4e6), (2e6, 1e6), (0.0, 4e6)]),
}


@pytest.mark.parametrize("kind", sorted(POINT_SETS))
@pytest.mark.parametrize("seed", range(4))
def test_mode3_compiled_equals_evaluate(kind: str, seed: int) -> None:
    """The same formula on the same coefficients, in the same order: equal, bit for bit."""
    rng = np.random.default_rng(seed)
    pts = POINT_SETS[kind](rng)
    vals = rng.normal(0, 40, (len(pts), 4)).round()
    x = CrosstalkComp("new", 1, mode=3, ax_1=pts[:, 0], ax_2=pts[:, 1], corrections=vals)
    tab = Packer()
    kind_, off, m, t, nt, e, ne = crosstalk.pack(x, tab)
    packed = tab.done()
    assert kind_ == crosstalk.MODE3
    tri = triangulate(tuple((float(a), float(b)) for a, b in pts))
    queries = np.concatenate(
        [
            rng.uniform(-1e7, 1e7, (400, 2)),
            pts + rng.normal(0, 1.0, pts.shape),  # near the test points
            pts,  # on them
        ]
    )
    for qx, qy in queries:
        for col in range(4):
            want = evaluate(tri, list(vals[:, col]), float(qx), float(qy))
            got = crosstalk.evaluate(packed, off + col * m, t, nt, e, ne, float(qx), float(qy))
            assert got == want


def test_compiled_interp_equals_interp() -> None:
    """The binary search and the formula of the reference; the held edges exact."""
    rng = np.random.default_rng(7)
    for _ in range(30):
        m = int(rng.integers(1, 12))
        x = np.unique(np.sort(rng.uniform(-1e6, 1e6, m)).round())
        y = rng.normal(0, 50, len(x))
        tab = Packer()
        off = tab.table(x, y)
        packed = tab.done()
        qs = list(rng.uniform(-1.5e6, 1.5e6, 50)) + list(x)  # the knots themselves
        qs += [np.nextafter(x[0], -np.inf), np.nextafter(x[-1], np.inf), x[0], x[-1]]
        for q in qs:
            got = compiled_interp(packed, off, len(x), float(q))
            assert got == pytest.approx(interp(list(x), list(y), float(q)), abs=1e-9)
            if q <= x[0]:
                assert got == y[0]
            elif q >= x[-1]:
                assert got == y[-1]


def test_sin2_weight_table_is_bit_identical() -> None:
    ns = np.array([[0, 1, 2, 7, 20]])
    table, off = sin2.weights(ns)
    for j, n in enumerate(ns[0]):
        for k in range(n + 1):
            want = 0.0 if n == 0 else math.cos(math.pi * k / (2 * n)) ** 2
            assert table[off[0, j] + k] == want


def test_sin2_restarts_and_reloads() -> None:
    """The filter's k ← min(k + 1, N) and J ← target − previous output on an event,
    against the plain rule, with events at random cycles and new lengths mid-ramp."""
    rng = np.random.default_rng(3)
    ns = [0, 1, 2, 3, 7, 20, 20]
    table, off = sin2.weights(np.array([ns]))
    k = list(ns)
    jump = [0.0] * len(ns)
    prev = [0.0] * len(ns)
    for cycle in range(120):
        if cycle == 60:
            ns = [5, 0, 2, 1, 30, 7, 20]
            table, off = sin2.weights(np.array([ns]))
            k = [min(a, b) for a, b in zip(k, ns, strict=True)]
        for j, n in enumerate(ns):
            ev = bool(rng.random() < 0.1)
            target = float(rng.normal(0, 100))
            out, k2, j2 = sin2.output(target, prev[j], ev, k[j], n, jump[j], table, off[0, j])
            if ev:
                jump[j], k[j] = target - prev[j], 0
            k[j] = min(k[j] + 1, n)
            w = 0.0 if n == 0 else math.cos(math.pi * k[j] / (2 * n)) ** 2
            assert (out, k2, j2) == (target - jump[j] * w, k[j], jump[j])
            prev[j] = out


def test_lsec_tables_follow_direction() -> None:
    """LSEC picks its table per direction: a bilateral table must follow every reversal
    like the reference."""
    cfg = random_machine(6, 11)
    fast, ref = Kernel(cfg), ReferenceKernel(cfg)
    m = Motion(6, seed=5)
    for _ in range(400):
        m.step()
        for k in (fast, ref):
            k.step(m.pos, m.vel, m.acc, m.homed, m.reversal)
        np.testing.assert_allclose(fast.actual, ref.actual, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fast.total_offset, ref.total_offset, rtol=0, atol=1e-9)


def test_temperature_law_compiled_once() -> None:
    """The kernel compiles the module's own law (`temperature.offset`), not a copy."""
    assert step._offset.py_func is step.temperature.offset
