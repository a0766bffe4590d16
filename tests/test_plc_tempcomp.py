"""PLC temperature adaptation (clients/geo_clients/plc_tempcomp.py; manual 000 §3.2, p.14–24).

Pure derivation checked by hand, then end to end: the adaptation client against a
stepped server over Zenoh, Modbus and ADS. The warm-up curve is evaluated at chosen
simulated times (`adapter.tick(t)`), the server is stepped between ticks, and the
TEMPC objects must equal the values computed by hand from the shipped reference table
and the manual's formula Δs = offset_0 + coefficient·1e-6·(s − position_0) (000 p.15).
"""

from __future__ import annotations

import json
import math
import time

import pytest
from geo_clients.plc_tempcomp import (
    EXAMPLE_REFERENCE,
    ConstantTemperature,
    CsvTemperature,
    ErrorLine,
    Parameters,
    ReferenceTableError,
    TemperatureAdapter,
    TwinSensors,
    WarmUp,
    ZenohTemperature,
    compensation,
    derive_parameters,
    fit_line,
    interpolate_line,
    load_reference,
    main,
    parse_reference,
    parse_temperature,
    virtual_intersection,
    warmup_temperature,
)
from geo_clients.testing import GeoTestServer

from geo_server.dictionary import round_half_away
from geo_server.errors import AdsError

pytest_plugins = ["geo_clients.pytest_plugin"]

TAU = 600.0
#: warm-up 20 → 50 °C: T(t) = 50 − 30·exp(−t/τ); these times give round temperatures
T25 = TAU * math.log(30 / 25)  # 25 °C
T30 = TAU * math.log(30 / 20)  # 30 °C
T45 = TAU * math.log(30 / 5)  # 45 °C: beyond the last measured temperature (40 °C)


# ============================================================================ pure math


def test_fit_line_by_hand():
    # d = 3 + 2·s through (0, 3), (1, 5), (2, 7); noise +-1 around it keeps the LS line
    assert fit_line([(0, 3), (1, 5), (2, 7)]) == (3.0, 2.0)
    a, b = fit_line([(0, 4), (1, 4), (2, 8), (3, 8)])  # mean x 1.5, mean y 6
    # sxy = (-1.5)(-2) + (-0.5)(-2) + 0.5·2 + 1.5·2 = 8, sxx = 5 → b = 1.6, a = 6 − 2.4
    assert b == pytest.approx(1.6) and a == pytest.approx(3.6)
    with pytest.raises(ValueError, match="two distinct"):
        fit_line([(1, 2), (1, 3)])


def test_line_from_parameters_is_the_manual_formula():
    # 000 p.17 example: position_0 100, offset_0 40, coefficient 4000 µm/m
    ln = ErrorLine.from_parameters(20.0, 100, 40, 4000)
    assert ln.at(100) == pytest.approx(40)
    assert ln.at(1_000_000) == pytest.approx(40 + 4000e-6 * 999_900)  # 4039.6
    assert ln.coefficient == pytest.approx(4000)
    p = Parameters(20.0, 100, 40, 4000.0)
    assert compensation(p, 1_000_000) == pytest.approx(4039.6)


def test_virtual_intersection():
    lines = [ErrorLine.from_parameters(t, 100, 40, c) for t, c in ((20, 4000), (30, 4600))]
    s, d = virtual_intersection(lines)
    assert s == pytest.approx(100) and d == pytest.approx(40)
    # parallel lines: none; three lines missing a common point: none
    assert virtual_intersection([ErrorLine(20, 0, 1e-5), ErrorLine(30, 10, 1e-5)]) is None
    y = [ErrorLine.from_parameters(t, 0, o, c) for t, o, c in ((20, 0, 23), (30, 50, 35))]
    y.append(ErrorLine.from_parameters(40, 0, 120, 40))
    assert virtual_intersection(y) is None
    assert virtual_intersection(y[:1]) is None


