"""`COMP … NO_MOVE` (000 §5.1 p.94), cycle by cycle in stepped mode.

"By default the position offset occurring when axis compensations are switched on/off is
executed before NC program processing is continued. The keyword NO_MOVE suppresses this
motion. [...] The position offset is only executed at the next axis motion programmed in
the NC program." So after `COMP … NO_MOVE` the selection changes at once (the objects
`*::activated` and the effective flags follow), the compensation's output stays where it
was through any dwell, and the sin² ramp of the switch (docs/design.md §3.4) runs from the
first cycle of the axis' next motion block: out_k = target_k − (target_1 − held)·cos²(πk/2N).

Expected values are computed here by hand from the manual's formulas and the default
machine's lists (lists/achsmd*.lis, lists/achskw*.lis), never by the code under test.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import pytest

from geo_server import access
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService

X, Y, Z = 1, 2, 3


def rhaz(x: float) -> int:
    """Round half away from zero (docs/design.md §3), written out independently."""
    return math.floor(abs(x) + 0.5) * (1 if x >= 0 else -1)


def cos2(k: int, n: int) -> float:
    return math.cos(math.pi * k / (2 * n)) ** 2


@dataclass
class Row:
    line: int  # NC line of the block executed last (the waiting block during a wait)
    velocity: float  # of the moving axis
    command: float  # SIM::command_position of the moving axis, 0.1 µm
    value: int  # the compensation's output object
    selected: bool
    extra: dict[str, object]


def run(
    machine: Machine,
    svc: ObjectService,
    program: str,
    axis: int,
    obj: str,
    selected: str,
    extra: tuple[tuple[str, int], ...] = (),
) -> list[Row]:
    """Run `program` to its end, one row per cycle."""
    machine.start_program(program)
    rows = []
    for _ in range(20_000):
        machine.run_cycle()
        player = machine.player
        assert player is not None and player.error is None, player and player.error
        rows.append(
            Row(
                line=player.line,
                velocity=access.read_name(svc, "SIM::velocity", axis),
                command=access.read_name(svc, "SIM::command_position", axis),
                value=access.read_name(svc, obj, axis),
                selected=access.read_name(svc, selected, axis),
                extra={f"{n}@{a}": access.read_name(svc, n, a) for n, a in extra},
            )
        )
        if not player.running:
            return rows
    raise AssertionError("program did not end")


def motion_rows(rows: list[Row], line: int) -> list[Row]:
    """The rows from the first cycle of the motion block on `line` (velocity ≠ 0)."""
    start = next(i for i, r in enumerate(rows) if r.line == line and r.velocity != 0)
    return rows[start:]


@pytest.fixture
def svc(machine: Machine) -> ObjectService:
    machine.step(40)  # start-up ramps over (the longest is 20 cycles)
    return ObjectService(machine)


#: X's temperature offset at 100 mm, 000 p.17: position_0 100, offset_0 40, coefficient
#: 4000 µm/m: 40 + 4000e-6·(1 000 000 − 100) = 4039.6 (published 4040)
HELD_X = 40 + 4000e-6 * (1_000_000 - 100)


def x_at_100_mm(machine: Machine, svc: ObjectService) -> None:
    access.write_name(svc, "SIM::set_position", X, 1_000_000)
    machine.step(25)  # temp_comp_n_cycles 20: the ramp of the new position is over


def hold_x_temp(machine: Machine, svc: ObjectService) -> None:
    """X at 100 mm, then `X[COMP OFF TEMP NO_MOVE]` run to its end: 4040 held."""
    x_at_100_mm(machine, svc)
    run(
        machine,
        svc,
        "X[COMP OFF TEMP NO_MOVE]\nM30\n",
        X,
        "TEMPC::actual_offset",
        "TEMPC::activated",
    )


# --------------------------------------------------------------------- the manual's numbers


def test_temp_off_no_move_holds_the_offset_through_a_dwell(machine, svc):
    """000 p.17: position_0 100, offset_0 40, coefficient 4000 µm/m; X at 100 mm:
    40 + 4000e-6·(1 000 000 − 100) = 4039.6 → 4040. `X[COMP OFF TEMP NO_MOVE]`, a 50 ms
    dwell, then an X move: the offset stays through the dwell and ramps out over
    temp_comp_n_cycles = 20 from the first cycle of the move."""
    x_at_100_mm(machine, svc)
    held = HELD_X
    assert access.read_name(svc, "TEMPC::actual_offset", X) == rhaz(held) == 4040
    output = access.read_name(svc, "SIM::output_position", X)
    # X's LSEC at 100 mm is −table[60].pos = 42 (lists/achskw1.lis): the 1 004 082
    assert output == 1_000_000 + 4040 + 42
    prog = "N10 X[COMP OFF TEMP NO_MOVE]\nN20 G04 0.05\nN30 G91 G01 X1 F6000\nN40 M30\n"
    rows = run(
        machine, svc, prog, X, "TEMPC::actual_offset", "TEMPC::activated",
        (("SIM::output_position", X), ("TEMPC::f_is_active", X)),
    )  # fmt: skip
    dwell = [r for r in rows if r.line == 2]
    assert len(dwell) == 50  # round(0.05 s / 1 ms) cycles, the last one ends the wait
    last = max(i for i, r in enumerate(rows) if r.line == 2)
    for r in rows[: last + 1]:
        assert not r.selected and r.extra["TEMPC::f_is_active@1"] is False
        assert r.value == 4040  # held: not ramped out during the dwell
        assert r.extra["SIM::output_position@1"] == output
    moving = motion_rows(rows, 3)
    for k in range(1, 21):
        assert moving[k - 1].value == rhaz(held * cos2(k, 20)), k
    assert all(r.value == 0 for r in moving[20:])


def test_temp_on_no_move_ramps_in_with_the_move(machine, svc):
    """`X[COMP ON TEMP NO_MOVE]`: 0 through the dwell although active; from the move's
    first cycle out_k = t_k − t_1·cos²(πk/40) with t = 40 + 4000e-6·(s − 100) (000 p.15)."""
    x_at_100_mm(machine, svc)
    prog = (
        "N10 X[COMP OFF TEMP]\nN20 X[COMP ON TEMP NO_MOVE]\nN30 G04 0.05\n"
        "N40 G91 G01 X1 F6000\nN50 M30\n"
    )
    rows = run(
        machine, svc, prog, X, "TEMPC::actual_offset", "TEMPC::activated",
        (("TEMPC::f_is_active", X),),
    )  # fmt: skip
    dwell = [r for r in rows if r.line == 3]
    assert len(dwell) == 50
    for r in dwell:
        assert r.selected and r.extra["TEMPC::f_is_active@1"] is True and r.value == 0
    moving = motion_rows(rows, 4)

    def target(s: float) -> float:
        return 40 + 4000e-6 * (s - 100)

    t1 = target(moving[0].command)
    for k in range(1, 21):
        r = moving[k - 1]
        assert abs(r.value - (target(r.command) - t1 * cos2(k, 20))) <= 0.51, k
    end = moving[-1]
    assert end.value == rhaz(target(end.command)) == rhaz(40 + 4000e-6 * (1_010_000 - 100))


# --------------------------------------------------------------------- every kind


@dataclass(frozen=True)
class Case:
    kind: str
    axis: int
    obj: str
    selected: str
    n: int  # sin² length of the switch
    move: str  # the motion block that executes the held offset
    prepare: str = ""
    #: target while selected, from the held value v0 and the command position s
    target: Callable[[float, float], float] = lambda v0, s: v0


CASES = [
    # X: anwahl_losekomp 1 (start-up direction positive), lose 1000, n_backlash_cyc 10;
    # after a negative move the target is d·lose = −1000 (000 §2), also while moving on
    Case(
        "BACKLASH", X, "BC::actual backlash", "SIM::backlash_selected", 10,
        "G91 G01 X-1 F6000", prepare="G91 G01 X-1 F6000\n", target=lambda v0, s: -1000,
    ),
    # Z's cross (master X) and plane (masters X, Y) do not change while Z moves;
    # n_cycles 20 each (lists/achskw3.lis)
    Case("CROSS", Z, "CROSSC::actual_offset", "CROSSC::activated", 20, "G91 G01 Z1 F6000"),
    Case("PLANE", Z, "CC2::correction", "CC2::activated", 20, "G91 G01 Z1 F6000"),
    # X's LSEC at 0 … 10 mm: table[50].pos −9, table[51].pos −6 (lists/achskw1.lis); the
    # applied value is −Δs (000 §4.4); ramp length n_backlash_cyc 10
    Case(
        "LEAD", X, "LSEC::sum epsilon", "ssfk activated", 10, "G91 G01 X1 F6000",
        target=lambda v0, s: -(-9 + (s / 100_000) * (-6 - -9)),
    ),
]  # fmt: skip


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.kind)
def test_every_kind_is_held_until_the_next_motion_off_and_on(machine, svc, case):
    if case.prepare:
        run(machine, svc, case.prepare + "M30\n", case.axis, case.obj, case.selected)
        machine.step(40)
    v0 = access.read_name(svc, case.obj, case.axis)
    assert v0 != 0  # otherwise holding could not be told from switching
    if case.kind == "BACKLASH":
        assert v0 == -1000
    name = {X: "X", Y: "Y", Z: "Z"}[case.axis]
    prog = (
        f"N10 {name}[COMP OFF {case.kind} NO_MOVE]\nN20 G04 0.03\nN30 {case.move}\n"
        f"N40 {name}[COMP ON {case.kind} NO_MOVE]\nN50 G04 0.03\nN60 {case.move}\nN70 M30\n"
    )
    rows = run(machine, svc, prog, case.axis, case.obj, case.selected)
    off_dwell = [r for r in rows if r.line == 2]
    on_dwell = [r for r in rows if r.line == 5]
    assert len(off_dwell) == len(on_dwell) == 30
    assert all(r.value == v0 and not r.selected for r in off_dwell)
    assert all(r.value == 0 and r.selected for r in on_dwell)
    # OFF: from the held v0 to 0
    off_move = motion_rows(rows, 3)
    for k in range(1, case.n + 1):
        assert abs(off_move[k - 1].value - v0 * cos2(k, case.n)) <= 1.0, ("off", k)
    assert off_move[case.n].value == 0
    # ON: from the held 0 to the target
    on_move = motion_rows(rows, 6)
    t1 = case.target(v0, on_move[0].command)
    for k in range(1, case.n + 1):
        r = on_move[k - 1]
        want = case.target(v0, r.command) - t1 * cos2(k, case.n)
        assert abs(r.value - want) <= 1.0, ("on", k, r.value, want)
    r = on_move[case.n]
    assert abs(r.value - case.target(v0, r.command)) <= 0.51


def test_crosstalk_on_no_move_is_held_while_the_master_accelerates(machine, svc):
    """Y's crosstalk (mode 1, master X, a_ref 2000 mm/s², accelerate_dir_pos 30,
    n_cycles 10; lists/achskw2.lis) after `Y[COMP ON CROSSTALK NO_MOVE]`: X accelerating
    at its a_max 2000 mm/s² gives the target 30·min(2000/2000, 1) = 30 (000 §4.6 p.84),
    but the output stays 0 until Y moves; a block moving X and Y then ramps it in."""
    prog = (
        "N10 Y[COMP OFF CROSSTALK]\nN20 Y[COMP ON CROSSTALK NO_MOVE]\n"
        "N30 G91 G01 X20 F6000\nN40 G91 G01 X20 Y1 F6000\nN50 M30\n"
    )
    rows = run(
        machine, svc, prog, X, "CROSSTALK::actual_offset", "CROSSTALK::activated",
        (("CROSSTALK::actual_offset", Y), ("CROSSTALK::end_offset", Y),
         ("CROSSTALK::activated", Y), ("SIM::acceleration", X)),
    )  # fmt: skip
    first = [r for r in rows if r.line == 3]
    accelerating = [r for r in first if r.extra["SIM::acceleration@1"] == 2000]
    assert len(accelerating) >= 40  # 100 mm/s at 2000 mm/s²: 50 cycles
    for r in first:
        assert r.extra["CROSSTALK::activated@2"] is True
        assert r.extra["CROSSTALK::actual_offset@2"] == 0  # held
    assert all(r.extra["CROSSTALK::end_offset@2"] == 30 for r in accelerating)
    both = motion_rows(rows, 4)
    for k in range(1, 11):  # X accelerates at a_max through these cycles: target 30
        r = both[k - 1]
        assert r.extra["SIM::acceleration@1"] == 2000
        assert r.extra["CROSSTALK::actual_offset@2"] == rhaz(30 - 30 * cos2(k, 10)), k


def test_frict_switches_at_once(machine, svc):
    """Friction is a current, not a position offset: NO_MOVE has nothing to hold, the
    switch acts at once (docs/design.md §12): off before the move, no current during it
    (with the switch the current would follow the velocity, 000 §4.5)."""
    prog = "N10 X[COMP OFF FRICT NO_MOVE]\nN20 G91 G01 X1 F6000\nN30 M30\n"
    rows = run(
        machine, svc, prog, X, "FRICT::additive_current", "SIM::friction_selected",
    )  # fmt: skip
    assert not machine.kernel.held.any()
    assert all(not r.selected and r.value == 0 for r in rows)
    assert sum(r.velocity != 0 for r in rows) > 20


def test_frict_current_without_the_switch(machine, svc):
    """The control for the test above: the same move with friction on has a current."""
    rows = run(
        machine, svc, "N20 G91 G01 X1 F6000\nN30 M30\n", X, "FRICT::additive_current",
        "SIM::friction_selected",
    )  # fmt: skip
    assert any(r.value != 0 for r in rows)


def test_comp_without_no_move_executes_a_held_offset(machine, svc):
    """A later COMP without NO_MOVE on the same axis executes everything outstanding: the
    offset held through the dwell ramps out with that COMP, which waits for it."""
    x_at_100_mm(machine, svc)
    prog = "N10 X[COMP OFF TEMP NO_MOVE]\nN20 G04 0.03\nN30 X[COMP OFF LEAD]\nN40 M30\n"
    rows = run(machine, svc, prog, X, "TEMPC::actual_offset", "TEMPC::activated")
    dwell = [i for i, r in enumerate(rows) if r.line == 2]
    assert len(dwell) == 30 and all(rows[i].value == 4040 for i in dwell)
    at = dwell[-1] + 1  # the COMP runs in the cycle the dwell ends
    held = HELD_X
    assert rows[at].line == 3
    for k in range(1, 21):
        assert rows[at + k - 1].value == rhaz(held * cos2(k, 20)), k
    assert rows[-1].line == 4 and len(rows) - at == 21


def test_tempc_activated_write_executes_a_held_offset(machine, svc):
    """`TEMPC::activated` written acts at once, also on an offset a NO_MOVE held back."""
    hold_x_temp(machine, svc)
    machine.step(50)
    assert access.read_name(svc, "TEMPC::actual_offset", X) == 4040
    access.write_name(svc, "TEMPC::activated", X, False)  # already off: only the release
    held = HELD_X
    for k in range(1, 21):
        machine.run_cycle()
        assert access.read_name(svc, "TEMPC::actual_offset", X) == rhaz(held * cos2(k, 20)), k


def test_a_comp_that_changes_nothing_holds_nothing(machine, svc):
    """Z's cross compensation is on: `Z[COMP ON CROSS NO_MOVE]` switches nothing, so its
    value keeps following the master X (000 §4.2)."""
    before = access.read_name(svc, "CROSSC::actual_offset", Z)
    prog = "N10 Z[COMP ON CROSS NO_MOVE]\nN20 G90 G01 X-300 F60000\nN30 M30\n"
    run(machine, svc, prog, Z, "CROSSC::actual_offset", "CROSSC::activated")
    assert not machine.kernel.held.any()
    machine.step(30)
    assert access.read_name(svc, "CROSSC::actual_offset", Z) != before


def test_no_move_while_the_axis_moves_is_executed_with_that_motion(machine, svc):
    """The axis is jogging when the COMP arrives: its offset is executed with that
    motion (there is no standstill to hold it through)."""
    x_at_100_mm(machine, svc)
    access.write_name(svc, "SIM::target_position", X, 2_000_000)
    machine.step(5)
    machine.start_program("X[COMP OFF TEMP NO_MOVE]\n", mdi=True)
    machine.step(25)
    assert not machine.kernel.held.any()
    assert access.read_name(svc, "TEMPC::actual_offset", X) == 0


def test_monitoring_sees_a_no_move_switch_of_the_same_cycle(machine, svc):
    """Y requires LEAD | TEMP (lists/achsmd2.lis, 000 §5.3 p.97). `Y[COMP OFF TEMP NO_MOVE]`
    does not wait, so the next block runs in the same cycle: its Y move raises 70435 —
    and after `Y[COMP ON TEMP NO_MOVE]` a Y move is allowed."""
    machine.start_program("N10 Y[COMP OFF TEMP NO_MOVE]\nN20 G91 G01 Y1 F6000\nN30 M30\n")
    machine.step(3)
    assert machine.player is not None and machine.player.error is not None
    assert machine.player.error.error_id == 70435 and machine.player.error.line == 2
    prog = "N10 Y[COMP OFF TEMP]\nN20 Y[COMP ON TEMP NO_MOVE]\nN30 G91 G01 Y1 F6000\nN40 M30\n"
    rows = run(machine, svc, prog, Y, "TEMPC::actual_offset", "TEMPC::activated")
    assert rows[-1].line == 4  # ran to its end (run() asserts no error)


def test_a_manual_move_executes_a_held_offset(machine, svc):
    """The next axis motion need not come from the program: a `SIM::target_position`
    write (jog) moves the axis and executes the held offset."""
    hold_x_temp(machine, svc)
    machine.step(100)
    assert access.read_name(svc, "TEMPC::actual_offset", X) == 4040  # still held
    access.write_name(svc, "SIM::target_position", X, 1_010_000)  # applied at the next cycle
    held = HELD_X
    for k in range(1, 21):
        machine.run_cycle()
        assert access.read_name(svc, "TEMPC::actual_offset", X) == rhaz(held * cos2(k, 20)), k
