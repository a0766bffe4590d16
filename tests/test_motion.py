"""Motion profiles (docs/design.md §5): hand-computed trapezoids, synchronisation, queue, modulo.

Reference axis: v_max 10000 units/s (1 mm/s), a_max 1 mm/s² = 10000 units/s², dt 1 ms.
A 20000-unit move then accelerates 1 s (5000 units), cruises 1 s (10000 units) and
decelerates 1 s (5000 units): 3000 cycles.
"""

from __future__ import annotations

import numpy as np
import pytest

from geo_server.machine.motion import Motion, MotionError
from geo_server.model import AxisParams

DT = 0.001


def axis(nr: int, v: float = 10_000.0, a: float = 1.0, **kw) -> AxisParams:
    return AxisParams(log_nr=nr, name="XYZC"[nr - 1], v_max=v, a_max=a, **kw)


def run(m: Motion, cycles: int) -> None:
    for _ in range(cycles):
        m.step()


def approx(x: float):
    return pytest.approx(x, rel=1e-12, abs=1e-9)


def test_trapezoid_positions_velocities_and_exact_end():
    m = Motion([axis(1)], DT)
    assert m.move_to(0, 20_000.0) == 3000
    expected = {
        500: (1250.0, 5000.0, 10_000.0),
        1500: (10_000.0, 10_000.0, 0.0),
        2500: (18_750.0, 5000.0, -10_000.0),
    }
    for k in range(1, 3001):
        m.step()
        if k in expected:
            p, v, a = expected[k]
            assert (m.pos[0], m.vel[0], m.acc[0]) == (approx(p), approx(v), approx(a))
        if k < 3000:
            assert not m.in_position(0)
            assert m.pos[0] < 20_000.0
    assert m.in_position(0)
    assert (m.pos[0], m.vel[0], m.acc[0]) == (20_000.0, 0.0, 0.0)
    run(m, 5)
    assert m.pos[0] == 20_000.0


def test_triangular_profile_when_short():
    m = Motion([axis(1)], DT)
    # 2500 units at 10000 units/s²: ta = sqrt(0.25) = 0.5 s, peak 5000 units/s < v_max
    assert m.move_to(0, 2500.0) == 1000
    run(m, 500)
    assert (m.pos[0], m.vel[0]) == (approx(1250.0), approx(5000.0))
    run(m, 500)
    assert m.pos[0] == 2500.0 and m.in_position(0)


def test_negative_move_velocity_sign_and_direction_holds():
    m = Motion([axis(1)], DT)
    m.move_to(0, -20_000.0)
    run(m, 1500)
    assert m.pos[0] == approx(-10_000.0) and m.vel[0] == approx(-10_000.0)
    assert m.direction(0) == -1
    run(m, 1500)
    assert m.pos[0] == -20_000.0 and m.vel[0] == 0.0 and m.direction(0) == -1


def test_feed_limits_and_clamps_to_v_max():
    m = Motion([axis(1)], DT)
    # feed 5000: ta 0.5 s, T = 20000/5000 + 0.5 = 4.5 s
    assert m.move_to(0, 20_000.0, feed=5000.0) == 4500
    run(m, 4500)
    assert m.move_to(0, 40_000.0, feed=1e9) == 3000  # clamped to v_max
    with pytest.raises(MotionError):
        m.move_to(0, 0.0)  # still moving
    run(m, 3000)
    with pytest.raises(MotionError):
        m.move_to(0, 0.0, feed=0.0)


def test_g01_synchronised_straight_line():
    m = Motion([axis(1, v=1e6), axis(2, v=1e6)], DT)
    # L = 50000 at path feed 5000 units/s; path accel min(10000·5/3, 10000·5/4) = 12500
    # ta = 0.4 s, T = 10 + 0.4 = 10.4 s
    assert m.move_linear({0: 30_000.0, 1: 40_000.0}, feed=5000.0) == 10_400
    for k in range(1, 10_401):
        m.step()
        assert m.pos[1] * 3.0 == approx(m.pos[0] * 4.0)
        assert abs(m.acc[1]) <= 10_000.0 * (1 + 1e-12)
        if k == 5000:
            assert (m.vel[0], m.vel[1]) == (approx(3000.0), approx(4000.0))
        if k < 10_400:
            assert not m.all_in_position([0, 1])
    assert (m.pos[0], m.pos[1]) == (30_000.0, 40_000.0)
    assert m.all_in_position()


def test_g00_slowest_axis_governs():
    m = Motion([axis(1, v=3000.0), axis(2, v=1e6)], DT)
    # X may only do 3000 units/s -> path 5000 units/s, as above
    assert m.move_linear({0: 30_000.0, 1: 40_000.0}, feed=None, rapid=True) == 10_400
    peak = 0.0
    for _ in range(10_400):
        m.step()
        peak = max(peak, abs(m.vel[0]))
    assert peak == approx(3000.0)
    assert (m.pos[0], m.pos[1]) == (30_000.0, 40_000.0)