def test_interpolation_and_extrapolation_by_hand():
    lines = [ErrorLine(20, 0.0, 10e-6), ErrorLine(30, 50.0, 20e-6), ErrorLine(40, 60.0, 40e-6)]
    mid = interpolate_line(lines, 25)  # halfway between 20 and 30
    assert (mid.intercept, mid.coefficient) == pytest.approx((25.0, 15.0))
    hi = interpolate_line(lines, 50)  # beyond 40 with the 30–40 pair: +1 step
    assert (hi.intercept, hi.coefficient) == pytest.approx((70.0, 60.0))
    lo = interpolate_line(lines, 10)  # below 20 with the 20–30 pair: −1 step
    assert (lo.intercept, lo.coefficient) == pytest.approx((-50.0, 0.0))
    assert interpolate_line(lines[:1], 99).coefficient == pytest.approx(10.0)


def test_derive_parameters_rounds_like_the_objects():
    lines = [ErrorLine.from_parameters(20, 0, 0, 23), ErrorLine.from_parameters(30, 0, 50, 35)]
    p = derive_parameters(lines, 21.0, 0.4)  # P rounds to 0
    assert p == Parameters(21.0, 0, 5, 24.2)
    # offset_0 is evaluated at the rounded position_0, rounded half away from zero
    p = derive_parameters(lines, 20.0, -250_000.4)
    assert p.position_0 == -250_000
    assert p.offset_0 == -6  # 23e-6·(−250 000) = −5.75 → −6


def test_warmup_curve():
    assert warmup_temperature(0, 20, 50, TAU) == 20
    assert warmup_temperature(T25, 20, 50, TAU) == pytest.approx(25)
    assert warmup_temperature(T45, 20, 50, TAU) == pytest.approx(45)
    assert warmup_temperature(1e9, 20, 50, TAU) == pytest.approx(50)
    assert WarmUp(20, 50, TAU).temperature(T30) == pytest.approx(30)


# ============================================================================ file format


def test_example_reference_table():
    table = load_reference(EXAMPLE_REFERENCE)
    assert sorted(table.axes) == [1, 2, 3]
    assert table.form == "lines+points"
    x = table.axes[1]
    assert [ln.temperature for ln in x.lines] == [20, 30, 40]
    assert [ln.coefficient for ln in x.lines] == pytest.approx([4000, 4600, 5000])
    p, how = x.reference_position()
    assert how == "virtual intersection" and p == pytest.approx(100)
    p, how = table.axes[2].reference_position()
    assert (p, how) == (0.0, "position_0 of the table")
    assert table.axes[2].reference_position(1234)[0] == 1234.0


def test_reference_file_units_and_errors(tmp_path):
    t = parse_reference("axis,temperature_C,position_mm,deviation_um\n1,20,0,1\n1,20,1,2\n")
    (line,) = t.lines(1)
    # 0 mm → 10 incr, 1 mm = 10000 incr → 20 incr: slope 1e-3 = 1000 µm/m
    assert line.intercept == pytest.approx(10) and line.coefficient == pytest.approx(1000)
    bad = [
        ("1,20,0,0\n", "header"),
        ("axis,temperature_C,position\n1,20,0\n", "deviation"),
        ("axis,temperature_C,position,deviation\n1,20,0\n", "3 values"),
        ("axis,temperature_C,position,deviation\n1,20,x,1\n", "not a number"),
        ("axis,temperature_C,position,deviation\n1,20,5,1\n1,20,5,2\n", "distinct"),
        ("axis,temperature_C,position_0,offset_0,coefficient\n1,20,0,0,1\n1,20,0,0,2\n", "twice"),
        ("# nothing\n", "no measurements"),
    ]
    for text, msg in bad:
        with pytest.raises(ReferenceTableError, match=msg):
            parse_reference(text, "ref.csv")
    with pytest.raises(ReferenceTableError, match=r"missing\.csv"):
        load_reference(tmp_path / "missing.csv")


