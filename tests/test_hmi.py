"""HMI diagnostics readout (`geo_clients.hmi`), headless against a stepped server over Zenoh.

Snapshot output (`--once --format json|csv`) is checked field by field against values
computed by hand (temperature compensation of the manual's example, 000 p.17) and read
from the server; the live view is driven by real Zenoh publications and rendered to text.
"""

from __future__ import annotations

import csv
import functools
import io
import json

import pytest
from geo_clients.hmi import (
    AXIS_FIELDS,
    COMPENSATIONS,
    CSV_FIELDS,
    Hmi,
    HmiModel,
    KeyParser,
    main,
    render_text,
    rich_text,
    run_live,
    snapshot_csv,
)
from geo_clients.testing import GeoTestServer

from geo_server import access

pytest_plugins = ["geo_clients.pytest_plugin"]

X_AT_100MM = 1_000_000
#: 000 p.17: position_0 100, offset_0 40, coefficient 4000 µm/m; X at 100 mm:
#: 40 + 4000e-6·(1 000 000 − 100) = 4039.6 -> 4040 (docs/design.md §3 rounding)
TEMPC_X = 4040


@pytest.fixture
def srv(geo_server: GeoTestServer) -> GeoTestServer:
    geo_server.start("zenoh")
    geo_server.move("X", X_AT_100MM)
    geo_server.step(25)  # temp_comp_n_cycles 20: the ramp is over
    return geo_server


def argv(srv: GeoTestServer, *extra: str) -> list[str]:
    opts = srv.client_options("zenoh")
    return ["--connect", opts["endpoint"], "--machine", opts["machine"], "--timeout", "5", *extra]


def expected_axis(srv: GeoTestServer, axis: int) -> dict:
    """The snapshot entry of one axis, built from the server's own values."""
    r = functools.partial(access.read_name, srv.service)
    entry = {"axis": axis, **{f: r(n, axis) for f, n in AXIS_FIELDS}}
    comps = {}
    for cv in COMPENSATIONS:
        c = {col: None if getattr(cv, col) is None else r(getattr(cv, col), axis)
             for col in ("selected", "effective", "actual", "delta", "unfiltered")}  # fmt: skip
        c["parameters"] = {k: r(n, axis) for k, n in cv.parameters}
        comps[cv.key] = c
    entry["compensations"] = comps
    return entry


def test_key_parser():
    k = KeyParser("m")
    kind, obj, axis = k.parse("cnc/m/axis/2/tempc/actual_offset")
    assert (kind, obj.name, axis) == ("named", "TEMPC::actual_offset", 2)
    assert k.parse("cnc/m/axis/1/lsec/ssfk_activated")[1].name == "ssfk activated"
    assert k.parse("cnc/m/axis/1/bc/conf_backlash")[1].name == "BC::conf. backlash"
    assert k.parse("cnc/m/sim/axis/3/frict_additive_current")[1].name == "FRICT::additive_current"
    assert k.parse("cnc/m/sim/machine/cycle_count")[1:][1] == 0
    assert k.parse("cnc/m/status")[0] == "status"
    assert k.parse("cnc/m/errors")[0] == "errors"
    assert k.parse("cnc/other/status")[0] == "other"
    assert k.parse("cnc/m/axis/x/tempc/actual_offset")[0] == "other"


def test_get_replies_never_overwrite_publications():
    m = HmiModel("m")
    m.apply("cnc/m/axis/1/tempc/actual_offset", b"7", published=True)
    m.apply("cnc/m/axis/1/tempc/actual_offset", b"3", published=False)
    assert m.value("TEMPC::actual_offset", 1) == 7
    m.apply("cnc/m/errors", b'[{"message": "a"}, {"message": "b"}]', published=False)
    m.apply("cnc/m/errors", b'{"message": "c"}', published=True)
    assert [e["message"] for e in m.errors] == ["a", "b", "c"]
    m.apply("cnc/m/axis/1/tempc/actual_offset", b"not json")  # ignored
    assert m.value("TEMPC::actual_offset", 1) == 7


def test_once_json_field_by_field(srv: GeoTestServer, capsys):
    assert main(argv(srv, "--once", "--format", "json")) == 0
    snap = json.loads(capsys.readouterr().out)
    assert snap["machine"] == "test"
    assert snap["status"]["cycle"] == srv.cycle
    assert snap["status"]["axes"] == [1, 2, 3, 4]
    assert snap["status"]["cycle_time_us"] == 1000
    assert [a["axis"] for a in snap["axes"]] == [1, 2, 3, 4]
    x = snap["axes"][0]
    # by hand: X stands at 100 mm, temperature compensation of 000 p.17
    assert x["command_position"] == X_AT_100MM
    assert x["homed"] is True and x["velocity"] == 0
    t = x["compensations"]["TEMP"]
    assert t == {
        "selected": True,
        "effective": True,
        "actual": TEMPC_X,
        "delta": None,
        "unfiltered": None,
        "parameters": {"coefficient": 4000.0, "offset_0": 40, "position_0": 100},
    }
    assert x["compensations"]["BC"]["parameters"] == {"conf_backlash": 1000}  # achsmd1.lis
    # docs/design.md §3: output = command + BC + TEMPC + CROSSC + CC2 + LSEC + CROSSTALK
    comps = x["compensations"]
    total = sum(comps[k]["actual"] for k in ("BC", "TEMP", "CROSS", "PLANE", "LSEC", "CROSSTALK"))
    assert x["total_offset"] == total
    assert x["output_position"] == X_AT_100MM + total
    # every field of every axis equals what the server holds
    for entry in snap["axes"]:
        assert entry == expected_axis(srv, entry["axis"])
    assert snap["errors"] == srv.errors()


