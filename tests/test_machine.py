"""The machine end to end: GEO cycle, objects, COMP, monitoring, reload, save, determinism.

Expected values are computed here from the manuals' formulas (000 §2, §3; docs/design.md §3 sin²
rule), never by calling the code under test.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest
from support.machines import with_params

from geo_server import access
from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import data_dir
from geo_server.service import ObjectService


def rhaz(x: float) -> int:
    """Round half away from zero (docs/design.md §3), written out independently of the code."""
    return math.floor(abs(x) + 0.5) * (1 if x >= 0 else -1)


def sin2_ramp(start: float, target: float, k: int, n: int) -> float:
    """docs/design.md §3: out_k = target − J·cos²(π·k/(2N)), J = target − start."""
    return target - (target - start) * math.cos(math.pi * k / (2 * n)) ** 2


# ------------------------------------------------------------------------- temperature


def test_temperature_manual_example_through_the_objects(service):
    # 000 p.17: position_0 100, offset_0 40, coefficient 4000 µm/m; X homed at 100 mm.
    access.write_name(service, "SIM::set_position", 1, 1_000_000)
    access.step(service, 25)  # temp_comp_n_cycles 20: the start-up ramp is over
    expected = 40 + 4000e-6 * (1_000_000 - 100)  # 4039.6
    assert access.read_name(service, "TEMPC::actual_offset", 1) == rhaz(expected) == 4040
    assert access.read_name(service, "TEMPC::f_is_active", 1) is True
    # the drive gets command + every position compensation; the display does not
    total = access.read_name(service, "SIM::total_offset", 1)
    assert access.read_name(service, "SIM::command_position", 1) == 1_000_000
    assert access.read_name(service, "SIM::output_position", 1) == 1_000_000 + total


def test_temperature_coefficient_write_ramps_cycle_by_cycle(service):
    access.write_name(service, "SIM::set_position", 1, 1_000_000)
    access.step(service, 25)
    old = 40 + 4000e-6 * 999_900
    new = 40 + 2500e-6 * 999_900
    access.write_name(service, "TEMPC::coefficient", 1, 2500.0)
    for k in range(1, 21):
        access.step(service, 1)
        assert access.read_name(service, "TEMPC::actual_offset", 1) == rhaz(
            sin2_ramp(old, new, k, 20)
        )
    assert access.read_name(service, "TEMPC::coefficient", 1) == 2500.0


def test_unhomed_axis_has_no_temperature_offset(default_cfg):
    svc = ObjectService(Machine(default_cfg, homed=False))
    access.write_name(svc, "SIM::set_position", 1, 1_000_000)
    access.step(svc, 30)
    assert access.read_name(svc, "TEMPC::activated", 1) is True
    assert access.read_name(svc, "TEMPC::f_is_active", 1) is False
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 0
    access.write_name(svc, "SIM::homed", 1, True)
    access.step(svc, 20)
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 4040


# ------------------------------------------------------------------------- backlash


def test_backlash_manual_example_reversal(service):
    # 000 p.13: lose 1000, anwahl_losekomp 1 (positive), n_backlash_cyc 10.
    access.step(service, 2)
    assert access.read_name(service, "BC::conf. backlash", 1) == 1000
    assert access.read_name(service, "BC::actual backlash", 1) == 0
    access.write_name(service, "SIM::target_position", 1, -100_000)  # move negative: a reversal
    previous = 0
    for k in range(1, 11):
        access.step(service, 1)
        expected = rhaz(-1000 * math.sin(math.pi * k / 20) ** 2)
        assert access.read_name(service, "BC::actual backlash", 1) == expected
        assert access.read_name(service, "BC::delta backlash", 1) == expected - previous
        assert access.read_name(service, "BC::sum backlash", 1) == -1000
        previous = expected
    access.step(service, 1)
    assert access.read_name(service, "BC::actual backlash", 1) == -1000
    assert access.read_name(service, "BC::delta backlash", 1) == 0


# ------------------------------------------------------------------------- COMP, monitoring


def _run_until_done(machine: Machine, limit: int = 5000) -> None:
    for _ in range(limit):
        machine.run_cycle()
        if machine.player is None or not machine.player.running:
            return
    raise AssertionError("program did not finish")


def test_comp_off_is_program_global(machine):
    machine.step(1)
    machine.start_program("N10 X[COMP OFF TEMP]\nN20 M30\n")
    _run_until_done(machine)
    machine.step(25)
    svc = ObjectService(machine)
    assert access.read_name(svc, "TEMPC::activated", 1) is False
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 0


def test_manual_activation_is_deselected_at_program_end(default_cfg):
    cfg = with_params(default_cfg, 1, temp_comp_manual_activation=True)
    machine = Machine(cfg, homed=True)
    svc = ObjectService(machine)
    machine.step(1)
    assert access.read_name(svc, "TEMPC::activated", 1) is False  # manual: off until COMP ON
    machine.start_program("N10 X[COMP ON TEMP]\nN20 G04 0.05\nN30 M30\n")
    machine.step(5)
    assert access.read_name(svc, "TEMPC::activated", 1) is True
    _run_until_done(machine)
    assert access.read_name(svc, "TEMPC::activated", 1) is False


def test_comp_on_frict_without_parameter_is_70495(service):
    # Y has lr_param.frict_comp 0 in the default machine.
    service.nc.run("Y[COMP ON FRICT]")
    access.step(service, 3)
    assert [e["error_id"] for e in service.errors()][-1] == 70495
    assert access.read_name(service, "SIM::last_error_id") == 70495


def test_required_compensations_are_monitored_70435(default_cfg):
    # Y: prog_movement_requires_compensations LEAD | TEMP; unhomed, neither is effective.
    svc = ObjectService(Machine(default_cfg, homed=False))
    svc.nc.run("G01 Y10 F1000")
    access.step(svc, 5)
    assert [e["error_id"] for e in svc.errors()][-1] == 70435
    assert access.read_name(svc, "SIM::command_position", 2) == 0  # the move was not started
    access.write_name(svc, "SIM::homed", 2, True)
    access.step(svc, 2)
    svc.nc.run("G01 Y10 F1000")
    access.step(svc, 2000)
    assert access.read_name(svc, "SIM::command_position", 2) == 100_000
    assert [e["error_id"] for e in svc.errors()].count(70435) == 1


def test_70435_while_moving_is_reported_in_the_motion(default_cfg):
    """Issue 45 #5, 000 §5.3 p.97: Y requires LEAD | TEMP, both need the axis referenced.
    Y loses its reference 100 cycles into a 10 mm move: 70435 comes in that motion (within
    the two cycles a write and the effective flags it changes take), the axis stops
    short of its target (a controlled stop), and the program's next block never runs."""
    machine = Machine(default_cfg, cycle_s=0.001, homed=True)
    svc = ObjectService(machine)
    svc.nc.run("N10 G01 Y10 F1000\nN20 X5")
    access.step(svc, 100)
    before = access.read_name(svc, "SIM::command_position", 2)
    assert 0 < before < 100_000 and not svc.errors()
    access.write_name(svc, "SIM::homed", 2, False)
    access.step(svc, 2)
    assert [e["error_id"] for e in svc.errors()] == [70435]
    assert machine.player is not None and machine.player.error is not None
    assert machine.player.error.line == 1
    access.step(svc, 2000)
    after = access.read_name(svc, "SIM::command_position", 2)
    assert before < after < 100_000  # decelerated from where it was, never arrived
    assert access.read_name(svc, "SIM::command_position", 1) == 0  # N20 never ran
    assert access.read_name(svc, "SIM::velocity", 2) == 0
    assert access.read_name(svc, "SIM::program_running") is False


