"""Measurement on the twin (docs/twin.md): the ISO 230-2 test cycle, the commissioning
values, the closed loop measure → lists → reload → measure, the reference measurement,
`geo-server measure` and the Zenoh command `cmd/measure`.

Expected values are worked out by hand from the twin files written here: a scale error
of s µm/m reads s·P/1000 µm at P mm; lost motion L µm moving against the reference
direction puts every negative approach L µm higher (ISO 230-2 §2.12: B_i = −L).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from geo_server import access
from geo_server.cli import main as cli_main
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.twin import iso230
from geo_server.twin.measure import (
    MeasureError,
    MeasurementPlan,
    StepBench,
    commission,
    plan_from_json,
    reference_measurement,
    run_test,
    write_lists,
)

AXIS_LIST = """kopf.achs_nr 1
kopf.log_achs_name X
kenngr.achs_typ 1
getriebe[0].vb_max 500000
getriebe[0].a_max 2000
getriebe[0].lose 0
lr_param.anwahl_losekomp 1
lr_param.n_backlash_cyc 1
lr_param.ssfk 1
"""
COMP_LIST = """kopf.achs_nr 1
kopf.log_achs_name X
kw.ssfk.unit 1
kw.ssfk.interval 500000
kw.ssfk.kw_startpos 0
kw.ssfk.kw_nr_max 3
kw.ssfk.bilateral 0
kw.ssfk.table[0].pos 0
kw.ssfk.table[1].pos 0
kw.ssfk.table[2].pos 0
"""
STARTUP = """zahl_mds 1
achs_mds[0] achsmd1.lis
achs_mds_log_ax_nr[0] 1
zahl_kw 1
achs_kw[0] achskw1.lis
achs_kw_log_ax_nr[0] 1
"""
#: 100 µm/m scale error about 0, 4 µm lost motion moving negative; nothing random
TWIN = """[axis.X]
linear = { offset = 0.0, slope = 100.0, reference = 0.0 }
reversal = 4.0
reference_direction = 1
"""
TARGETS = (0.0, 50.0, 100.0)  # the LSEC setpoints of COMP_LIST: 0, 500 000, 1 000 000


def simple_machine(folder: Path, twin: str = TWIN) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in (
        ("achsmd1.lis", AXIS_LIST),
        ("achskw1.lis", COMP_LIST),
        ("hochlauf.lis", STARTUP),
        ("twin.toml", twin),
    ):
        (folder / name).write_text(text, encoding="utf-8")
    return folder / "hochlauf.lis"


def stepped(startup: Path) -> ObjectService:
    return ObjectService(Machine(load_machine(startup), homed=True))


def plan(**kw) -> MeasurementPlan:
    return MeasurementPlan(**{"axis": 1, "targets": TARGETS, "runs": 2, "dwell_s": 0.01, **kw})


# ---------------------------------------------------------------------- the test cycle


def test_the_test_cycle_reads_the_twin_by_hand(tmp_path):
    """x↑ = 0.1 µm/mm · P = 0, 5, 10 µm; x↓ = x↑ + 4 µm. Then ISO 230-2: x̄ = 2, 7, 12;
    B_i = −4, B = 4, B̄ = −4; s = 0 so R↑ = R↓ = 0 and R = |B| = 4; E↑ = E↓ = 10,
    E = 14 − 0 = 14; M = 12 − 2 = 10; A = E = 14."""
    ev = run_test(StepBench(stepped(simple_machine(tmp_path))), plan())
    assert ev.mean_up == pytest.approx([0.0, 5.0, 10.0], abs=1e-6)
    assert ev.mean_down == pytest.approx([4.0, 9.0, 14.0], abs=1e-6)
    assert ev.mean == pytest.approx([2.0, 7.0, 12.0], abs=1e-6)
    assert ev.reversal == pytest.approx(4.0) and ev.mean_reversal == pytest.approx(-4.0)
    assert ev.repeatability_up == pytest.approx(0.0, abs=1e-6)
    assert ev.repeatability == pytest.approx(4.0)
    assert ev.systematic_up == pytest.approx(10.0) and ev.systematic == pytest.approx(14.0)
    assert ev.mean_error == pytest.approx(10.0) and ev.accuracy == pytest.approx(14.0)


def test_plan_errors_are_specific(tmp_path):
    svc = stepped(simple_machine(tmp_path))
    bench = StepBench(svc)
    with pytest.raises(MeasureError, match="ascend"):
        run_test(bench, plan(targets=(50.0, 0.0)))
    with pytest.raises(MeasureError, match="finite"):
        run_test(bench, plan(targets=(0.0, float("nan"))))
    # without an overrun the first and the last target would be reached from the wrong
    # side (ISO 230-2 §5): refused
    with pytest.raises(MeasureError, match="overrun"):
        run_test(bench, plan(overrun=0.0))
    access.write_name(svc, "SIM::homed", 1, False)
    access.step(svc, 1)
    with pytest.raises(MeasureError, match="not homed"):
        run_test(bench, plan())
    cfg = svc.info.config
    assert plan_from_json({"axis": "x"}, cfg).targets == TARGETS  # the LSEC setpoints
    assert plan_from_json({"axis": 1, "runs": 3, "off": ["lead"]}, cfg).compensation_off == (
        "LEAD",
    )
    for spec, match in (
        ([], "JSON object"),
        ({"axis": 1, "targets": [0, 1e400]}, "finite"),
        ({"axis": 1, "targets": [10, 0]}, "ascend"),
        ({"axis": 1, "overrun": 0}, "overrun"),
        ({"axis": 1, "targets": [0, 300_000]}, "within"),
        ({"axis": "Q"}, "not an axis"),
        ({"axis": 1, "runs": 1}, "runs"),
        ({"axis": 1, "targets": [0, "a"]}, "numbers"),
        ({"axis": 1, "targets": [0]}, "2 …"),
        ({"axis": 1, "dwell_s": -1}, "dwell_s"),
        ({"axis": 1, "off": ["WARP"]}, "off must"),
        ({"axis": 1, "speed": 2}, "unknown"),
    ):
        with pytest.raises(MeasureError, match=match):
            plan_from_json(spec, cfg)


# ---------------------------------------------------------------------- commissioning


def test_commission_values_by_hand():
    """Unilateral, reference direction + (anwahl_losekomp 1): the table is x̄↑ in 0.1 µm,
    the backlash mean(x↓ − x↑) = 4 µm = 40 increments; reference direction −: the
    table is x̄↓ and the backlash mean(x↑ − x↓)·(−1) = 40 again; bilateral: both tables,
    the backlash left alone."""
    up = np.array([[0.0, 5.0, 10.0], [0.0, 5.0, 10.0]])
    ev = iso230.evaluate(TARGETS, up, up + 4.0)
    c = commission(ev, 1, bilateral=False, reference_direction=1)
    assert c.setpoints == (0, 500_000, 1_000_000)
    assert c.pos == (0, 50, 100) and c.neg is None and c.backlash == 40
    c = commission(ev, 1, bilateral=False, reference_direction=-1)
    assert c.pos == (40, 90, 140) and c.backlash == 40
    c = commission(ev, 1, bilateral=True, reference_direction=1)
    assert (c.pos, c.neg, c.backlash) == ((0, 50, 100), (40, 90, 140), None)


def test_the_loop_closes_on_a_simple_machine(tmp_path):
    """Measured with LSEC and backlash off, written, reloaded, measured again: the scale
    error and the lost motion are gone to the interpolation's second order (0.1 µm/mm
    of a 10 µm correction: 0.001 µm)."""
    startup = simple_machine(tmp_path)
    svc = stepped(startup)
    bench = StepBench(svc)
    before = run_test(bench, plan(compensation_off=("LEAD", "BACKLASH")))
    c = commission(before, 1, bilateral=False, reference_direction=1)
    written = write_lists(c, tmp_path / "achsmd1.lis", tmp_path / "achskw1.lis")
    assert written == [str(tmp_path / "achskw1.lis"), str(tmp_path / "achsmd1.lis")]
    text = (tmp_path / "achskw1.lis").read_text(encoding="utf-8")
    assert "kw.ssfk.table[1].pos 50\n" in text and "kw.ssfk.table[2].pos 100\n" in text
    assert "getriebe[0].lose 40\n" in (tmp_path / "achsmd1.lis").read_text(encoding="utf-8")
    assert svc.commands.reload().ok
    after = run_test(bench, plan())
    assert np.abs(after.mean_up).max() < 0.01 and np.abs(after.mean_down).max() < 0.01
    assert after.accuracy < 0.02 and before.accuracy == pytest.approx(14.0)


# ---------------------------------------------------------------------- reference


def test_reference_measurement_by_hand(tmp_path):
    """Expansion 10 µm/m/K about 0, no other error: in the chamber at 30 °C the axis is
    10e-6 · 10 K · P long, 5 µm at 50 mm, 10 µm at 100 mm; the rows say what the
    compensation must add, the negative. No heat from motion: the sensor reads 30.0."""
    twin = """[[node]]