def test_csv_temperature_source(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("time,temperature_C\n0,20\n10,22\n20,26\n")
    src = CsvTemperature(f)
    assert [src.temperature(t) for t in (-5, 0, 5, 15, 20, 99)] == [20, 20, 21, 24, 26, 26]
    f.write_text("2024-05-01T08:00:00,20.0\n2024-05-01T08:01:00,23.0\n")
    assert CsvTemperature(f).temperature(30) == pytest.approx(21.5)
    # time zero is the earliest timestamp, not the first row
    f.write_text("time,temperature_C\n2024-05-01T08:01:00,23.0\n2024-05-01T08:00:00,20.0\n")
    assert CsvTemperature(f).samples == [(0.0, 20.0), (60.0, 23.0)]
    f.write_text("time,temperature_C\nyesterday,20\n")
    with pytest.raises(ValueError, match=r"t\.csv:2: time must be seconds or ISO-8601"):
        CsvTemperature(f)


def test_parse_temperature():
    assert parse_temperature(b"23.5") == 23.5
    assert parse_temperature(b'{"value": 21}') == 21.0
    assert parse_temperature(b'{"temperature_C": 22.25}') == 22.25
    for bad in (b"hot", b"true", b'"20"', b"[1]"):
        with pytest.raises(ValueError):
            parse_temperature(bad)


# ============================================================================ adapter logic


class FakeClient:
    """Records writes; can fail a number of times first."""

    def __init__(self, failures: list[BaseException] | None = None) -> None:
        self.failures = list(failures or [])
        self.writes: list[tuple[str, int, object]] = []

    def write(self, name: str, axis: int, value: object) -> object:
        if self.failures:
            raise self.failures.pop(0)
        self.writes.append((name, axis, value))
        return value


def test_adapter_writes_only_changes_and_retries_transient_failures():
    table = load_reference(EXAMPLE_REFERENCE)
    sleeps: list[float] = []
    client = FakeClient([TimeoutError("no reply"), ConnectionError("reset")])
    ad = TemperatureAdapter(
        client, table, WarmUp(20, 50, TAU), axes=[1], sleep=sleeps.append, retry_delay=0.5
    )
    r = ad.tick(0.0)
    assert client.writes == [
        ("TEMPC::position_0", 1, 100),
        ("TEMPC::offset_0", 1, 40),
        ("TEMPC::coefficient", 1, 4000.0),
    ]
    assert r.writes[0].attempts == 3 and r.writes[0].ok
    assert sleeps == [0.5, 1.0]  # linear back-off
    client.writes.clear()
    r = ad.tick(T25)  # only the coefficient changes: offset_0 stays 40 (000 p.17)
    assert client.writes == [("TEMPC::coefficient", 1, 4300.0)]
    assert r.parameters[1] == Parameters(pytest.approx(25), 100, 40, 4300.0)


def test_adapter_does_not_retry_permanent_errors():
    table = load_reference(EXAMPLE_REFERENCE)
    client = FakeClient([AdsError(0x704, "read-only")])
    ad = TemperatureAdapter(client, table, ConstantTemperature(20), axes=[1], sleep=lambda s: None)
    r = ad.tick(0)
    assert not r.writes[0].ok and r.writes[0].attempts == 1 and "read-only" in r.writes[0].error
    # no half-updated set: offset_0 and coefficient belong to the position_0 that failed
    assert [(w.name, w.ok) for w in r.writes] == [("TEMPC::position_0", False)]
    assert client.writes == [] and "TEMPC::position_0 := 100 failed" in r.refused[1]
    r = ad.tick(1)  # the next period writes the whole set
    assert client.writes == [
        ("TEMPC::position_0", 1, 100),
        ("TEMPC::offset_0", 1, 40),
        ("TEMPC::coefficient", 1, 4000.0),
    ]
    assert r.refused == {}


def test_adapter_run_ticks_on_the_wall_clock():
    """`run(period, duration, speed)`: a tick every period, source time = elapsed · speed."""
    table = load_reference(EXAMPLE_REFERENCE)
    seen: list[float] = []

    class Recording:
        def temperature(self, t: float) -> float:
            seen.append(t)
            return 20.0

    client = FakeClient()
    ad = TemperatureAdapter(client, table, Recording(), axes=[1])
    n = ad.run(period=0.05, duration=0.32, speed=100.0)
    assert 5 <= n <= 8 and len(seen) == n  # ticks at ~0, 0.05, … 0.30 s of wall time
    assert seen[0] < 1.0 and seen == sorted(seen)
    # tick k is never early: at ≥ k·0.05 s of wall time, i.e. source time ≥ k·5 s
    # (a late tick is followed by catch-up ticks, so the gaps themselves may be short)
    assert all(t >= k * 5.0 - 0.01 for k, t in enumerate(seen))
    # constant 20 °C: the set is written once, never again
    assert client.writes == [
        ("TEMPC::position_0", 1, 100),
        ("TEMPC::offset_0", 1, 40),
        ("TEMPC::coefficient", 1, 4000.0),
    ]


def test_adapter_refuses_values_out_of_range(caplog):
    table = load_reference(EXAMPLE_REFERENCE)
    client = FakeClient()
    ad = TemperatureAdapter(
        client, table, ConstantTemperature(200.0), axes=[1, 2], plausible=(-40.0, 250.0)
    )
    with caplog.at_level("ERROR", logger="geo_clients.plc_tempcomp"):
        r = ad.tick(0)
    # X at 200 °C: 5000 + (200 − 40)·40 = 11400 µm/m > 10000 (000 p.21): nothing for X
    assert r.parameters[1].coefficient == 11400.0
    assert 1 in r.refused and "TEMPC::coefficient: 11400.0 outside the range" in r.refused[1]
    assert "200.000 °C" in r.refused[1]
    assert all(axis == 2 for _name, axis, _v in client.writes)  # Y is still written
    assert "refused, not written" in caplog.text


def test_adapter_without_temperature_writes_nothing():
    table = load_reference(EXAMPLE_REFERENCE)

    class Silent:
        def temperature(self, t: float) -> None:
            return None

    client = FakeClient()
    r = TemperatureAdapter(client, table, Silent()).tick(1.0)
    assert r.temperature is None and not client.writes


def test_adapter_needs_every_axis_in_the_table():
    with pytest.raises(ReferenceTableError, match="axis \\[4\\]"):
        TemperatureAdapter(FakeClient(), load_reference(EXAMPLE_REFERENCE), WarmUp(), axes=[4])


# ============================================================================ end to end


def hand_values(temperature: float) -> dict[int, tuple[int, int, float, int]]:
    """(position_0, offset_0, coefficient, actual_offset) of X at 100 mm and Y at 200 mm,
    computed by hand from the example table (clients/geo_clients/data/reference_measurement.csv)."""
    # X: offset 40 at the virtual intersection 100; coefficient 4000/4600/5000 at 20/30/40
    # Y: position_0 0; offset 0/50/120, coefficient 23/35/40 at 20/30/40 °C
    table = {
        20: ((100, 40, 4000.0, 4040), (0, 0, 23.0, 46)),  # 40+4000e-6·999900 = 4039.6
        25: ((100, 40, 4300.0, 4340), (0, 25, 29.0, 83)),  # 40+4299.57; 25+58
        30: ((100, 40, 4600.0, 4640), (0, 50, 35.0, 120)),  # 40+4599.54; 50+70
        45: ((100, 40, 5200.0, 5239), (0, 155, 42.5, 240)),  # 40+5199.48; 155+85
    }
    x, y = table[round(temperature)]
    return {1: x, 2: y}


@pytest.mark.parametrize("via", ["zenoh", "modbus", "ads"])
def test_warm_up_end_to_end(geo_server: GeoTestServer, via: str):
    if via == "ads":
        pytest.importorskip("pyads")
    srv = geo_server
    srv.set_position("X", 1_000_000)  # 100 mm
    srv.set_position("Y", 2_000_000)  # 200 mm
    client = srv.start(via).client(via)
    table = load_reference(EXAMPLE_REFERENCE)
    ad = TemperatureAdapter(client, table, WarmUp(20, 50, TAU), axes=[1, 2])
    assert ad.transport == via
    g = srv.via(via)
    for t in (0.0, T25, T30, T45):
        r = ad.tick(t)
        assert all(w.ok and w.transport == via and w.rtt_s > 0 for w in r.writes), r.writes
        srv.step(25)  # the writes are step events ramped over temp_comp_n_cycles (20, 10)
        for axis, (p0, off, coef, actual) in hand_values(r.temperature).items():
            g.assert_values(
                axis,
                {
                    "TEMPC::position_0": p0,
                    "TEMPC::offset_0": off,
                    "TEMPC::coefficient": coef,
                    "TEMPC::actual_offset": actual,
                },
            )
            # and the manual's formula with the values read back
            assert actual == round_half_away(compensation(r.parameters[axis], 1_000_000 * axis))
    written = [(w.axis, w.name, w.value) for w in ad.history]
    # X: position_0 and offset_0 once (virtual intersection), then the coefficient only
    assert [w for w in written if w[0] == 1] == [
        (1, "TEMPC::position_0", 100),
        (1, "TEMPC::offset_0", 40),
        (1, "TEMPC::coefficient", 4000.0),
        (1, "TEMPC::coefficient", 4300.0),
        (1, "TEMPC::coefficient", 4600.0),
        (1, "TEMPC::coefficient", 5200.0),
    ]
    # by address too: TEMPC::coefficient of axis 2 at 0x120300 / 0x20043
    g.assert_raw(0x120300, 0x20043, 42.5)


def test_the_ramp_follows_a_write(geo_server: GeoTestServer):
    """Between ticks the server ramps with sin² over temp_comp_n_cycles (docs/design.md §3)."""
    srv = geo_server
    srv.set_position("X", 1_000_000)
    ad = TemperatureAdapter(
        srv.client("service"), load_reference(EXAMPLE_REFERENCE), WarmUp(20, 50, TAU), axes=[1]
    )
    ad.tick(0)
    srv.step(25)
    ad.tick(T30)
    srv.step(10)  # halfway through the 20-cycle ramp: strictly between old and new
    mid = srv.read("TEMPC::actual_offset", 1)
    assert 4040 < mid < 4640
    srv.step(10)
    assert srv.read("TEMPC::actual_offset", 1) == 4640


def test_zenoh_temperature_source(geo_server: GeoTestServer):
    client = geo_server.start("zenoh").client("zenoh")
    src = ZenohTemperature(client.session, "lab/x/temperature")
    try:
        assert src.temperature(0) is None
        client.session.put("lab/x/temperature", b'{"temperature_C": 30}')
        deadline = time.monotonic() + 5
        while src.temperature(0) is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert src.temperature(0) == 30.0
        geo_server.set_position("X", 1_000_000)
        ad = TemperatureAdapter(client, load_reference(EXAMPLE_REFERENCE), src, axes=[1])
        ad.tick(123.0)
        geo_server.step(25)
        assert geo_server.read("TEMPC::coefficient", 1) == 4600.0
        assert geo_server.read("TEMPC::actual_offset", 1) == 4640
    finally:
        src.close()


# ============================================================================ command line


def test_cli_derive(capsys):
    assert main([str(EXAMPLE_REFERENCE), "--derive", "25", "45", "--axis", "1"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [
        "temperature_C,axis,position_0,offset_0,coefficient,ok",
        "25.0,1,100,40,4300.0,ok",
        "45.0,1,100,40,5200.0,ok",
    ]


@pytest.mark.parametrize("via", ["zenoh", "modbus"])
def test_cli_once_writes_and_logs(geo_server: GeoTestServer, via: str, tmp_path, capsys):
    log_file = tmp_path / "writes.jsonl"
    opts = geo_server.client_options(via)
    argv = [
        str(EXAMPLE_REFERENCE),
        "--constant",
        "30",
        "--once",
        "--axis",
        "2",
        "--via",
        via,
        "--connect",
        opts["endpoint"],
        "--machine",
        opts["machine"],
        "--log-file",
        str(log_file),
    ]
    assert main(argv) == 0
    geo_server.step(15)
    assert geo_server.read("TEMPC::offset_0", 2) == 50
    assert geo_server.read("TEMPC::coefficient", 2) == 35.0
    records = [json.loads(line) for line in log_file.read_text().splitlines()]
    assert [(r["name"], r["value"], r["transport"], r["ok"]) for r in records] == [
        ("TEMPC::position_0", 0, via, True),
        ("TEMPC::offset_0", 50, via, True),
        ("TEMPC::coefficient", 35.0, via, True),
    ]
    assert all(r["rtt_s"] > 0 for r in records)


def test_cli_warmup_on_the_wall_clock_over_ads(geo_server: GeoTestServer, tmp_path):
    """`--warmup 20:35:600 --speed 600 --period 0.1 --duration 0.45` over ADS: the first
    period writes the 20 °C set of X (000 p.17: through (100, 40) at 4000 µm/m), later
    periods only the rising coefficient; the server ends with the last value logged."""
    log_file = tmp_path / "writes.jsonl"
    opts = geo_server.client_options("ads")
    argv = [
        *("--warmup", "20:35:600", "--speed", "600", "--period", "0.1", "--duration", "0.45"),
        *("--axis", "1", "--via", "ads", "--connect", opts["endpoint"]),
        *("--netid", opts["netid"], "--log-file", str(log_file)),
    ]
    assert main(argv) == 0
    records = [json.loads(line) for line in log_file.read_text().splitlines()]
    assert all(r["ok"] and r["transport"] == "ads" and r["axis"] == 1 for r in records)
    assert [(r["name"], r["value"]) for r in records[:2]] == [
        ("TEMPC::position_0", 100),
        ("TEMPC::offset_0", 40),
    ]
    # the first tick is microseconds after the start: T a hair above 20 °C
    assert records[2]["name"] == "TEMPC::coefficient"
    assert 4000.0 <= records[2]["value"] < 4001.0
    later = records[3:]
    assert len(later) >= 2 and {r["name"] for r in later} == {"TEMPC::coefficient"}
    # T(t) = 35 − 15·exp(−t/600) rises, and with it the coefficient (4000 + 60/K, table)
    coefficients = [r["value"] for r in later]
    assert coefficients == sorted(coefficients) and coefficients[0] > 4000.0
    # source time ≤ 0.45 s · 600 = 270 s: T ≤ 35 − 15·e^(−0.45) = 25.4 °C → ≤ 4324 µm/m
    assert coefficients[-1] < 4325.0
    geo_server.step(25)
    assert geo_server.read("TEMPC::coefficient", 1) == coefficients[-1]


def test_cli_bad_reference(tmp_path, capsys):
    f = tmp_path / "bad.csv"
    f.write_text("axis,temperature_C,position,deviation\n1,20,1,x\n")
    assert main([str(f), "--derive", "20"]) == 2
    assert "bad.csv:2: not a number" in capsys.readouterr().err


class _FailingSensors:
    """A client whose reads fail: the first `transient` times with ADS 0x707 (not
    ready), then for good if `forever`."""

    def __init__(self, transient: int, forever: bool = False) -> None:
        self.transient, self.forever, self.reads = transient, forever, 0
        self.writes: list[tuple[str, int, object]] = []

    def read(self, name: str, axis: int = 0) -> float:
        self.reads += 1
        if self.forever or self.reads <= self.transient:
            raise AdsError(0x707, "GEO cycle stalled")
        return 20.0 + axis  # axis 1: 21 °C, axis 3: 23 °C

    def write(self, name: str, axis: int, value: object) -> object:
        self.writes.append((name, axis, value))
        return value


def test_twin_sensors_failing_reads_are_retried_then_skip_the_period():
    table = load_reference(EXAMPLE_REFERENCE)
    client = _FailingSensors(transient=2)
    adapter = TemperatureAdapter(
        client, table, TwinSensors(client, []), axes=[1, 3], sleep=lambda s: None
    )
    result = adapter.tick(0.0)  # two transient failures, then both axes read
    assert result.writes and {r.axis for r in result.writes} == {1, 3}
    # each axis with its own temperature, also in the log records
    assert {r.axis: r.temperature for r in result.writes} == {1: 21.0, 3: 23.0}
    dead = _FailingSensors(transient=0, forever=True)
    adapter = TemperatureAdapter(dead, table, TwinSensors(dead, []), axes=[1], sleep=lambda s: None)
    result = adapter.tick(0.0)  # no exception: nothing written this period
    assert result.temperature is None and not result.writes and not dead.writes
    assert dead.reads == adapter.retries + 1