# ------------------------------------------------------------------------- service errors


def test_read_lengths_and_batch_from_one_snapshot(service):
    access.step(service, 1)
    with pytest.raises(AdsError) as e:
        service.read(0x120300, 0x10043, 4)
    assert e.value.code == 0x705
    assert len(service.read(0x120300, 0x10043, 100)) == 8  # never more than the object
    out = service.read_many(
        [(0x120300, 0x10043, 8), (0x120300, 0x19999, 4), (0x12F300, 0x00001, 4)]
    )
    assert out[0] == service.read(0x120300, 0x10043)
    assert isinstance(out[1], AdsError) and out[1].code == 0x703
    assert out[2] == (1).to_bytes(4, "little")
    with pytest.raises(AdsError) as e:
        access.write_name(service, "BC::actual backlash", 1, 5)
    assert e.value.code == 0x704


# ------------------------------------------------------------------------- reload, save


def test_rejected_reload_changes_nothing(lists_copy: Path):
    cfg = load_machine(lists_copy)
    a = Machine(load_machine(lists_copy), homed=True)
    b = Machine(cfg, homed=True)  # the twin that never sees the reload
    svc = ObjectService(a)
    cfg_before = a.cfg
    a.step(30)
    b.step(30)
    axis_list = Path(cfg.axes[1].params.path)
    text = axis_list.read_text(encoding="utf-8")
    axis_list.write_text(
        text.replace("lr_param.temp_comp_coefficient 4000", "lr_param.temp_comp_coefficient 99999"),
        encoding="utf-8",
    )
    result = svc.commands.reload()
    assert not result.ok
    assert any("achsmd1.lis" in e and "temp_comp_coefficient" in e for e in result.errors)
    assert a.cfg is cfg_before
    a.step(40)
    b.step(40)
    np.testing.assert_array_equal(a.snapshot.values, b.snapshot.values)