def test_axis_without_distance_does_not_move():
    m = Motion([axis(1), axis(2)], DT)
    assert m.move_linear({0: 0.0, 1: 2500.0}, feed=None) == 1000
    assert m.in_position(0) and not m.in_position(1)
    assert m.move_linear({0: 0.0}, feed=100.0) == 0


def test_set_position_and_home():
    m = Motion([axis(1, start_position=7.0)], DT)
    assert m.pos[0] == 7.0 and not m.homed[0]
    m.move_to(0, 20_000.0)
    run(m, 10)
    m.set_position(0, 123.0)
    assert m.in_position(0) and m.pos[0] == 123.0 and m.vel[0] == 0.0
    run(m, 10)
    assert m.pos[0] == 123.0
    m.home(0)
    assert m.homed[0] and m.pos[0] == 123.0


def test_controlled_stop_from_cruise():
    m = Motion([axis(1)], DT)
    m.move_to(0, 100_000.0)
    run(m, 1500)  # cruising at 10000 units/s, pos 10000
    m.stop(0)
    # decelerate 10000 units/s² for 1 s: 5000 units more
    assert m.target[0] == approx(15_000.0)
    run(m, 500)
    assert (m.pos[0], m.vel[0], m.acc[0]) == (approx(13_750.0), approx(5000.0), approx(-1e4))
    run(m, 500)
    assert m.pos[0] == m.target[0] and m.in_position(0)


def test_queue_next_and_reversal_in():
    m = Motion([axis(1), axis(2)], DT)
    out = np.zeros(2, dtype=np.int64)
    m.reversal_in(out)
    assert out.tolist() == [-1, -1]
    m.move_to(0, 20_000.0)
    m.queue_next(0, 0.0)  # goes back: reversal when the first move ends
    run(m, 1000)
    m.reversal_in(out)
    assert out.tolist() == [2000, -1]
    run(m, 2000)  # arrives; the queued move is planned in the same cycle
    assert m.pos[0] == 20_000.0 and m.vel[0] == 0.0 and not m.in_position(0)
    m.reversal_in(out)
    assert out.tolist() == [-1, -1]
    run(m, 3000)
    assert m.pos[0] == 0.0 and m.in_position(0) and m.direction(0) == -1


def test_announce_next_same_direction_and_at_rest():
    m = Motion([axis(1)], DT)
    out = np.zeros(1, dtype=np.int64)
    m.move_to(0, 2500.0)
    m.announce_next(0, +1)
    m.reversal_in(out)
    assert out[0] == -1
    m.announce_next(0, -1)
    run(m, 400)
    m.reversal_in(out)
    assert out[0] == 600
    run(m, 600)
    m.reversal_in(out)
    assert out[0] == 0  # at rest, the next move reverses
    m.move_to(0, 0.0)
    m.reversal_in(out)
    assert out[0] == -1


def test_modulo_display_wraps_command_stays_unwrapped():
    c = axis(4, kind="R", modulo=True, modulo_period=3_600_000.0)
    m = Motion([axis(1), c], DT)
    m.set_position(0, -100.0)
    m.set_position(1, -100.0)
    assert m.display_pos().tolist() == [-100.0, 3_599_900.0]
    m.set_position(1, 2 * 3_600_000.0 + 5.0)
    out = np.empty(2)
    m.display_pos(out)
    assert out[1] == 5.0 and m.pos[1] == 7_200_005.0
    m.set_position(1, -1e-12)
    assert 0.0 <= m.display_pos()[1] < 3_600_000.0


def test_deterministic_and_arrays_updated_in_place():
    def trace() -> bytes:
        m = Motion([axis(1), axis(2, v=7000.0, a=0.3)], DT)
        arrays = (m.pos, m.vel, m.acc)
        m.move_linear({0: 12_345.6, 1: -7_654.3}, feed=4321.0)
        chunks = []
        for _ in range(4000):
            m.step()
            chunks.append(m.pos.tobytes() + m.vel.tobytes() + m.acc.tobytes())
        assert all(x is y for x, y in zip((m.pos, m.vel, m.acc), arrays, strict=True))
        return b"".join(chunks)

    assert trace() == trace()


def test_rejects_bad_parameters():
    with pytest.raises(MotionError):
        Motion([axis(1, v=0.0)], DT)
    with pytest.raises(MotionError):
        Motion([axis(1)], 0.0)
    with pytest.raises(MotionError):
        Motion([axis(1)], DT).move_to(3, 1.0)