name = "screw"
tau = 600.0
initial = 20.0

[[sensor]]
name = "screw"
node = "screw"
axis = "X"
noise = 0.0
resolution = 0.01

[axis.X]
expansion = { node = "screw", coefficient = 10.0, reference = 0.0 }
"""
    bench = StepBench(stepped(simple_machine(tmp_path, twin)))
    points = reference_measurement(bench, plan(), [20.0, 30.0])
    assert [p.temperature for p in points] == [20.0, 30.0]
    rows = [r for p in points for r in p.rows(1)]
    assert [r[:3] for r in rows] == [(1, t, p) for t in (20.0, 30.0) for p in TARGETS]
    assert [r[3] for r in rows] == pytest.approx([0, 0, 0, 0, -5.0, -10.0], abs=1e-4)
    # the PLC client reads the CSV: 100 µm/m more compensation per 10 K
    from geo_clients.plc_tempcomp import parse_reference

    table = parse_reference(iso230.reference_csv(rows))
    lines = table.lines(1)
    assert [ln.coefficient for ln in lines] == pytest.approx([0.0, -100.0], abs=1e-3)


def test_reference_rows_add_the_active_temperature_compensation(tmp_path):
    """Measured with the compensation on, a row is the whole line: active + residual. X
    of the default machine: TEMPC position_0 100, offset_0 40, 4000 µm/m (000 p.24), so
    at 0 mm the compensation adds 4 + 4000e-6·(0 − 0.01) mm = 3.96 µm."""
    svc = ObjectService(Machine(load_machine(default_startup_list()), homed=True))
    points = reference_measurement(
        StepBench(svc), MeasurementPlan(1, (0.0, 100.0), 2, 1.0, 0.01), [20]
    )
    assert points[0].tempc == (100.0, 4.0, 4000.0)
    rows = points[0].rows(1)
    active = [3.96, 4 + 4000e-6 * (100 - 0.01) * 1000]  # µm
    residual = points[0].evaluation.mean
    # the rows carry 4 decimals (0.0001 µm): half of the last one
    assert [r[3] for r in rows] == pytest.approx(
        [a - x for a, x in zip(active, residual, strict=True)], abs=5e-5
    )
    assert np.abs(residual).max() < 1.0  # the twin is commissioned at 20 °C


# ---------------------------------------------------------------------- the default machine


def list_values(path: Path, key: str) -> list[int]:
    """The LSEC values of a list, read with a regular expression (not our loader)."""
    found = re.findall(rf"^kw\.ssfk\.table\[(\d+)\]\.{key} (-?\d+)", path.read_text(), re.M)
    return [int(v) for _, v in sorted(found, key=lambda f: int(f[0]))]


@pytest.mark.slow
def test_commissioning_the_default_machine_reproduces_its_lists(tmp_path):
    """`geo-server measure --commission` on X of a copy of the default machine: the
    LSEC table it writes is the shipped one (the twin is the machine those lists were
    commissioned on, docs/twin.md) within the scatter and the warming of the test itself,
    the backlash is the list's 1000 (0.1 mm, 000 p.13), and after the reload the axis
    is left with its noise and interpolation floor; the figures and plots are written."""
    assert cli_main(["init", str(tmp_path / "m")]) == 0
    shipped = list_values(tmp_path / "m" / "achskw1.lis", "pos")
    out = tmp_path / "out"
    argv = ["measure", str(tmp_path / "m" / "hochlauf.lis"), "--axis", "X", "--commission"]
    argv += ["--runs", "2", "--dwell", "0.02", "--out", str(out), "--plot"]
    assert cli_main(argv) == 0
    measured = list_values(tmp_path / "m" / "achskw1.lis", "pos")
    assert len(measured) == len(shipped) == 101
    diff = np.array(measured) - np.array(shipped)
    assert np.abs(diff).max() <= 6  # 0.6 µm
    assert np.abs(diff).mean() <= 2.5
    lose = re.search(
        r"^getriebe\[0\]\.lose (\d+)", (tmp_path / "m" / "achsmd1.lis").read_text(), re.M
    )
    assert lose is not None and abs(int(lose.group(1)) - 1000) <= 3
    result = json.loads((out / "result.json").read_text())
    before, after = result["before"]["figures"], result["after"]["figures"]
    # before: the 100 µm lost motion and the 11 µm pitch error (the lists' −8 µm trend,
    # ±2 µm periodic, 1.5 µm bow); after: the floor
    assert before["reversal"] == pytest.approx(100.0, abs=1.5)
    assert 10.0 < before["mean_error"] < 12.5
    assert after["systematic"] < 2.5 and after["accuracy"] < 5.0 and after["reversal"] < 1.5
    for name in ("error_curve.png", "error_curve.svg", "hysteresis.png", "deviations.csv"):
        assert (out / name).stat().st_size > 1000, name


def test_measure_refuses_to_commission_the_shipped_lists(capsys):
    assert cli_main(["measure", "--axis", "X", "--commission"]) == 2
    assert "geo-server init" in capsys.readouterr().err
    # named explicitly, the checkout's lists/ are the shipped machine all the same
    shipped = str(default_startup_list())
    assert cli_main(["measure", shipped, "--axis", "X", "--commission"]) == 2
    assert "geo-server init" in capsys.readouterr().err
    assert cli_main(["measure", "--axis", "X", "--targets", "0,nan"]) == 2
    assert "finite" in capsys.readouterr().err
    assert cli_main(["measure", "--axis", "X", "--overrun", "-5", "--targets", "0,10"]) == 2
    assert "overrun" in capsys.readouterr().err
    assert cli_main(["measure", "--axis", "Q"]) == 2
    assert "no axis 'Q'" in capsys.readouterr().err


def test_plot_without_matplotlib_is_refused_before_measuring(tmp_path, monkeypatch, capsys):
    """--plot without matplotlib is said at once (it used to be said after 220 s of
    commissioning): nothing is measured, no folder made."""
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    out = tmp_path / "out"
    argv = ["measure", "--axis", "X", "--targets", "0,10", "--plot", "--out", str(out)]
    assert cli_main(argv) == 2
    assert "pip install geo-server[plots]" in capsys.readouterr().err
    assert not out.exists()


# ---------------------------------------------------------------------- over Zenoh


def test_measure_over_zenoh(tmp_path):
    """`cmd/measure` with a JSON plan on a stepped test server (the service steps the
    machine itself): the figures by hand as above; a bad plan is 0x706."""
    from geo_clients.testing import GeoTestServer

    with GeoTestServer(simple_machine(tmp_path)) as srv:
        srv.start("zenoh")
        z = srv.client("zenoh")
        reply = z.measure({"axis": "X", "runs": 2, "dwell_s": 0.01}, timeout=60)
        assert reply["ok"] and reply["axis"] == 1
        assert reply["figures"]["systematic"] == pytest.approx(14.0, abs=1e-6)
        assert reply["per_target"]["mean_up"] == pytest.approx([0.0, 5.0, 10.0], abs=1e-6)
        with pytest.raises(AdsError) as err:
            z.measure({"axis": "X", "runs": 1})
        assert err.value.code == 0x706 and "runs" in err.value.message
        with pytest.raises(AdsError) as err:
            z.measure({"axis": "X", "targets": [10, 0]})
        assert err.value.code == 0x706 and "ascend" in err.value.message


@pytest.mark.realtime
def test_measure_on_a_free_running_machine(tmp_path):
    """A running machine (free mode: cycles back to back on their own thread): the
    service measures through object writes and waits on the cycles (`LiveBench`) — the
    same figures as in stepped mode, since the twin counts cycles, not clocks."""
    from geo_server.machine.scheduler import Scheduler

    machine = Machine(load_machine(simple_machine(tmp_path)), homed=True)
    sched = Scheduler(machine, mode="free")
    svc = ObjectService(machine, sched)
    sched.start()
    try:
        reply = svc.measurements.run({"axis": "X", "runs": 2, "dwell_s": 0.01})
    finally:
        sched.stop()
    assert reply["figures"]["systematic"] == pytest.approx(14.0, abs=1e-6)
    assert reply["figures"]["reversal"] == pytest.approx(4.0, abs=1e-6)


def test_a_plain_measurement_writes_list_files_ready_to_load(tmp_path):
    """`geo-server measure --off LEAD,BACKLASH` on the simple machine: lsec_X.lis is a
    compensation value list with the table x̄↑ = 0, 5, 10 µm at 0, 50, 100 mm (explicit
    setpoints), backlash_X.lis the 4 µm; loaded in place of the machine's own lists
    they close the loop."""
    startup = simple_machine(tmp_path / "m")
    out = tmp_path / "out"
    argv = ["measure", str(startup), "--axis", "X", "--runs", "2", "--dwell", "0.01"]
    assert cli_main([*argv, "--off", "LEAD,BACKLASH", "--out", str(out)]) == 0
    lsec = (out / "lsec_X.lis").read_text(encoding="utf-8")
    for line in (
        "kw.ssfk.interval 0",
        "kw.ssfk.kw_nr_max 3",
        "kw.ssfk.bilateral 0",
        "kw.ssfk.table[1].setpoint 500000",
        "kw.ssfk.table[1].pos 50",
        "kw.ssfk.table[2].pos 100",
    ):
        assert line in lsec.splitlines(), line
    backlash = (out / "backlash_X.lis").read_text(encoding="utf-8").splitlines()
    assert "getriebe[0].lose 40" in backlash and "lr_param.anwahl_losekomp 1" in backlash
    (tmp_path / "m" / "achskw1.lis").write_text(lsec, encoding="utf-8")
    axis_list = AXIS_LIST.replace("getriebe[0].lose 0", "getriebe[0].lose 40")
    (tmp_path / "m" / "achsmd1.lis").write_text(axis_list, encoding="utf-8")
    assert cli_main([*argv, "--out", str(tmp_path / "after")]) == 0
    after = json.loads((tmp_path / "after" / "result.json").read_text())["test"]["figures"]
    assert after["accuracy"] < 0.02


def test_the_compensations_are_restored_exactly(tmp_path):
    """Only what was selected is switched off and back on, one kind a line: backlash
    switched off before the test stays off; FRICT (not configured: `COMP ON FRICT`
    would fail, 000 p.73) is not touched, so LSEC comes back on."""
    svc = stepped(simple_machine(tmp_path))
    bench = StepBench(svc)
    bench.nc("X[COMP OFF BACKLASH]")
    assert not access.read_name(svc, "SIM::backlash_selected", 1)
    assert not access.read_name(svc, "SIM::friction_selected", 1)
    run_test(bench, plan(compensation_off=("LEAD", "BACKLASH", "FRICT")))
    assert access.read_name(svc, "ssfk activated", 1)
    assert not access.read_name(svc, "SIM::backlash_selected", 1)
    with pytest.raises(MeasureError, match="P-ERR-70495"):  # an NC error is not ignored
        bench.nc("X[COMP ON FRICT]")


def test_a_modulo_axis_is_measured(default_cfg):
    """C of the default machine is modulo 360°: its command position reads wrapped
    (−5° as 355°, 360° as 0°), the test still arrives and reads every target."""
    svc = ObjectService(Machine(default_cfg, homed=True))
    ev = run_test(StepBench(svc), MeasurementPlan(4, (0.0, 120.0, 240.0, 360.0), 2, 5.0, 0.01))
    assert ev.m == 4 and np.abs(ev.mean).max() < 5.0  # 0.001°: the LSEC table corrects C


def test_geo_warmup_strokes_a_modulo_axis():
    from geo_clients.warmup import run_warmup

    rec = run_warmup(hours=0.05, axis="C", stroke_mm=(400.0, 500.0), time_scale=100.0)
    assert len(rec.times_s) >= 2 and rec.times_s[-1] >= 180.0