def _set_coefficient_in_the_list(svc: ObjectService, text: str) -> None:
    """Axis 1's list says `lr_param.temp_comp_coefficient <text>` instead of 4000."""
    axis_list = Path(svc.info.config.axes[1].params.path)
    before = axis_list.read_text(encoding="utf-8")
    after = before.replace("temp_comp_coefficient 4000", f"temp_comp_coefficient {text}")
    assert after != before
    axis_list.write_text(after, encoding="utf-8")


def test_valid_reload_ramps_to_the_new_value(lists_copy: Path):
    svc = ObjectService(Machine(load_machine(lists_copy), homed=True))
    access.write_name(svc, "SIM::set_position", 1, 1_000_000)
    access.step(svc, 30)
    _set_coefficient_in_the_list(svc, "2000")
    result = svc.commands.reload()
    assert result.ok, result.errors
    old, new = 40 + 4000e-6 * 999_900, 40 + 2000e-6 * 999_900
    access.step(svc, 10)
    assert (
        access.read_name(svc, "TEMPC::actual_offset", 1)
        == rhaz(sin2_ramp(old, new, 10, 20))
        == 3040
    )
    access.step(svc, 10)
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 2040
    assert access.read_name(svc, "TEMPC::coefficient", 1) == 2000.0


def test_save_round_trips(lists_copy: Path):
    svc = ObjectService(Machine(load_machine(lists_copy), homed=True))
    axis_list = Path(svc.info.config.axes[1].params.path)
    before = axis_list.read_bytes()
    access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
    access.write_name(svc, "TEMPC::offset_0", 1, -7)
    access.step(svc, 1)
    result = svc.commands.save()
    assert result.ok and result.files == [str(axis_list)]
    after = axis_list.read_bytes()
    assert after == before.replace(b"coefficient 4000 ", b"coefficient 1234.5 ").replace(
        b"offset_0 40 ", b"offset_0 -7 "
    )
    cfg = load_machine(lists_copy)
    assert cfg.axes[1].params.temp_comp_coefficient == 1234.5
    assert cfg.axes[1].params.temp_comp_offset_0 == -7
    # the configuration as saved is the machine's from the next cycle boundary on (a
    # new one, swapped whole: a loaded configuration never changes under its readers)
    access.step(svc, 1)
    assert svc.info.config.axes[1].params.temp_comp_coefficient == 1234.5
    assert svc.commands.save().files == []  # nothing changed since: nothing written


def test_a_loaded_configuration_is_read_only(lists_copy: Path):
    """What an interface reads of the machine (`info.config`) cannot be changed under it
    (docs/design.md §4.4-4.5): a write to any part is refused; a save makes a new
    configuration, swapped at the next cycle boundary, and the one a reader holds stays
    as it was (4000 is the list's coefficient of axis 1)."""
    svc = ObjectService(Machine(load_machine(lists_copy), homed=True))
    cfg = svc.info.config
    with pytest.raises(AttributeError, match="read-only"):
        cfg.axes[1].params.temp_comp_coefficient = 1.0
    with pytest.raises(AttributeError, match="read-only"):
        cfg.startup_path = Path("/etc/passwd")
    comp = cfg.axes[1].comp
    assert comp is not None
    with pytest.raises(AttributeError, match="read-only"):
        comp.lsec = None
    access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
    access.step(svc, 1)
    assert svc.commands.save().ok
    access.step(svc, 1)
    assert cfg.axes[1].params.temp_comp_coefficient == 4000.0
    assert svc.info.config.axes[1].params.temp_comp_coefficient == 1234.5


# ------------------------------------------------------------------------- determinism


