"""Volumetric compensation at program end, in the error case, and position errors given
over arguments (004 p.24, p.31-32; docs/volumetric.md §3, §5).

- M30 with a compensation linked to the channel (`associate_to_channel 1`, 004 p.17) still
  active: an error is output and the values are reduced without movement (p.24) — at
  once, in the M30's cycle, the command position unchanged and the drive holding what it
  got (`VOLC::held`) until the axis' next motion ramps it out;
- an axis in error state (its reference lost, its drive no longer enabled) marks every
  active compensation it takes part in incorrect (`VOLC::incorrect`) and switches it off
  without movement (p.24); the drive enable is a precondition of ON (p.20: "error-free");
- a position error given over arguments is a function of them (p.32: "typically (but
  not necessarily) constant"); an ISG parameter whose values differ over the arguments
  of its block is refused with file and line, the compensation not available; records
  that all give one value are that constant.

Expected values are worked out by hand from the model (docs/volumetric.md §2), as in
tests/test_volcomp.py: EXX = 2e-5·x at x = 100 mm gives Δx = −2e-5·100/1.00002 mm =
−19.9996 increments, a quarter of it per cycle over `filter_steps 4`.
"""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import pytest
from conftest import run_in
from test_volcomp import add_volc, held_around_a_move, smooth_files, value
from test_zenoh_commands import JSON, Served, get

from geo_server import access
from geo_server.listfile import load_machine
from geo_server.listfile.checks import EMU_VOLC_ERROR
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService
from geo_server.web.server import HmiOptions, HmiServer

#: EXX = 2e-5·x at x = 100 mm, in increments (the module docstring)
FULL = -2e-5 * 100 / 1.00002 * 10_000
X = 0  # slot of X on the default machine (axis 1)


def linked(folder: Path, channel: int = 1) -> str:
    """smooth_files' VOLC list (manual activation, filter_steps 4) with the p.17 entry."""
    return smooth_files(folder) + f"associate_to_channel {channel}\n"


