"""The recorder and golden traces (docs/recorder.md): selection, trigger, files, inputs,
replay, compare — in stepped mode with values that follow from the machine's lists, in
a real-time machine, over Zenoh and from the command line."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from conftest import geo_server_running
from geo_clients.testing import GeoTestServer, check_golden

from geo_server import access
from geo_server.cli import main as server_main
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.recorder import (
    Recorder,
    RecordSpec,
    SelectionError,
    Trace,
    TraceFileError,
    compare,
    load_trace,
    parse_tolerances,
    resolve_columns,
)
from geo_server.recorder.inputs import load_inputs
from geo_server.recorder.replay import replay
from geo_server.recorder.selection import parse_trigger
from geo_server.service import ObjectService

pytest.importorskip("pyarrow", reason="Parquet traces need pyarrow (the test extra)")

pytest_plugins = ["pytester"]

AXES = (1, 2, 3, 4)
NAMES = {1: "X", 2: "Y", 3: "Z", 4: "C"}


@pytest.fixture
def srv():
    with GeoTestServer() as s:
        yield s


def labels(selectors, dictionary):
    return [c.label for c in resolve_columns(selectors, dictionary, AXES, NAMES)]


# ---------------------------------------------------------------------- selection


def test_selection_by_name_axis_wildcard_and_address(srv):
    d = srv.dictionary
    assert labels(["TEMPC::coefficient"], d) == [f"TEMPC::coefficient@{a}" for a in AXES]
    assert labels(["tempc::coefficient@x"], d) == ["TEMPC::coefficient@1"]
    assert labels(["0x120300:0x30043"], d) == ["TEMPC::coefficient@3"]
    assert labels(["*::f_is_active@2"], d) == ["TEMPC::f_is_active@2", "CROSSC::f_is_active@2"]
    assert labels(["SIM::cycle_count", "TEMPC::coefficient@1", "TEMPC::coefficient"], d) == [
        "SIM::cycle_count",
        *(f"TEMPC::coefficient@{a}" for a in AXES),
    ]


@pytest.mark.parametrize(
    ("selector", "message"),
    [
        ("TEMPC::nonsense", "selector 'TEMPC::nonsense': "),
        ("TEMPC::coefficient@Q", "no axis 'Q' (axes: 1 X, 2 Y, 3 Z, 4 C)"),
        ("SIM::last_error", "SIM::last_error cannot be recorded"),
        ("SIM::reload", "SIM::reload cannot be recorded"),
        ("NOPE::*", "selector 'NOPE::*' names no recordable object"),
        ("0x120300:0x10099", "selector '0x120300:0x10099': "),
    ],
)
def test_selection_errors(srv, selector, message):
    with pytest.raises(SelectionError) as info:
        labels([selector], srv.dictionary)
    assert message in str(info.value)


def test_trigger_grammar(srv):
    d = srv.dictionary
    t = parse_trigger("TEMPC::offset_0@1 >= 100", d, AXES, NAMES)
    assert (t.column.label, t.op, t.value) == ("TEMPC::offset_0@1", ">=", 100.0)
    assert t.fires(None, 100.0) and not t.fires(None, 99.0)
    edge = parse_trigger("SIM::program_running rising", d, AXES, NAMES)
    assert not edge.fires(None, 1.0) and edge.fires(0.0, 1.0) and not edge.fires(1.0, 1.0)
    with pytest.raises(SelectionError, match="expected '<object>"):
        parse_trigger("TEMPC::offset_0@1 ~ 3", d, AXES, NAMES)
    with pytest.raises(SelectionError, match="names 4 values; name one axis"):
        parse_trigger("TEMPC::offset_0 > 3", d, AXES, NAMES)
    with pytest.raises(SelectionError, match="'abc' is not a number"):
        parse_trigger("TEMPC::offset_0@1 > abc", d, AXES, NAMES)


# ---------------------------------------------------------------------- recording


def test_recording_every_cycle_holds_what_a_read_returns(srv):
    rec = srv.record("TEMPC::offset_0@X", "SIM::cycle_count", "TEMPC::actual_offset@1")
    srv.step(9)
    access.write_name(srv.service, "TEMPC::offset_0", 1, 140)  # applied in cycle 10
    srv.step(31)
    trace = rec.stop()
    assert trace.labels == ["TEMPC::offset_0@1", "SIM::cycle_count", "TEMPC::actual_offset@1"]
    assert trace.types == ["SGN32", "UNS32", "SGN32"]
    assert trace.cycles.tolist() == list(range(1, 41))
    assert trace.rows()[8] == [9, 0.009, 40, 9, 17]
    assert trace.column("TEMPC::offset_0@1").tolist() == [40] * 9 + [140] * 31
    assert trace.column("SIM::cycle_count").tolist() == list(range(1, 41))
    # the write ramps over temp_comp_n_cycles = 20 (lists/achsmd1.lis): within 20 cycles
    # actual_offset is offset_0 + 4000e-6·(0 − 100) = 139.6 -> 140 increments (000 p.15)
    offset = trace.column("TEMPC::actual_offset@1")
    assert offset[29] == 140 and offset[9] < 140 and all(offset[29:] == 140)
    assert rec.inputs == [{"cycle": 9, "op": "write", "items": [["TEMPC::offset_0", 1, 140]]}]
    srv.step(5)
    assert len(rec.stop()) == 40  # stopped: nothing more


def test_every_n_cycles(srv):
    rec = srv.record("SIM::cycle_count", every=7)
    srv.step(30)
    assert rec.stop().cycles.tolist() == [1, 8, 15, 22, 29]


def test_trigger_with_pre_and_post_samples(srv):
    rec = srv.record("TEMPC::offset_0@1", trigger="TEMPC::offset_0@1 > 100", pre=3, post=5, every=1)
    srv.step(9)
    access.write_name(srv.service, "TEMPC::offset_0", 1, 140)  # cycle 10 fires the trigger
    srv.step(4)
    assert rec.triggered_at == 10 and not rec.done
    srv.step(10)
    assert rec.done
    trace = rec.stop()
    # 3 before the trigger, the trigger, 5 after
    assert trace.cycles.tolist() == [7, 8, 9, 10, 11, 12, 13, 14, 15]
    assert trace.column("TEMPC::offset_0@1").tolist() == [40, 40, 40] + [140] * 6
    assert trace.meta["triggered_at"] == "10"


def test_a_rising_edge_trigger_on_an_nc_program(srv):
    rec = srv.record(
        "SIM::program_running",
        "SIM::cycle_count",
        trigger="SIM::program_running rising",
        pre=2,
        post=2,
    )
    srv.step(5)
    srv.service.nc.run("G91 G01 X1 F6000")  # started in cycle 6
    srv.step(10)
    trace = rec.stop()
    assert trace.column("SIM::program_running").tolist() == [0, 0, 1, 1, 1]
    assert trace.cycles.tolist() == [4, 5, 6, 7, 8]


def test_stop_before_the_trigger_keeps_the_pre_samples(srv):
    rec = srv.record("SIM::cycle_count", trigger="SIM::cycle_count > 1000", pre=4)
    srv.step(20)
    trace = rec.stop()
    assert rec.triggered_at is None and trace.cycles.tolist() == [17, 18, 19, 20]


@pytest.mark.realtime
def test_recording_in_a_real_time_machine_has_no_gaps():
    m = Machine(load_machine(default_startup_list()), homed=True)
    sched = Scheduler(m, mode="realtime", engine="exact")
    service = ObjectService(m, sched)
    rec = Recorder(service, RecordSpec(["SIM::cycle_count", "SIM::command_position@1"])).start()
    sched.start()
    try:
        service.nc.run("G91 G01 X2 F6000")
        start = m.cycle  # 150 cycles recorded, however slowly the host runs them
        deadline = time.monotonic() + 30
        while m.cycle < start + 150 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        trace = rec.stop()
        sched.stop()
    cycles = trace.cycles
    assert len(cycles) > 100
    assert np.all(np.diff(cycles) == 1)  # every cycle, none twice
    assert np.array_equal(trace.column("SIM::cycle_count"), cycles)


# ---------------------------------------------------------------------- files


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_trace_files_round_trip(srv, tmp_path, suffix):
    rec = srv.record("TEMPC::*@1", "SIM::command_position@1", "TWIN::sensor_temperature@1")
    srv.nc("G91 G01 X1 F6000")
    trace = rec.stop()
    back = load_trace(trace.save(tmp_path / f"t{suffix}"))
    assert back.labels == trace.labels and back.types == trace.types
    assert back.units == trace.units and back.meta["selectors"] == trace.meta["selectors"]
    assert back.rows() == trace.rows()
    assert compare(trace, back).ok


def test_csv_format(tmp_path):
    t = Trace(
        ["A@1", "B"],
        np.array([[1, 0.001, 1.5, 1.0], [2, 0.002, -2.0, 0.0]]),
        ["REAL64", "BOOLEAN"],
        ["[mm]", "[-]"],
        {"machine": "m"},
    )
    text = t.to_csv()
    assert text == (
        "# geo-server trace 1\n# machine: m\n"
        '# types: ["REAL64", "BOOLEAN"]\n# units: ["[mm]", "[-]"]\n'
        "cycle,time_s,A@1,B\n1,0.001,1.5,1\n2,0.002,-2.0,0\n"
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("cycle,time_s\n", "t.csv:1: not a geo-server trace"),
        ("# geo-server trace 1\n# machine m\n", "t.csv:2: metadata line without 'key: value'"),
        ("# geo-server trace 1\nc,t,A\n", "t.csv:2: the header must start with cycle,time_s"),
        ("# geo-server trace 1\ncycle,time_s,A\n1,0.001,2\n2,0.002\n", "t.csv:4: 2 cells"),
        ("# geo-server trace 1\ncycle,time_s,A\n1,0.001,x\n", "t.csv:3: 'x' is not a number"),
    ],
)
def test_malformed_trace_files_name_file_and_line(tmp_path, text, message):
    (tmp_path / "t.csv").write_text(text, encoding="utf-8")
    with pytest.raises(TraceFileError) as info:
        load_trace(tmp_path / "t.csv")
    assert str(info.value).endswith(message) or message in str(info.value)


def test_malformed_inputs_name_file_and_line(tmp_path):
    f = tmp_path / "i.jsonl"
    f.write_text('{"cycle": 5, "op": "reset"}\n{"cycle": 3, "op": "reset"}\n', encoding="utf-8")
    with pytest.raises(TraceFileError, match=r"i.jsonl:2: needs a 'cycle' at or after"):
        load_inputs(f)
    f.write_text("{nope\n", encoding="utf-8")
    with pytest.raises(TraceFileError, match=r"i.jsonl:1: not JSON"):
        load_inputs(f)


# ---------------------------------------------------------------------- replay, compare

SELECTION = ["TEMPC::*", "SIM::command_position", "TWIN::sensor_temperature", "BC::*@1"]


def _scenario(s: GeoTestServer) -> Recorder:
    """Writes at chosen cycles, a program, a temperature change, a reset."""
    rec = s.record(*SELECTION)
    s.step(25)
    s.write("TEMPC::coefficient", 1, 4300.0)
    s.service.nc.run("G91 G01 X5 Y-3 F3000\nG01 X-2 F6000")
    s.step(400)
    s.write("TWIN::ambient_temperature", 0, 31.5)
    s.step(200)
    s.service.nc.reset()
    s.step(100)
    return rec


def test_replay_reproduces_a_stepped_recording_exactly(tmp_path):
    with GeoTestServer(time_scale=100) as s:
        rec = _scenario(s)
        golden = rec.stop()
        inputs = rec.inputs
    assert [line["op"] for line in inputs] == ["write", "nc", "write", "reset"]
    assert [line["cycle"] for line in inputs] == [25, 26, 426, 627]
    again = replay(
        default_startup_list(),
        inputs,
        RecordSpec(SELECTION),
        int(golden.cycles[-1]),
        time_scale=100,
    )
    result = compare(golden, again)
    assert result.ok, result.report()
    assert result.compared_rows == len(golden) == 727
    assert again.rows() == golden.rows()


def _tiny(values_a, values_b=None):
    cycles = np.arange(1, len(values_a) + 1)
    data = np.column_stack([cycles, cycles / 1000, values_a] + ([values_b] if values_b else []))
    return Trace(["TEMPC::coefficient@1", "SIM::feed@1"][: data.shape[1] - 2], data)


def test_compare_report_is_readable():
    golden = _tiny([4000.0, 4000.0, 4100.0, 4200.0], [100, 100, 100, 100])
    new = _tiny([4000.0, 4000.3, 4100.9, 4207.0], [100, 100, 100, 100])
    ok = compare(golden, new, ["TEMPC::*=1"])
    assert not ok.ok
    assert ok.report() == (
        "traces differ: 1 of 2 columns out of tolerance, 4 rows compared\n"
        "column | tolerance | max |Δ| | first failing cycle: golden → new | failing\n"
        "TEMPC::coefficient@1 | 1 | 7 | 4: 4200 → 4207 | 1"
    )
    assert compare(golden, new, ["TEMPC::*=7"]).report() == "traces match: 2 columns, 4 rows"
    assert compare(golden, new, parse_tolerances(["*=0.2%"])).ok  # 0.2 % of 4200 = 8.4
    short = _tiny([4000.0, 4000.0])
    result = compare(golden, short)
    assert not result.ok and result.missing_cycles == [3, 4]
    assert "missing columns (in the golden trace only): SIM::feed@1" in result.report()
    with pytest.raises(ValueError, match="expected PATTERN=VALUE"):
        parse_tolerances(["0.5"])


def test_check_golden_writes_once_then_compares(tmp_path):
    golden = _tiny([1.0, 2.0, 3.0])
    path = tmp_path / "golden" / "g.csv"
    with pytest.raises(AssertionError, match="no golden trace yet; written now"):
        check_golden(golden, path)
    assert check_golden(golden, path).ok
    with pytest.raises(AssertionError, match=r"TEMPC::coefficient@1 \| 0 \| 0.5 \| 2: 2 → 2.5"):
        check_golden(_tiny([1.0, 2.5, 3.0]), path)
    assert check_golden(_tiny([1.0, 2.5, 3.0]), path, ["*=0.5"]).ok
    assert check_golden(_tiny([9.0, 9.0, 9.0]), path, update=True) is None
    assert load_trace(path).column("TEMPC::coefficient@1").tolist() == [9.0, 9.0, 9.0]


# ---------------------------------------------------------------------- Zenoh, CLI, plugin


def test_zenoh_record_command(tmp_path):
    with GeoTestServer(record_dir=tmp_path) as srv:
        _zenoh_record_command(srv, tmp_path)


def _zenoh_record_command(srv, tmp_path):
    srv.start("zenoh")
    z = srv.client("zenoh")
    key = f"cnc/{srv.machine_name}/cmd/record"

    def command(body: dict) -> dict:
        import json

        return json.loads(z.get(key, json.dumps(body).encode())[0][1])

    out = tmp_path / "z.csv"
    # a file name in the recordings folder (docs/recorder.md §7)
    started = command({"start": {"objects": ["SIM::cycle_count"], "every": 2, "out": out.name}})
    assert started["recording"]["columns"] == 1 and started["recording"]["file"] == str(out)
    with pytest.raises(AdsError) as info:
        command({"start": {"objects": ["SIM::cycle_count"]}})
    assert info.value.code == 0x708
    srv.step(10)
    assert z.status()["recording"]["rows"] == 5
    stopped = command({"stop": True})["recording"]
    assert stopped["rows"] == 5 and Path(stopped["inputs_file"]).name == "z.inputs.jsonl"
    assert load_trace(out).cycles.tolist() == [1, 3, 5, 7, 9]
    for bad, message in [
        ({"start": {"objects": ["NOPE::x"]}}, "selector 'NOPE::x'"),
        ({"start": {"objects": ["SIM::cycle_count"], "evry": 2}}, "record: unknown evry"),
        ({"stop": True}, "no recording runs"),
    ]:
        with pytest.raises(AdsError) as info:
            command(bad)
        assert message in info.value.message


@pytest.mark.realtime
def test_cli_record_replay_compare(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    nc = tmp_path / "p.nc"
    nc.write_text("G91 G01 X3 F6000\nM30\n", encoding="utf-8")
    args = [
        "run",
        "--homed",
        "--mode",
        "free",
        "--cycles",
        "600",
        "--no-zenoh",
        "--no-ads",
        "--no-opcua",
        "--modbus-port",
        "0",
        "--program",
        str(nc),
        "--status-period",
        "0.05",
        "--record",
        "SIM::command_position@1",
        "--record",
        "TEMPC::*@1",
        "--record-out",
        "golden.csv",
    ]
    assert server_main(args) == 0
    out = capsys.readouterr().out
    assert "recording written: golden.csv (600 rows), inputs golden.inputs.jsonl (1 lines)" in out
    assert [line["op"] for line in load_inputs("golden.inputs.jsonl")] == ["nc"]
    replay_args = [
        "replay",
        "golden.inputs.jsonl",
        "--cycles",
        "600",
        "--out",
        "new.csv",
        "--record",
        "SIM::command_position@1",
        "--record",
        "TEMPC::*@1",
    ]
    assert server_main(replay_args) == 0
    assert capsys.readouterr().out == "replayed 600 cycles: new.csv (600 rows)\n"
    assert server_main(["compare", "golden.csv", "new.csv"]) == 0
    assert capsys.readouterr().out == "traces match: 7 columns, 600 rows\n"
    # a regression: the program ends 1 mm short
    nc.write_text("G91 G01 X2 F6000\nM30\n", encoding="utf-8")
    assert server_main([*args[:-1], "short.csv"]) == 0
    capsys.readouterr()
    assert server_main(["compare", "golden.csv", "short.csv", "--tol", "TEMPC::*=50"]) == 1
    report = capsys.readouterr().out
    assert report.startswith("traces differ: 1 of 7 columns out of tolerance")
    # 3 mm and 2 mm at 100 mm/s part ways while accelerating, 1 mm (10000 incr.) apart
    assert "\nSIM::command_position@1 | 0 | 10000 | 33: 10240 → 10237 | 568\n" in report
    assert server_main(["compare", "golden.csv", "missing.csv"]) == 2


@pytest.mark.slow
def test_the_pytest_plugin_golden_fixture(pytester):
    pytester.makepyfile(
        # the example of docs/recorder.md, as written there
        """
        def test_warm_ramp(geo_server, geo_golden):
            rec = geo_server.record("TEMPC::actual_offset@X", "TEMPC::offset_0@X")
            geo_server.step(5)
            geo_server.write("TEMPC::offset_0", "X", 140)
            geo_server.step(40)
            geo_golden(rec.stop(), "golden/ramp.csv", ["TEMPC::actual_offset*=1"])
        """
    )
    first = pytester.runpytest_subprocess("-p", "geo_clients.pytest_plugin", "-q")
    first.assert_outcomes(failed=1)
    first.stdout.fnmatch_lines(["*no golden trace yet; written now*"])
    pytester.runpytest_subprocess("-p", "geo_clients.pytest_plugin", "-q").assert_outcomes(passed=1)
    golden = pytester.path / "golden" / "ramp.csv"
    text = golden.read_text(encoding="utf-8").replace(",140,140\n", ",140,141\n", 1)
    golden.write_text(text, encoding="utf-8")
    failed = pytester.runpytest_subprocess("-p", "geo_clients.pytest_plugin", "-q")
    failed.assert_outcomes(failed=1)
    failed.stdout.fnmatch_lines(["*TEMPC::offset_0@1 | 0 | 1 | 25: 141 → 140 | 1"])
    pytester.runpytest_subprocess(
        "-p", "geo_clients.pytest_plugin", "-q", "--geo-update-golden"
    ).assert_outcomes(passed=1)


def test_recorder_cost_stays_off_the_loop(srv):
    """Per sample the recorder copies from the snapshot's arrays: the values it holds
    are those of the snapshot (checked against a read of each) — its speed is in
    bench/recorder.py, not asserted here."""
    rec = srv.record("TEMPC::*@1", "BC::*@1", "CROSSC::*@1", "SIM::command_position@1")
    srv.nc("G91 G01 X1 F6000")
    trace = rec.stop()
    snap = srv.snapshot
    last = len(trace) - 1
    for c in rec.columns:
        assert trace.value(c.label, last) == snap.value(c.obj, c.axis)


def test_a_bare_service_needs_no_loop_or_transport():
    m = Machine(load_machine(default_startup_list()), homed=True)
    service = ObjectService(m)
    rec = Recorder(service, RecordSpec(["SIM::cycle_count"])).start()
    access.step(service, 3)
    assert rec.stop().cycles.tolist() == [1, 2, 3]


@pytest.mark.slow
def test_run_writes_a_triggered_recording_when_it_completes_not_at_ctrl_c(
    tmp_path: Path, lists_copy: Path
) -> None:
    """docs/recorder.md: `run --record … --record-trigger … --record-post N` writes the
    file when the trigger's samples are in. Trigger at cycle 51, 100 cycles after it:
    complete by cycle 151 (0.15 s of 1 ms cycles); the file is written while `run`
    still serves (before, `run` looked for a `service.recording` that had moved to
    `service.recordings.recording`, and wrote nothing until Ctrl-C)."""
    out = tmp_path / "trace.csv"
    args = ["run", str(lists_copy), "--homed", "--no-zenoh", "--no-ads", "--no-modbus"]
    args += ["--no-opcua", "--status-period", "60", "--record", "SIM::cycle_count"]
    args += ["--record-trigger", "SIM::cycle_count > 50", "--record-pre", "0"]
    args += ["--record-post", "100", "--record-out", str(out)]
    with geo_server_running(args, tmp_path, "recording written") as proc:
        assert proc.poll() is None  # still serving
        rows = [r for r in out.read_text(encoding="utf-8").splitlines() if r[:1] != "#"]
        # the trigger's cycle (the first with a count above 50) and the 100 after it
        assert [rows[1].split(",")[0], rows[-1].split(",")[0], len(rows)] == ["51", "151", 102]
