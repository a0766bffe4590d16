"""Example test suite against geo-server's default machine — copy it and adapt it.

It uses the fixtures of `geo_clients.pytest_plugin` (enabled below; with the installed
package `-p geo_clients.pytest_plugin` or the pytest11 entry point does the same):

- `geo_server`: the machine in stepped mode, every axis homed (nothing moves until the
  test steps, so every value is exact); `step`, `move`, `home`, `nc`.
- `geo_server_factory(startup=None, homed=False, ...)`: more servers / other options.
- `geo`: reads, writes and assertions over one transport — in-process (`service`),
  `zenoh`, `modbus` or `ads` — chosen with `--geo-via` or by parametrizing `geo_via`.

The default machine (`lists/`): X (1), Y (2), Z (3) linear, C (4) rotary. X carries the
temperature compensation example of the manual (000 p.17: position_0 100 [0.1 µm],
offset_0 40 [0.1 µm], coefficient 4000 µm/m, temp_comp_n_cycles 20) and its backlash
example (000 p.13: 1000 [0.1 µm], positive, 10 cycles). Positions are in 0.1 µm.
"""

from __future__ import annotations

import pytest

pytest_plugins = ["geo_clients.pytest_plugin"]

ALL_TRANSPORTS = ["service", "zenoh", "modbus", "ads"]


@pytest.mark.parametrize("geo_via", ALL_TRANSPORTS)
def test_temperature_compensation_example_of_the_manual(geo):
    """000 p.17: Δs = 40 + 4000 µm/m · (s − 100); at X = 100 mm that is 4039.6 → 4040."""
    geo.assert_values(
        "X",
        {
            "TEMPC::activated": True,
            "TEMPC::position_0": 100,
            "TEMPC::offset_0": 40,
            "TEMPC::coefficient": 4000.0,
        },
    )
    geo.move("X", 1_000_000)  # 100 mm
    geo.step(20)  # the move's own change is not filtered; give the ramp its 20 cycles
    geo.assert_value("TEMPC::actual_offset", "X", 4040)
    geo.assert_value("SIM::command_position", "X", 1_000_000)  # display: no compensation
    # the same object by index group / index offset (axis 1 -> 0x10042), docs/design.md §2
    geo.assert_raw(0x120300, 0x10042, 4040)


@pytest.mark.parametrize("geo_via", ALL_TRANSPORTS)
def test_a_plc_write_ramps_with_temp_comp_n_cycles(geo):
    geo.move("X", 1_000_000)
    geo.write("TEMPC::coefficient", "X", 2000.0)  # steps one cycle: the ramp starts
    geo.step(19)  # 20 cycles in all (000 p.18: sin² filter over temp_comp_n_cycles)
    geo.assert_value("TEMPC::actual_offset", "X", 2040)  # 40 + 2000e-6·999 900 = 2039.8


def test_addresses_and_attributes(geo):
    geo.assert_raw(0x120300, 0x10043, 4000.0)  # TEMPC::coefficient, axis 1
    geo.assert_raw(0x120300, 0x20043, 23.0)  # Y: achsmd2.lis
    geo.assert_raw(0x120300, 0x100AF, 1000)  # BC::conf. backlash of X (000 p.12)
    geo.assert_raw(0x120400, 0x10043, "TEMPC::coefficient")  # name attribute (+0x100)
    geo.assert_raw(0x120500, 0x10043, "REAL64")  # type attribute (+0x200)
    geo.assert_raw(0x120600, 0x10043, 8)  # length attribute (+0x300)
    geo.assert_raw(0x120800, 0x10043, 1)  # writable attribute (+0x500)


def test_backlash_on_reversal(geo_server):
    """000 p.13: X backlash 1000 with positive initial direction: moving negative after
    the reversal adds −1000, ramped over n_backlash_cyc = 10 cycles."""
    geo = geo_server.via("service")
    geo.move("X", 100_000)
    geo.assert_value("BC::actual backlash", "X", 0)  # same direction as the initial one
    geo.move("X", 0)
    geo.assert_values("X", {"BC::actual backlash": -1000, "BC::sum backlash": -1000})
    # Y: 50, initial direction negative -> moving positive is the other direction
    geo.move("Y", 10_000)
    geo.assert_value("BC::actual backlash", "Y", 50)


@pytest.mark.parametrize("geo_via", ["service", "zenoh"])
def test_nc_switches_temperature_compensation_off(geo):
    geo.move("X", 1_000_000)
    geo.step(20)
    geo.nc("X[COMP OFF TEMP]")  # 000 §5.1
    geo.step(20)
    geo.assert_values("X", {"TEMPC::activated": False, "TEMPC::actual_offset": 0})
    geo.nc("X[COMP ON TEMP]")
    geo.step(20)
    geo.assert_value("TEMPC::actual_offset", "X", 4040)


def test_temperature_compensation_needs_homing(geo_server_factory):
    """000 p.15: effective only when selected and the axis is homed."""
    geo = geo_server_factory(homed=False).via("service")
    geo.step(1)
    geo.assert_values("X", {"TEMPC::activated": True, "TEMPC::f_is_active": False})
    geo.assert_value("TEMPC::actual_offset", "X", 0)
    geo.home("X")
    geo.step(20)
    geo.assert_value("TEMPC::f_is_active", "X", True)
    geo.assert_value("TEMPC::actual_offset", "X", 40)  # 40 + 4000e-6·(0 − 100) = 39.6


@pytest.mark.parametrize("geo_via", ALL_TRANSPORTS)
def test_errors_carry_the_ads_codes(geo):
    # docs/design.md §9: out of range 0x706 (coefficient −10000…10000, 000 p.21); read-only 0x704
    geo.expect_error(0x706, lambda: geo.write("TEMPC::coefficient", "X", 20000.0))
    geo.expect_error(0x704, lambda: geo.write("BC::actual backlash", "X", 1))
    geo.assert_value("TEMPC::coefficient", "X", 4000.0)
