"""The integration-test helpers (`geo_clients.testing`, `geo_clients.pytest_plugin`).

Used here as a user would: the fixtures of the plugin (enabled by `pytest_plugins`), and
a pytest run in a subprocess that loads the plugin with `-p geo_clients.pytest_plugin` and
selects the transport and the machine from the command line.
"""

from __future__ import annotations

import shutil
import struct

import pytest
from geo_clients.testing import GeoTestServer, ServiceClient

from geo_server.errors import AdsError
from geo_server.paths import data_dir

pytest_plugins = ["pytester", "geo_clients.pytest_plugin"]


def test_machine_control(geo_server: GeoTestServer):
    srv = geo_server
    assert srv.axes == (1, 2, 3, 4) and srv.axis("y") == 2 and srv.axis(3) == 3
    with pytest.raises(KeyError, match="no axis named 'Q'"):
        srv.axis("Q")
    n = srv.move("X", 500_000, feed=100_000)  # 50 mm at 100 mm/s: ≥ 500 cycles at 1 ms
    assert n >= 500 and srv.read("SIM::command_position", "X") == 500_000
    assert srv.read("SIM::feed", 1) == 100_000
    srv.set_position("Z", 1234)
    assert srv.read("SIM::command_position", "Z") == 1234
    cycles = srv.nc("G91 G01 X-100 F6000")  # 100 mm at 100 mm/s
    assert srv.read("SIM::command_position", "X") == -500_000 and cycles > 900
    with pytest.raises(TimeoutError, match="within 3 cycles"):
        srv.run_until(lambda s: False, max_cycles=3)
    before = srv.cycle
    srv.step(7)
    assert srv.cycle == before + 7 == srv.read("SIM::cycle_count")


def test_assertion_helpers_report_clearly(geo_server: GeoTestServer):
    geo = geo_server.via("service")
    geo.assert_value("TEMPC::coefficient", "X", 4000.0)
    with pytest.raises(AssertionError, match=r"TEMPC::coefficient \(axis X\) over service: "
                       r"expected 1\.0, got 4000\.0"):  # fmt: skip
        geo.assert_value("TEMPC::coefficient", "X", 1.0)
    geo.assert_value("TEMPC::coefficient", 1, 4000.4, abs_tol=0.5)
    with pytest.raises(AssertionError) as info:
        geo.assert_values(1, {"TEMPC::offset_0": 41, "TEMPC::position_0": 101})
    assert "offset_0" in str(info.value) and "position_0" in str(info.value)
    geo.assert_raw(0x120300, 0x10043, struct.pack("<d", 4000.0))  # bytes
    with pytest.raises(AssertionError, match="expected ADS error 0x706 over service, got none"):
        geo.expect_error(0x706, lambda: None)
    with pytest.raises(AssertionError, match=r"expected ADS error 0x704 .* got 0x706"):
        geo.expect_error(0x704, lambda: geo.write("TEMPC::coefficient", 1, 1e6))
    with pytest.raises(ValueError, match="unknown transport"):
        geo_server.via("carrier-pigeon")


def test_service_client_raw_access(geo_server: GeoTestServer):
    c = geo_server.client("service")
    assert isinstance(c, ServiceClient)
    c.write_raw(0x120300, 0x10044, struct.pack("<i", -250))
    geo_server.step(1)
    assert c.read("TEMPC::offset_0", 1) == -250
    assert c.read_raw(0x120300, 0x10044) == struct.pack("<i", -250)
    with pytest.raises(AdsError) as info:
        c.read_raw(0x120300, 0x90044)
    assert info.value.code == 0x703


@pytest.mark.parametrize("via", ["zenoh", "modbus", "ads"])
def test_every_transport_sees_the_same_values(geo_server: GeoTestServer, via: str):
    if via == "ads":
        pytest.importorskip("pyads")
    geo_server.move("X", 1_000_000)
    geo_server.step(20)
    g = geo_server.via(via)
    assert geo_server.client(via) is g.client  # one client per transport, cached
    for name in ("TEMPC::actual_offset", "LSEC::sum epsilon", "SIM::output_position"):
        assert g.read(name, "X") == geo_server.read(name, "X"), name
    g.assert_value("TEMPC::actual_offset", "X", 4040)  # 000 p.17 example
    g.write("TEMPC::offset_0", "X", 100)  # steps one cycle: applied
    assert geo_server.read("TEMPC::offset_0", 1) == 100
    assert g.read_address(0x120300, 0x10044) == 100


def test_two_machines_from_the_factory(geo_server_factory, tmp_path):
    lists = tmp_path / "lists"
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    a = geo_server_factory(lists / "hochlauf.lis", machine_name="a", homed=False)
    b = geo_server_factory(machine_name="b", cycle_ms=2.0)
    a.step(3)
    assert a.read("SIM::homed", 1) is False and b.read("SIM::homed", 1) is True
    assert b.read("SIM::cycle_time_us") == 2000
    assert a.cycle == 3 and b.cycle == 0


PLUGIN_USER_TEST = """
import pytest

def test_via_option(geo, geo_via):
    assert geo_via == "zenoh" and geo.name == "zenoh"
    geo.assert_value("SIM::homed", "X", False)      # marker below / --geo-startup list
    geo.home("X")
    geo.step(20)
    geo.assert_value("TEMPC::actual_offset", "X", 40)

@pytest.mark.geo_machine(homed=True, machine_name="m2")
def test_marker(geo_server):
    assert geo_server.machine_name == "m2"
    assert geo_server.read("SIM::homed", "X") is True

@pytest.mark.parametrize("geo_via", ["modbus"])
def test_parametrized_transport(geo):
    geo.assert_raw(0x120300, 0x10043, 4000.0)
"""


@pytest.mark.slow
def test_plugin_from_the_command_line(pytester: pytest.Pytester, tmp_path):
    lists = tmp_path / "machine"
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    # a start-up list whose axes start unhomed is the default; --geo-startup selects it,
    # the marker's homed=False keeps them unhomed
    marked = "@pytest.mark.geo_machine(homed=False)\ndef test_via_option"
    pytester.makepyfile(test_user=PLUGIN_USER_TEST.replace("def test_via_option", marked))
    result = pytester.runpytest_subprocess(
        "-p",
        "geo_clients.pytest_plugin",
        "--geo-via",
        "zenoh",
        "--geo-startup",
        str(lists / "hochlauf.lis"),
        "-W",
        "error",
        "-q",
        timeout=120,
    )
    result.assert_outcomes(passed=3)