@pytest.mark.realtime
def test_stepped_and_free_running_give_identical_values(default_cfg):
    program = (data_dir("lists") / "demo_temperature.nc").read_text(encoding="utf-8")
    n = 3000
    stepped = Machine(default_cfg, homed=False)
    stepped.start_program(program)
    want = {}
    for _ in range(n):
        snap = stepped.run_cycle()
        if snap.cycle % 50 == 0:
            want[snap.cycle] = snap.values.copy()
    free = Machine(load_machine(default_cfg.startup_path), homed=False)
    free.start_program(program)
    got: dict[int, np.ndarray] = {}
    done = threading.Event()

    def record(snap) -> None:
        if snap.cycle % 50 == 0 and snap.cycle <= n:
            got[snap.cycle] = snap.values.copy()
        if snap.cycle >= n:
            done.set()

    free.listeners.append(record)
    sched = Scheduler(free, mode="free")
    sched.start()
    assert done.wait(60)
    sched.stop()
    assert sorted(got) == sorted(want)
    moved = False
    for cycle, values in want.items():
        np.testing.assert_array_equal(got[cycle], values, err_msg=f"cycle {cycle}")
        moved |= bool(values[0, stepped.layout.col("SIM::velocity")] != 0)
    assert moved  # the program really ran


@pytest.mark.realtime
def test_realtime_scheduler_runs_and_reports(default_cfg):
    machine = Machine(default_cfg, cycle_s=0.001)
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    sched.start()
    try:
        deadline = threading.Event()
        deadline.wait(0.3)
        # a status is an observation: the engine (asleep at rest) catches up to it first
        st = service.status()
    finally:
        sched.stop()
    assert st["cycle"] > 50  # ~300 cycles at 1 ms; generous for a loaded CI machine
    assert st["cycle"] == machine.cycle
    assert st["lateness_p50_us"] >= 0 and st["lateness_max_us"] >= st["lateness_p99_us"]
    assert access.read_name(ObjectService(machine, sched), "SIM::cycle_time_us") == 1000


def test_nc_while_a_program_runs_is_refused_and_reset_stops_it(service):
    service.nc.run("G90 G01 X50 F6000")
    access.step(service, 100)  # X still moving (50 mm at 100 mm/s takes 500 ms)
    assert access.read_name(service, "SIM::velocity", 1) != 0
    fut = service.nc.run("G90 G01 X-50 F6000")
    write = access.write_name(service, "TEMPC::coefficient", 1, 4100.0)
    access.step(service, 1)
    assert write.result(timeout=1) is None  # the cycle ran; the write was answered
    with pytest.raises(AdsError) as e:
        fut.result(timeout=1)
    assert e.value.code == 0x708
    assert access.read_name(service, "TEMPC::coefficient", 1) == 4100.0
    service.nc.reset()
    access.step(service, 400)  # a controlled stop, then standstill
    assert access.read_name(service, "SIM::velocity", 1) == 0
    service.nc.run("G90 G01 X0 F6000")
    access.step(service, 2000)
    assert access.read_name(service, "SIM::command_position", 1) == 0
    assert service.current(stale_ok=True).cycle == 2501


def test_a_move_the_machine_cannot_start_ends_the_program_not_the_cycle(service):
    access.write_name(service, "SIM::target_position", 1, 500_000)  # a single-axis move
    access.step(service, 10)
    service.nc.run("G90 G01 X0 F6000")  # X is busy: the program must end with an error
    access.step(service, 3)
    assert service.current(stale_ok=True).cycle == 13
    assert "NC program stopped" in service.errors()[-1]["message"]


def _first_moving_cycle(machine: Machine, program: str) -> int:
    """Cycles from the program start until X's command velocity is non-zero."""
    machine.step(30)  # temperature ramp of start-up over (temp_comp_n_cycles 20)
    svc = ObjectService(machine)
    machine.start_program(program)
    for n in range(1, 200):
        machine.run_cycle()
        if access.read_name(svc, "SIM::velocity", 1) != 0:
            return n
    raise AssertionError("X never moved")


def test_comp_switch_waits_for_the_offset_unless_no_move(default_cfg):
    """000 §5.1: the position offset of COMP ON/OFF is executed before the program goes
    on; NO_MOVE suppresses the wait. X's temperature ramp is temp_comp_n_cycles = 20."""
    prog = "N10 X[COMP OFF TEMP{}]\nN20 G91 G01 X1 F6000\nN30 M30\n"
    waited = _first_moving_cycle(Machine(default_cfg, homed=True), prog.format(""))
    # cycle 1 issues COMP (ramp k = 1), k = 20 in cycle 20, the wait ends in cycle 21
    # and the move starts with its first motion step in that cycle
    assert waited == 21
    direct = _first_moving_cycle(Machine(default_cfg, homed=True), prog.format(" NO_MOVE"))
    assert direct == 1  # no wait: the move block runs in the same cycle as the COMP block