def test_once_csv_field_by_field(srv: GeoTestServer, capsys):
    assert main(argv(srv, "--once", "--format", "csv", "--axis", "1", "--axis", "3")) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert tuple(rows[0]) == CSV_FIELDS
    assert [(r["axis"], r["compensation"]) for r in rows] == [
        (str(a), cv.key) for a in (1, 3) for cv in COMPENSATIONS
    ]
    by = {(int(r["axis"]), r["compensation"]): r for r in rows}
    t = by[(1, "TEMP")]
    assert (t["selected"], t["effective"], t["actual"], t["delta"], t["unfiltered"]) == (
        "True",
        "True",
        str(TEMPC_X),
        "",
        "",
    )
    assert t["parameters"] == "coefficient=4000.0;offset_0=40;position_0=100"
    assert t["command_position"] == str(X_AT_100MM)
    for (axis, comp), row in by.items():
        want = expected_axis(srv, axis)
        c = want["compensations"][comp]
        for col in ("selected", "effective", "actual", "delta", "unfiltered"):
            assert row[col] == ("" if c[col] is None else str(c[col])), (axis, comp, col)
        for fld in ("homed", "command_position", "output_position", "total_offset"):
            assert row[fld] == str(want[fld]), (axis, fld)


def test_once_text_and_no_server(srv: GeoTestServer, capsys):
    assert main(argv(srv, "--once", "--axis", "1")) == 0
    out = capsys.readouterr().out
    # X at 100 mm (1 000 000 increments of 0.1 µm); offset_0 40 increments = 4 µm
    assert "cnc/test  cycle" in out and "axis 1  homed yes  command 100 mm" in out
    assert "coefficient=4000 µm/m offset_0=4 µm position_0=0.01 mm" in out
    assert main(argv(srv, "--once", "--axis", "X", "--raw")) == 0  # by name; increments
    out = capsys.readouterr().out
    assert "axis 1  homed yes  command 1000000" in out
    assert "coefficient=4000 offset_0=40 position_0=100" in out
    assert main(argv(srv, "--once", "--axis", "Q")) == 2
    assert "no axis named 'Q'" in capsys.readouterr().err
    assert main(["--connect", srv.endpoint("zenoh"), "--machine", "nobody", "--timeout", "0.5",
                 "--once"]) == 1  # fmt: skip
    assert "no answer from cnc/nobody" in capsys.readouterr().err


def test_live_view_follows_publications(srv: GeoTestServer):
    with Hmi("test", [srv.endpoint("zenoh")], timeout=5) as hmi:
        model = hmi.start()
        assert model.value("TEMPC::actual_offset", 1) == TEMPC_X
        # the PLC writes a new coefficient: 40 + 2000e-6·999 900 = 2039.8 -> 2040
        srv.via("service").write("TEMPC::coefficient", 1, 2000.0)
        srv.step(25)
        assert model.wait_for(lambda m: m.value("TEMPC::actual_offset", 1) == 2040)
        assert model.wait_for(lambda m: m.value("TEMPC::coefficient", 1) == 2000.0)
        assert model.wait_for(lambda m: m.status.get("cycle") == srv.cycle)
        # an error reported by the machine (monitoring) arrives on cnc/<m>/errors
        srv.machine.report(70435, "movement requires compensations", axis=1)
        assert model.wait_for(lambda m: any(e.get("error_id") == 70435 for e in m.errors))
        text = render_text(model, [1])
        lines = text.splitlines()
        assert lines[0].startswith(f"cnc/test  cycle {srv.cycle}  T 1000 µs  stepped")
        assert lines[2].startswith("axis 1  homed yes  command 100 mm  output ")
        temp = next(ln for ln in lines if ln.strip().startswith("TEMP "))
        assert temp.split() == [
            "TEMP", "yes", "yes", "204", "µm", "-", "-",
            "coefficient=2000", "µm/m", "offset_0=4", "µm", "position_0=0.01", "mm",
        ]  # fmt: skip
        assert "[70435] axis 1 movement requires compensations" in lines[-1]
        buf = io.StringIO()  # not a terminal: views appended, no control codes
        run_live(hmi, [1], refresh=0.01, duration=0.05, plain=True, out=buf)
        assert "\x1b" not in buf.getvalue() and "TEMP" in buf.getvalue()
        assert buf.getvalue().startswith("--- ")

        class Tty(io.StringIO):
            def isatty(self) -> bool:
                return True

        tty = Tty()  # a terminal: redrawn in place
        run_live(hmi, [1], refresh=0.01, duration=0.05, plain=True, out=tty)
        assert "\x1b[2J" in tty.getvalue()
        pytest.importorskip("rich")
        rich_out = rich_text(model, width=140, only=[1])
        assert "axis 1  homed yes  command 100 mm" in rich_out
        row = next(ln for ln in rich_out.splitlines() if " TEMP " in ln)
        assert "204 µm" in row and "coefficient=2000 µm/m" in row
        assert "[70435]" in rich_out
        # the live loop itself, for a moment, into a buffer (rich)
        buf = Tty()
        run_live(hmi, [1], refresh=0.01, duration=0.05, out=buf)
        assert "TEMP" in buf.getvalue() and "coefficient" in buf.getvalue()


def test_csv_of_an_empty_model():
    assert snapshot_csv(HmiModel("m")) == ",".join(CSV_FIELDS) + "\n"
