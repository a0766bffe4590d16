"""Batches of cycles (docs/design.md §13.2) give the numbers of single cycles, bit for bit.

Two machines run the same NC program and the same writes: one cycle by cycle
(`run_cycle`, the reference), the other in batches of random size wherever the batch
accepts the stretch (`run_batch`), single cycles elsewhere. After every batch the whole
state that a later cycle or a snapshot reads is compared with `np.array_equal`: the
kernel's outputs, filter, source vector and friction delay line, the motion, the twin,
and the published snapshot. Machines: the default machine (every compensation, crosstalk
mode 3 among them), random machines (modulo axes, friction delays, manual activation,
missing compensations) and the default machine with two volumetric compensations acting
(docs/volumetric.md: ramps, CFACT, negate, a rotary chain, the tool length, the s_limit
stop and an axis fault while the axes move), where the drives' actual positions, the
compensations' state rows and the error list are compared too.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from support.machines import random_machine, volumetric_machine

from geo_server.listfile.loader import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.port import Reset, WriteObjects
from geo_server.model import MachineConfig
from geo_server.paths import default_startup_list


def state(m: Machine) -> list[np.ndarray]:
    k, mo, tw = m.kernel, m.motion, m.twin
    return [
        k.actual,
        k.target,
        k.previous,
        k.delta,
        k.effective,
        k.total_offset,
        # the whole of the kernel's state: sin² filter, direction, friction path and
        # delay line, the commands of the last cycle, the flags
        k.F7,
        k.B7,
        k.I7,
        k.F1,
        k.B1,
        k.G,
        k.ring,
        mo.pos,
        mo.vel,
        mo.acc,
        mo._k,
        m._reversal,
        m._output,
        m._drive_act,
        m.volc.S,  # every volumetric compensation's ramp, weights, values
        m.volc.offset,
        tw._vsum,
        tw.sensor_temperature,
        np.array([m.cycle, tw.cycles, m.player.cycle if m.player else 0]),
        np.array([m.player.running if m.player else False, m.volc.active_mask]),
        np.array([m.volc.incorrect_mask, m.volc.tool_length]),
    ]


#: what `run_pair` does to both machines before a cycle: an object write, or anything
Action = tuple | Callable[[Machine], object]


def program(names: list[str]) -> str:
    """Moves of every axis with reversals, a move of one axis, a dwell, a loop."""
    a = names
    there = " ".join(f"{x}{20 + 7 * i}" for i, x in enumerate(a))
    back = " ".join(f"{x}{-15 - 5 * i}" for i, x in enumerate(a))
    return (
        f"N10 G90 G01 {there} F3000\n"
        f"N20 {back}\n"
        f"N30 {a[0]}5\n"
        "N40 G04 X0.02\n"
        f"N50 G00 {there}\n"
        "N60 $GOTO N20\n"
    )


def run_pair(
    cfg: MachineConfig,
    seed: int,
    cycles: int,
    writes: dict[int, Action],
    seen: Callable[[Machine, tuple[bool, bool, int]], None] | None = None,
) -> int:
    """Run `cfg` cycle by cycle and in passes side by side, comparing after every pass;
    `writes` acts on both before the cycle it is keyed by (or the first one after a
    pass that ran past it); `seen(machine, before)` is
    told of every pass the batched machine ran, with what was before it: (a volumetric
    compensation active, ramps at rest, the number of events)."""
    ref, bat = Machine(cfg, homed=True), Machine(cfg, homed=True)
    names = sorted(ref.names, key=ref.names.__getitem__)
    for m in (ref, bat):
        m.set_epoch(0)
        m.start_program(program(names))
    rng = np.random.default_rng(seed)
    batched = 0
    due = sorted(writes.items(), key=lambda kv: kv[0])
    while ref.cycle < cycles:
        while due and due[0][0] <= ref.cycle:  # (a pass may have run past its cycle)
            w = due.pop(0)[1]
            for m in (ref, bat):
                if callable(w):
                    w(m)
                else:
                    m.submit(WriteObjects((w,)))
        size = int(rng.choice([2, 3, 4, 8, 16]))
        publish = bool(rng.integers(2))
        before = (bat.volc.busy, bat.volc.at_rest, len(bat.events))
        got = bat.run_batch(size)
        if got:
            if seen is not None:
                seen(bat, before)
            batched += got
            if publish:
                bat.publish()
            for _ in range(got - 1):
                ref.run_cycle(publish=False)
            ref.run_cycle(publish=publish)
        else:
            ref.run_cycle()
            bat.run_cycle()
        for i, (x, y) in enumerate(zip(state(ref), state(bat), strict=True)):
            assert np.array_equal(x, y), f"state {i} differs after cycle {ref.cycle}"
        assert events(ref) == events(bat)
        if got and publish:
            assert np.array_equal(ref.snapshot.values, bat.snapshot.values)
            assert ref.snapshot.stamp == bat.snapshot.stamp
    assert np.array_equal(ref.publish().values, bat.publish().values)
    return batched


def events(m: Machine) -> list[tuple[int, str]]:
    return [(e.cycle, e.diagnostic.describe()) for e in m.events]


def test_default_machine_batches_equal_single_cycles() -> None:
    cfg = load_machine(default_startup_list())
    writes = {
        700: ("TEMPC::offset_0", 1, -250),  # a sin² ramp while the axes move
        1500: ("TEMPC::coefficient", 2, 40.0),
        2200: ("TEMPC::activated", 3, False),
    }
    batched = run_pair(cfg, seed=1, cycles=4000, writes=writes)
    assert batched > 3000  # most of the run is steady motion


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [2, 5])
def test_random_machines_batches_equal_single_cycles(n: int, seed: int) -> None:
    cfg = random_machine(n, seed)
    for a, letter in zip(sorted(cfg.axes), "XYZUV", strict=False):
        cfg.axes[a].params.name = letter  # (its own names, A1 …, read as address A)
    writes = {400: ("TEMPC::offset_0", 1, 120), 900: ("TEMPC::position_0", 2, 5000)}
    assert run_pair(cfg, seed, cycles=1500, writes=writes) > 500


def test_a_batch_refuses_what_is_not_steady() -> None:
    """Nothing changes when the batch says no (at rest, with an operation queued), and
    a batch ends with the cycle in which a move ends (the program sees the arrival at
    the start of the next cycle, as after single cycles)."""
    m = Machine(load_machine(default_startup_list()), homed=True)
    m.step(3)
    before = [a.copy() for a in state(m)]
    assert m.run_batch(8) == 0  # at rest: the engine skips such cycles instead
    m.start_program("N10 G90 G01 X1 F6000\n")
    assert m.run_batch(8) == 0  # the program waits for the next single cycle
    for x, y in zip(before, state(m), strict=True):
        assert np.array_equal(x, y)
    m.step(1)  # the program starts the move, which takes its first step
    assert m.motion._k[0] == 1
    m.submit(WriteObjects((("TEMPC::offset_0", 1, 10),)))
    assert m.run_batch(4) == 0  # the write goes into the next single cycle
    m.step(1)
    left = int(m.motion._nc[0] - m.motion._k[0])
    assert left > 2
    assert m.run_batch(left + 5) == left  # up to the cycle of the arrival
    assert m.motion.pos[0] == 10_000.0 and m.motion.vel[0] == 0.0  # X1: arrived
    assert m.player is not None and m.player.running  # it sees the arrival next cycle
    m.step(1)
    assert not m.player.running  # the program's end


def test_a_long_friction_delay_keeps_the_pass_whole() -> None:
    """A delay of d cycles reads the delay line d rows back. A pass is the single cycle
    in a loop, so it reads each row after the cycle that wrote it, whatever d: the pass
    keeps its length (the array pass of earlier versions had to stop at 249 − d) and
    the numbers stay those of single cycles."""
    cfg = random_machine(3, 4)
    for a, letter in zip(sorted(cfg.axes), "XYZ", strict=True):
        cfg.axes[a].params.name = letter
    fr = cfg.axes[1].comp.frict
    assert fr is not None and fr.valid and fr.mode == 3
    fr.delay_cycles = 245  # ≤ 248 (000 p.79)
    m = Machine(cfg, homed=True)
    m.start_program(program(["X", "Y", "Z"]))
    m.step(5)
    assert m.run_batch(16) == 16
    run_pair(cfg, seed=4, cycles=800, writes={})


# ---------------------------------------------------------------------- volumetric


#: grid of the correction files (mm)
def test_volumetric_compensations_batch_equal_single_cycles(tmp_path: Path) -> None:
    """Passes while volumetric compensations act give the numbers of single cycles, bit
    for bit: ID1 ramping in with the first cycles of the program; the tool length
    written while the axes move; ID0 switched on by object while they move (its ramp
    runs in passes), then its X beyond s_limit (switched off with an error, the program
    stopped — in a pass) and the program started again, several times; ID1 ramped out
    and in again by object; an #VOLCOMP ON with CFACT in an MDI block; at last a drive
    switched off (the error case of 004 p.24)."""
    cfg = volumetric_machine(tmp_path)
    names = ["X", "Y", "Z", "C"]
    restart = program(names)

    def start(m: Machine) -> None:
        m.start_program(restart)

    def reset_and_weigh(m: Machine) -> None:
        m.submit(Reset())  # every compensation off (004 p.24), the program ended
        m.start_program("N1 #VOLCOMP ON [ID0 CFACT_X=0.5 CFACT_Z=0]\n" + restart)

    writes: dict[int, Action] = {
        40: ("VOLC::tool_length", 0, 80.0),
        300: ("cnc_vol_comp_enable_index_w", 0, 0),
        900: start,
        920: ("cnc_vol_comp_enable_index_w", 0, 0),
        1300: ("cnc_vol_comp_disable_index_w", 0, 1),
        1500: ("cnc_vol_comp_enable_index_w", 0, 1),
        1700: start,
        1720: ("cnc_vol_comp_enable_index_w", 0, 0),
        2300: reset_and_weigh,
        2850: ("cnc_vol_comp_enable_index_w", 0, 1),
        2900: ("SIM::drive_enable", 2, False),
    }
    passes = {"acting": 0, "ramping": 0, "stopped": 0}
    machines: list[Machine] = []

    def seen(m: Machine, before: tuple[bool, bool, int]) -> None:
        busy, at_rest, count = before
        machines[:] = [m]
        passes["acting"] += busy
        passes["ramping"] += busy and not at_rest
        new = list(m.events)[count:]
        passes["stopped"] += any(
            "exceeds lr_param.vol_comp.s_limit" in e.diagnostic.message for e in new
        )

    batched = run_pair(cfg, seed=3, cycles=3300, writes=writes, seen=seen)
    assert batched > 1500
    assert passes["acting"] > 100 and passes["ramping"] > 0 and passes["stopped"] > 0, passes
    said = [e.diagnostic.message for e in machines[0].events]
    assert sum("exceeds lr_param.vol_comp.s_limit" in t for t in said) >= 2, said
    assert sum("the drive of axis Y is not enabled: marked incorrect" in t for t in said) == 2