def machine(lists_copy: Path, volc: str, files: dict[str, str] | None = None) -> Machine:
    add_volc(lists_copy, volc, files or {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(X, 100 * 10_000)
    return m


def volc_errors(m: Machine) -> list[tuple[str, str, int]]:
    return [
        (e.message, e.file, e.line)
        for e in (ev.diagnostic for ev in m.events)
        if e.error_id == EMU_VOLC_ERROR
    ]


def trace(m: Machine, cycles: int) -> list[tuple[int, int, int]]:
    """(VOLC::active, VOLC::correction X, SIM::command_position X) per cycle."""
    out = []
    for _ in range(cycles):
        m.run_cycle()
        out.append(
            (
                value(m, "VOLC::active"),
                value(m, "VOLC::correction", 1),
                value(m, "SIM::command_position", 1),
            )
        )
    return out


# ---------------------------------------------------------------------- M30 (004 p.24)


def test_m30_reduces_a_compensation_linked_to_the_channel(lists_copy: Path) -> None:
    """N10 ramps the compensation in over 4 cycles (−5, −10, −15, −20 increments) and
    waits for it (p.22); N20 M30 finds it still active and linked to the channel: in
    the M30's cycle the correction is 0 and the compensation off, X's command position
    never moves, one error 990525 names the M30's line (p.24)."""
    m = machine(lists_copy, linked(lists_copy.parent))
    m.start_program("N10 #VOLCOMP ON [ID0]\nN20 M30\n")
    seen = trace(m, 8)
    assert [c for _, c, _ in seen] == [0, -5, -10, -15, -20, 0, 0, 0]
    assert [a for a, _, _ in seen] == [0, 1, 1, 1, 1, 0, 0, 0]
    assert {p for _, _, p in seen} == {1_000_000}  # no movement
    assert round(FULL) == -20 and round(FULL / 4) == -5
    (err,) = volc_errors(m)
    assert err[1:] == ("<nc>", 2)
    assert "associate_to_channel 1" in err[0] and "program end" in err[0]
    assert m.player is not None and m.player.finished and not m.volc.get(0).wanted
    # "without any additional movement": the drive keeps getting the −20 the
    # compensation gave it (VOLC::held), until X moves next; then it ramps out over
    # filter_steps 4 cycles, a quarter per cycle, from the motion's first cycle
    assert value(m, "VOLC::held", 1) == -20
    out = value(m, "SIM::output_position", 1) - value(m, "SIM::total_offset", 1)
    assert 1_000_000 - 21 <= out <= 1_000_000 - 19  # (two values rounded apart)
    before_motion, from_motion = held_around_a_move(m, "G91 G01 X1 F6000", 12)
    assert set(before_motion) <= {-20}
    assert from_motion[:4] == [-15, -10, -5, 0] and set(from_motion[4:]) == {0}
    # switched on again by #VOLCOMP (p.24: "re-activated by the #VOLCOMP command")
    for _ in range(200):
        m.run_cycle()
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    assert trace(m, 2)[-1][:2] == (1, -20)


def test_m30_leaves_a_compensation_not_linked_to_the_channel(lists_copy: Path) -> None:
    m = machine(lists_copy, linked(lists_copy.parent, channel=0))
    m.start_program("N10 #VOLCOMP ON [ID0]\nN20 M30\n")
    seen = trace(m, 8)
    assert [c for _, c, _ in seen] == [0, -5, -10, -15, -20, -20, -20, -20]
    assert volc_errors(m) == []


def test_m30_after_off_is_no_error(lists_copy: Path) -> None:
    """Only a compensation still active at M30 is an error (p.24)."""
    m = machine(lists_copy, linked(lists_copy.parent))
    m.start_program("N10 #VOLCOMP ON [ID0 NO_MOVE]\nN20 #VOLCOMP OFF [ID0 NO_MOVE]\nN30 M30\n")
    trace(m, 6)
    assert volc_errors(m) == [] and value(m, "VOLC::active") == 0


def test_mdi_lines_without_m30_are_no_program_end(lists_copy: Path) -> None:
    """MDI lines end without a program end unless they say M30 (nc.Player); with M30
    they do."""
    m = machine(lists_copy, linked(lists_copy.parent))
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    assert trace(m, 3)[-1][:2] == (1, -20)
    m.start_program("M30\n", mdi=True)
    assert trace(m, 2)[-1][:2] == (0, 0)
    assert [(f, ln) for _, f, ln in volc_errors(m)] == [("<nc>", 1)]


def test_the_m30_error_reaches_zenoh_and_the_web_hmi(loop_thread, lists_copy: Path) -> None:
    """The event of the M30 over the interfaces: the service's error list, a Zenoh get
    of `cnc/t/errors` and the web HMI's state, each with file and line."""
    m = machine(lists_copy, linked(lists_copy.parent))
    s = Served(loop_thread, ObjectService(m))
    hmi = HmiServer(s.service, HmiOptions(port=0, machine="t"))
    run_in(loop_thread, hmi.start())
    try:
        s.service.nc.run("#VOLCOMP ON [ID0 NO_MOVE]\nM30\n")
        access.step(s.service, 4)

        def linked_errors(events: list[dict]) -> list[tuple[int, str, int]]:
            return [
                (e["error_id"], e["file"], e["line"])
                for e in events
                if "associate_to_channel" in e["message"]
            ]

        want = [(EMU_VOLC_ERROR, "<nc>", 2)]
        assert linked_errors(s.service.errors()) == want
        oks, errs = get(s.session, "cnc/t/errors")
        assert not errs and linked_errors(json.loads(oks[0][1])) == want
        with urllib.request.urlopen(f"http://{hmi.address}/api/state", timeout=10) as r:
            assert linked_errors(json.loads(r.read())["errors"]) == want
    finally:
        run_in(loop_thread, hmi.close())
        s.close()


# ---------------------------------------------------------------------- error state (p.24)


def test_a_disabled_drive_marks_the_compensation_incorrect(lists_copy: Path) -> None:
    """Active at −20 on X; Y's drive switched off (Y is in the chain YXZ): the
    compensation is marked incorrect, off at once (correction 0 in that cycle), X does
    not move, the error names Y. ON is refused while the drive is off (p.20:
    "error-free"); with the drive on again, ON clears the mark."""
    m = machine(lists_copy, smooth_files(lists_copy.parent))
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    assert trace(m, 3)[-1] == (1, -20, 1_000_000)
    assert value(m, "VOLC::incorrect") == 0
    m.set_drive_enable(1, False)
    assert trace(m, 1)[-1] == (0, 0, 1_000_000)
    assert value(m, "VOLC::incorrect") == 1 and m.volc.offset[X] == 0.0
    (msg, _, _) = volc_errors(m)[-1]
    assert "drive of axis Y is not enabled" in msg and "marked incorrect" in msg
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    trace(m, 2)
    assert value(m, "VOLC::active") == 0 and value(m, "VOLC::incorrect") == 1
    assert "drive of Y is not enabled" in value(m, "SIM::last_error")
    m.set_drive_enable(1, True)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    assert trace(m, 2)[-1] == (1, -20, 1_000_000)
    assert value(m, "VOLC::incorrect") == 0


def test_the_error_case_holds_the_axis_in_error_and_reduces_the_others(lists_copy) -> None:
    """p.24: "Compensation values are removed from the axis without causing an
    additional axis movement [...] the other participating axes are stopped in a
    controlled fashion and their compensation values are reduced". X carries −20.
    Y's drive goes off: X is one of the other axes, its −20 is reduced over filter_steps
    4 from that cycle on (−15, −10, −5, 0). X's own drive goes off: X is the axis in error,
    its drive keeps getting −20 (VOLC::held) while the correction is 0."""
    m = machine(lists_copy, smooth_files(lists_copy.parent))
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\nG91 G01 X0.001 F600\n", mdi=True)
    trace(m, 40)  # (the move takes the held −20 in: nothing held any more)
    assert value(m, "VOLC::correction", 1) == -20 and value(m, "VOLC::held", 1) == 0
    m.set_drive_enable(1, False)  # Y
    held = []
    for _ in range(6):
        m.run_cycle()
        held.append(value(m, "VOLC::held", 1))
    assert value(m, "VOLC::correction", 1) == 0 and held == [-15, -10, -5, 0, 0, 0]
    m.set_drive_enable(1, True)
    m.start_program("#VOLCOMP ON [ID0]\n", mdi=True)
    trace(m, 8)
    assert value(m, "VOLC::correction", 1) == -20 and value(m, "VOLC::held", 1) == 0
    m.set_drive_enable(X, False)
    for _ in range(6):
        m.run_cycle()
        assert value(m, "VOLC::correction", 1) == 0 and value(m, "VOLC::held", 1) == -20


def test_a_lost_reference_marks_it_incorrect_and_reset_clears_the_mark(lists_copy) -> None:
    m = machine(lists_copy, smooth_files(lists_copy.parent))
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    trace(m, 3)
    m.motion.homed[2] = False  # Z
    assert trace(m, 1)[-1][:2] == (0, 0)
    assert value(m, "VOLC::incorrect") == 1
    assert "axis Z lost its reference" in volc_errors(m)[-1][0]
    m.reset()
    m.run_cycle()
    assert value(m, "VOLC::incorrect") == 0


def test_an_axis_outside_the_chain_and_an_inactive_compensation_are_not_marked(
    lists_copy: Path,
) -> None:
    """Only the compensations the axis takes part in, and only active ones (an inactive
    one cannot act; its ON checks the preconditions, p.20)."""
    m = machine(lists_copy, smooth_files(lists_copy.parent))
    m.set_drive_enable(1, False)  # Y, compensation still off
    trace(m, 2)
    assert value(m, "VOLC::incorrect") == 0 and volc_errors(m) == []
    m.set_drive_enable(1, True)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    trace(m, 2)
    m.set_drive_enable(3, False)  # C (axis 4): not in the chain YXZ
    assert trace(m, 2)[-1][:2] == (1, -20)
    assert value(m, "VOLC::incorrect") == 0


def test_automatic_activation_waits_for_the_drive(lists_copy: Path) -> None:
    """manual_activation 0 (p.20: "as soon as all participating axes allow it
    (error-free, referenced, etc.)"): with X's drive off it waits, then starts."""
    auto = smooth_files(lists_copy.parent).replace("manual_activation 1", "manual_activation 0")
    add_volc(lists_copy, auto, {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.set_drive_enable(X, False)
    trace(m, 3)
    assert value(m, "VOLC::active") == 0 and volc_errors(m) == []
    m.set_drive_enable(X, True)
    m.run_cycle()
    assert value(m, "VOLC::active") == 1


def test_incorrect_over_zenoh_with_the_drive_switched_by_a_zenoh_write(
    loop_thread, lists_copy: Path
) -> None:
    m = machine(lists_copy, smooth_files(lists_copy.parent))
    s = Served(loop_thread, ObjectService(m))
    try:
        s.service.nc.run("#VOLCOMP ON [ID0 NO_MOVE]\n")
        access.step(s.service, 3)
        oks, errs = get(s.session, "cnc/t/sim/machine/volc_incorrect")
        assert not errs and json.loads(oks[0][1]) == 0
        oks, errs = get(s.session, "cnc/t/sim/axis/2/drive_enable", b"false", JSON)
        assert not errs, errs
        access.step(s.service, 2)
        oks, errs = get(s.session, "cnc/t/sim/machine/volc_incorrect")
        assert not errs and json.loads(oks[0][1]) == 1
        oks, errs = get(s.session, "cnc/t/sim/machine/volc_active")
        assert json.loads(oks[0][1]) == 0
    finally:
        s.close()


# ---------------------------------------------------------------------- p.31-32


def csv_volc(folder: Path, csv: str) -> tuple[str, dict[str, str]]:
    volc = (
        "X 1\nY 2\nZ 3\nchain YXZ\nmanual_activation 0\nfile[0] pos.csv\nfile_format[0] ISG_CSV\n"
    )
    return volc, {"pos.csv": csv}


@pytest.mark.parametrize(
    ("x_mm", "want"),
    [(0.0, 100), (50.0, 150), (100.0, 200), (200.0, 200), (-10.0, 100)],
)
def test_a_position_error_over_an_argument_is_applied_as_its_function(
    lists_copy: Path, x_mm: float, want: int
) -> None:
    """004 p.32: position errors are "typically (but not necessarily) constant", and a
    header may name arguments with them. C0Y, the squareness of Y, given over X: 1e-4
    rad at x = 0, 2e-4 rad at x = 100 mm, linear between, the edge values held beyond
    (docs/volumetric.md §3). At y = 100 mm Y's travel is tilted by C0Y(x), the tool is
    off by −C0Y(x)·y in X, so Δx = +C0Y(x)·100 mm: 100, 150, 200 increments at x = 0,
    50, 100 mm, 200 beyond and 100 below (the second Newton step moves x by 0.015 mm at
    most: C0Y changes by 1.5e-8 rad, Δx by 0.015 increments). Before: refused with
    990525."""
    volc, files = csv_volc(lists_copy.parent, "// sag\nX C0Y\n0 0.0001\n100 0.0002\n")
    add_volc(lists_copy, volc, files)
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(X, round(x_mm * 10_000))
    m.motion.set_position(1, 100 * 10_000)  # Y (axis 2)
    m.run_cycle()
    m.run_cycle()
    assert value(m, "VOLC::available") == 1 and value(m, "VOLC::active") == 1
    assert [value(m, "VOLC::correction", a) for a in (1, 2, 3)] == [want, 0, 0]


@pytest.mark.parametrize(
    ("csv", "line", "what"),
    [
        # an ISG parameter (the offset IDX, p.30) varying over Z, after a component block
        ("X EXX\n0 0\n100 0.001\n#\nZ IDX\n0 0\n100 1\n", 5, "IDX is a constant of the machine"),
        ("// centre\nX PXC\n0 0\n100 1\n", 2, "PXC is a constant of the machine"),
    ],
)
def test_a_varying_isg_parameter_is_refused_with_file_and_line(
    lists_copy: Path, csv: str, line: int, what: str
) -> None:
    """An ISG parameter describes the machine (004 p.30) and has one value: one that
    varies over arguments is an error 990525 naming the correction file and the line of
    the block's header, the compensation not available, ON refused."""
    volc, files = csv_volc(lists_copy.parent, csv)
    add_volc(lists_copy, volc, files)
    cfg = load_machine(lists_copy)
    (comp,) = cfg.volumetric
    assert not comp.available and what in comp.problem
    (err,) = [d for d in cfg.diagnostics if d.error_id == EMU_VOLC_ERROR]
    assert Path(err.file).name == "pos.csv" and err.line == line
    assert "volumetric compensation 0" in err.message and "component error" in err.message
    m = Machine(cfg, cycle_s=0.001, homed=True)
    m.run_cycle()
    assert value(m, "VOLC::available") == 0 and value(m, "VOLC::active") == 0
    m.start_program("#VOLCOMP ON [ID0]\n", mdi=True)
    m.run_cycle()
    m.run_cycle()
    assert "not available" in value(m, "SIM::last_error")


@pytest.mark.parametrize(
    "csv",
    ["X C0Y\n0 0.00005\n100 0.00005\n", "X C0Y\n50 0.00005\n", "C0Y\n0.00005\n"],
    ids=["equal-over-X", "one-record-over-X", "constant"],
)
def test_a_position_error_with_one_value_is_that_constant(lists_copy: Path, csv: str) -> None:
    """C0Y = 5e-5 rad at y = 100 mm (x = z = 0): Y's travel is tilted, the tool is off
    by −C0Y·y = −0.005 mm in X, so Δx = +0.005 mm = +50 increments, Δy = Δz = 0
    (tests/test_volcomp.py::test_pure_squareness), whether the value is given alone or
    over an argument with one value."""
    volc, files = csv_volc(lists_copy.parent, csv)
    add_volc(lists_copy, volc, files)
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(1, 100 * 10_000)  # Y (axis 2)
    m.run_cycle()
    m.run_cycle()
    assert value(m, "VOLC::available") == 1 and value(m, "VOLC::active") == 1
    assert [value(m, "VOLC::correction", a) for a in (1, 2, 3)] == [50, 0, 0]


def test_a_varying_shift_of_a_linear_axis_is_refused(lists_copy: Path) -> None:
    """004 p.28: the position shift (X0k, Y0k, Z0k) "is only relevant for rotary axes":
    varying over X it would be accepted and change nothing, a compensation reported
    active that corrects nothing; refused at the block's header with 990525."""
    volc, files = csv_volc(lists_copy.parent, "X Y0X\n0 0.001\n100 0.002\n")
    add_volc(lists_copy, volc, files)
    cfg = load_machine(lists_copy)
    (comp,) = cfg.volumetric
    assert not comp.available and "only relevant for rotary axes" in comp.problem
    (err,) = [d for d in cfg.diagnostics if d.error_id == EMU_VOLC_ERROR]
    assert Path(err.file).name == "pos.csv" and err.line == 1