def test_lsec_objects_on_y_follow_the_table_by_direction(machine):
    """Y's bilateral LSEC table (lists/achskw2.lis) read through the objects. At
    s = 60000 (6 mm) the table points are setpoint[68] 58446 / [69] 62475 with pos 14 /
    15 and neg 178 / 180; the applied offset is −Δs (000 §4.4, docs/design.md §6). The program
    starts before the first cycle: Y requires LEAD | TEMP, and the 70435 monitoring must
    see them effective."""
    svc = ObjectService(machine)
    frac = (60000 - 58446) / (62475 - 58446)  # 0.3857
    machine.start_program("G90 G01 Y6 F6000\nM30\n")  # from 0 in the positive direction
    _run_until_done(machine)
    machine.step(10)  # reversal ramp (n_backlash_cyc 5) over
    assert access.read_name(svc, "ssfk activated", 2) is True
    assert access.read_name(svc, "LSEC::active", 2) is True
    assert access.read_name(svc, "LSEC::sum epsilon", 2) == round(-(14 + frac * 1))  # −14.39 → −14
    assert access.read_name(svc, "LSEC::epsilon", 2) == 0  # standing: no change this cycle
    machine.start_program("G90 G01 Y7 F6000\nG01 Y6\nM30\n")  # arrive from above
    _run_until_done(machine)
    machine.step(10)
    assert access.read_name(svc, "LSEC::sum epsilon", 2) == round(
        -(178 + frac * 2)
    )  # −178.77 → −179


def test_rejected_reload_of_a_broken_compensation_list_keeps_the_old_tables(lists_copy: Path):
    """A table that would be deactivated is a reload error (docs/design.md §4): nothing swaps."""
    machine = Machine(load_machine(lists_copy), homed=True)
    svc = ObjectService(machine)
    cfg_before = machine.cfg
    machine.step(30)
    before = access.read_name(svc, "LSEC::sum epsilon", 2)
    comp = lists_copy.parent / "achskw2.lis"
    comp.write_text(
        comp.read_text(encoding="utf-8").replace(
            "kw.ssfk.table[1].setpoint -199306", "kw.ssfk.table[1].setpoint -300000"
        ),
        encoding="utf-8",
    )
    result = svc.commands.reload()
    assert not result.ok
    assert any("achskw2.lis" in e for e in result.errors)
    assert machine.cfg is cfg_before
    machine.step(10)
    assert access.read_name(svc, "LSEC::active", 2) is True
    assert access.read_name(svc, "LSEC::sum epsilon", 2) == before == -98  # Y at 0, neg table


def test_invalid_table_is_selected_but_not_effective(lists_copy: Path):
    """000 §4.4.4: a defective LSEC table deactivates the function for the axis; the
    parameter still selects it (`ssfk activated`), `LSEC::active` stays FALSE and no
    offset is applied."""
    comp = lists_copy.parent / "achskw2.lis"
    comp.write_text(
        comp.read_text(encoding="utf-8").replace(
            "kw.ssfk.table[1].setpoint -199306", "kw.ssfk.table[1].setpoint -300000"
        ),
        encoding="utf-8",
    )
    machine = Machine(load_machine(lists_copy), homed=True)
    svc = ObjectService(machine)
    machine.step(20)
    assert access.read_name(svc, "ssfk activated", 2) is True
    assert access.read_name(svc, "LSEC::active", 2) is False
    assert access.read_name(svc, "LSEC::sum epsilon", 2) == 0


def test_reset_deselects_manual_activation_compensations(default_cfg):
    """000 §5.1: compensations selected by COMP ON under manual activation are
    deselected by a CNC reset (as at program end)."""
    cfg = with_params(default_cfg, 1, temp_comp_manual_activation=True)
    machine = Machine(cfg, homed=True)
    svc = ObjectService(machine)
    machine.start_program("N10 X[COMP ON TEMP]\nN20 G04 10\nN30 M30\n")
    machine.step(40)
    assert access.read_name(svc, "TEMPC::activated", 1) is True
    # X at 0: offset_0 + coefficient·1e-6·(s − position_0) = 40 + 4000e-6·(0 − 100) = 39.6
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 40
    machine.reset()
    machine.step(1)
    assert access.read_name(svc, "TEMPC::activated", 1) is False
    assert machine.player is not None and not machine.player.running


