"""The fast kernel equals the reference kernel (the oracle) on random scenarios.

Random machines (`support.machines.random_machine`: every compensation kind, both
crosstalk dialects and all modes, modulo axes, manual activation, missing lists) driven
by random motion with reversals, homing, COMP ON/OFF (with and without NO_MOVE holds and
their release), TEMPC writes and a reload.
"""

from __future__ import annotations

import numpy as np
import pytest
from support.machines import Motion, full_machine, random_machine
from support.reference import ReferenceKernel

from geo_server.kernel import COMP_ORDER, Kernel

OUTPUTS = ("target", "actual", "delta", "effective", "friction_current", "total_offset")


def assert_same(fast: Kernel, ref: ReferenceKernel, cycle: int) -> None:
    for name in OUTPUTS:
        a = np.asarray(getattr(fast, name), dtype=float)
        b = np.asarray(getattr(ref, name), dtype=float)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9, err_msg=f"{name} @ cycle {cycle}")
    np.testing.assert_array_equal(fast.selected, ref.selected)
    np.testing.assert_array_equal(fast.held, ref.held)
    for x, y in zip(fast.tempc_params, ref.tempc_params, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(8))
def test_random_scenarios(seed: int) -> None:
    n = 7
    cfg = random_machine(n, seed)
    fast, ref = Kernel(cfg), ReferenceKernel(cfg)
    np.testing.assert_array_equal(fast.axis_numbers, ref.axis_numbers)
    motion = Motion(n, seed)
    rng = np.random.default_rng(1000 + seed)
    for cycle in range(1500):
        motion.step()
        if rng.random() < 0.02:  # COMP ON/OFF
            slot, kind, on = int(rng.integers(n)), COMP_ORDER[rng.integers(7)], rng.random() < 0.5
            fast.set_selected(slot, kind, on)
            ref.set_selected(slot, kind, on)
            if rng.random() < 0.5:  # COMP … NO_MOVE: the offset waits for a motion
                fast.hold(slot, kind)
                ref.hold(slot, kind)
        if rng.random() < 0.01:  # the axis' next motion (or COMP without NO_MOVE)
            slot = int(rng.integers(n))
            fast.release(slot)
            ref.release(slot)
        if rng.random() < 0.02:  # TEMPC live write
            slot = int(rng.integers(n))
            field = ("coefficient", "offset_0", "position_0")[rng.integers(3)]
            value = float(rng.uniform(-100, 100))
            fast.write_tempc(slot, field, value)
            ref.write_tempc(slot, field, value)
        if cycle == 700:
            new = random_machine(n, seed + 50)
            fast.reload(new)
            ref.reload(new)
        fast.step(motion.pos, motion.vel, motion.acc, motion.homed, motion.reversal)
        ref.step(motion.pos, motion.vel, motion.acc, motion.homed, motion.reversal)
        assert_same(fast, ref, cycle)


def test_full_machine_manual_sizes() -> None:
    """Manual-sized tables (docs/design.md §11) on 3 axes, everything effective."""
    n = 3
    cfg = full_machine(n)
    fast, ref = Kernel(cfg), ReferenceKernel(cfg)
    motion = Motion(n, 3)
    motion.homed[:] = True
    for cycle in range(400):
        motion.step()
        fast.step(motion.pos, motion.vel, motion.acc, motion.homed, motion.reversal)
        ref.step(motion.pos, motion.vel, motion.acc, motion.homed, motion.reversal)
        assert_same(fast, ref, cycle)
    assert fast.effective.all()


def test_float_reversal_input_and_no_allocation_of_outputs() -> None:
    """Outputs are updated in place (the machine keeps references to them)."""
    cfg = random_machine(4, 99)
    k = Kernel(cfg)
    ids = [id(getattr(k, name)) for name in OUTPUTS]
    m = Motion(4, 1)
    for _ in range(20):
        m.step()
        k.step(m.pos, m.vel, m.acc, m.homed, m.reversal.astype(float))
    assert ids == [id(getattr(k, name)) for name in OUTPUTS]