# ---------------------------------------------------------------------- refusals listed


def test_refused_writes_and_nc_text_are_in_the_error_list(default_cfg):
    """Issue 31: a refused write (0x706) and NC text that does not parse (0x70D) are
    answered and also listed, as a rejected reload is: in the errors and in
    SIM::last_error. At most ten a second are listed, the rest counted."""
    from geo_server.errors import AdsError
    from geo_server.service import REFUSALS_PER_SECOND, ObjectService

    service = ObjectService(Machine(default_cfg, homed=True))
    with pytest.raises(AdsError) as refused:
        access.write_name(service, "TEMPC::coefficient", 1, 20000)  # range ±10000 µm/m (000 p.22)
    assert refused.value.code == 0x706
    with pytest.raises(AdsError) as bad_nc:
        service.nc.run("G01 X10 F$")
    assert bad_nc.value.code == 0x70D
    access.step(service, 1)
    last_two = [e["message"] for e in service.errors()[-2:]]
    assert last_two[0].startswith("write refused: ") and last_two[0].endswith("(ADS 0x706)")
    assert "TEMPC::coefficient" in last_two[0]
    assert last_two[1].startswith("NC text refused: ") and last_two[1].endswith("(ADS 0x70D)")
    assert access.read_name(service, "SIM::last_error", 0).endswith(last_two[1])
    # a client sending bad values in a loop: the list takes ten a second, counts the rest
    before = len(service.errors())
    for _ in range(3 * REFUSALS_PER_SECOND):
        with pytest.raises(AdsError):
            access.write_name(service, "TEMPC::coefficient", 1, 20000)
    access.step(service, 1)
    listed = len(service.errors()) - before
    assert listed <= 2 * REFUSALS_PER_SECOND  # the loop may straddle a second
    assert listed + service.status()["refusals_unreported"] == 3 * REFUSALS_PER_SECOND


def test_nc_run_applied_returns_the_cycle_that_ran_its_first_block(default_cfg):
    """`NC started at cycle N` (geo-client nc): N is the first cycle whose snapshot shows
    the program running, not the cycle of the snapshot after the wait (which came
    later than the program's first messages)."""
    import asyncio

    machine = Machine(default_cfg, cycle_s=0.001, homed=True)
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    running: list[int] = []
    obj = load_dictionary().by_name("SIM::program_running")

    def seen(snap) -> None:  # (the cycle's thread)
        if snap.value(obj, 0) and not running:
            running.append(snap.cycle)

    unsubscribe = service.subscribe(seen)
    release = sched.demand_every_cycle()
    sched.start()
    try:
        started = asyncio.run(service.nc.run_applied("N10 G91 G01 X10 F600\nM30"))
        deadline = threading.Event()
        for _ in range(200):
            if running:
                break
            deadline.wait(0.01)
    finally:
        release()
        unsubscribe()
        sched.stop()
    assert running == [started]


def test_reload_says_which_value_it_replaced_by_its_default(lists_copy: Path):
    """A reload of a list whose coefficient reads `40O0` goes through (the CNC's rule,
    002/003 §1.3: warn, use the default) and its answer names the file, line, entry and
    value it replaced."""
    svc = ObjectService(Machine(load_machine(lists_copy), homed=True))
    _set_coefficient_in_the_list(svc, "40O0")
    result = svc.commands.reload()
    assert result.ok, result.errors
    (warning,) = [w for w in result.warnings if "40O0" in w]
    assert "achsmd1.lis:" in warning and "lr_param.temp_comp_coefficient" in warning
    assert "default used" in warning


@pytest.mark.parametrize("scope", ["axis", "machine"])
def test_a_readable_object_nothing_feeds_is_refused_at_load(default_cfg, scope: str) -> None:
    """Issue 47: an object added to objects.toml that the machine does not compute read
    0 without a word. The machine refuses it when it is built, naming it; a write-only
    one (a command, a trigger) needs no source."""
    from dataclasses import replace

    from geo_server.dictionary import Dictionary

    base = load_dictionary()
    template = base.by_name("SIM::cycle_count")
    extra = replace(template, name="SIM::nobody_feeds", id=0x0FF0, scope=scope, aliases=())
    with pytest.raises(ValueError, match=r"nothing feeds the readable object\(s\) SIM::nobody"):
        Machine(default_cfg, dictionary=Dictionary([*base.objects, extra]))
    written = replace(extra, access="w")
    Machine(default_cfg, dictionary=Dictionary([*base.objects, written]))
