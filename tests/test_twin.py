"""The twin: true position and residual computed by hand for simple machines, the thermal
node's exponential at t = τ, the twin file's errors with file and line, determinism, and
the objects over every transport.

Units (docs/twin.md): the twin file speaks mm and µm; the objects increments (0.1 µm).
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest
from conftest import run_in

from geo_server import access
from geo_server.errors import AdsError
from geo_server.listfile import ListFileError, load_machine
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService
from geo_server.twin.file import TwinFileError, load_twin

AXIS_LIST = """kopf.achs_nr 1
kopf.log_achs_name X
kenngr.achs_typ 1
getriebe[0].vb_max 500000
getriebe[0].a_max 2000
"""
STARTUP = """zahl_mds 1
achs_mds[0] achsmd1.lis
achs_mds_log_ax_nr[0] 1
"""


def one_axis(folder: Path, twin: str) -> Path:
    """A machine with one linear axis X, no compensation, and `twin` as its twin file."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "achsmd1.lis").write_text(AXIS_LIST, encoding="utf-8")
    (folder / "hochlauf.lis").write_text(STARTUP, encoding="utf-8")
    (folder / "twin.toml").write_text(twin, encoding="utf-8")
    return folder / "hochlauf.lis"


def service(startup: Path, **options) -> ObjectService:
    return ObjectService(Machine(load_machine(startup), homed=True, **options))


def value(svc: ObjectService, name: str, axis: int = 1) -> float:
    return float(access.read_name(svc, name, axis))


def jump(svc: ObjectService, position: int) -> None:
    access.write_name(svc, "SIM::set_position", 1, position)
    access.step(svc, 1)


# ---------------------------------------------------------------------- geometry


def test_linear_pitch_error_by_hand(tmp_path):
    """Pitch error −10 µm at −100 mm … +10 µm at +100 mm, linear: at X = 50 mm the table
    is 5 µm further than the drive: true position 500 000 + 50 increments."""
    svc = service(
        one_axis(
            tmp_path,
            "[axis.X]\npitch = { positions = [-100.0, 100.0], errors = [-10.0, 10.0] }\n",
        )
    )
    jump(svc, 500_000)
    assert value(svc, "SIM::output_position") == 500_000  # no compensation
    assert value(svc, "TWIN::true_position") == pytest.approx(500_050, abs=1e-9)
    assert value(svc, "TWIN::residual") == pytest.approx(50, abs=1e-9)
    jump(svc, 1_500_000)  # beyond the curve: the edge value is held (+10 µm)
    assert value(svc, "TWIN::residual") == pytest.approx(100, abs=1e-9)


def test_the_drives_actual_torque_at_constant_speed_by_hand(tmp_path):
    """000 p.74: friction compensation's parameters are read off the drive's current,
    dig_drv.act_torque, "during a motion at constant speed", where it is the friction
    alone: sign(v)·(coulomb + viscous·|v|), v in mm/s (docs/twin.md). G01 at F6000 =
    100 mm/s with coulomb 2000 and viscous 12: 3200 drive units, −3200 the other way —
    the default machine's friction table was measured so (7900 at 500 mm/s)."""
    svc = service(one_axis(tmp_path, "[axis.X]\nfriction = { coulomb = 2000.0, viscous = 12.0 }\n"))
    for target, want in ((100, 3200.0), (0, -3200.0)):
        svc.nc.run(f"G90 G01 X{target} F6000")
        access.step(svc, 300)  # past the ramp (0.05 s at a_max 2000 mm/s²), not there yet
        assert value(svc, "SIM::velocity") == pytest.approx(math.copysign(100_000, want))
        assert value(svc, "dig_drv::act_torque") == pytest.approx(want, abs=1e-9)
        assert value(svc, "TWIN::friction_current") == value(svc, "dig_drv::act_torque")
        access.step(svc, 2000)


def test_reversal_and_linear_error_by_hand(tmp_path):
    """Lost motion 8 µm when moving negative (reference direction +1), and a scale error
    of 20 µm/m about 0: at +100 mm moving positive the error is 2 µm, arriving from
    above it is 2 + 8 = 10 µm."""
    svc = service(
        one_axis(
            tmp_path,
            "[axis.X]\nreversal = 8.0\nlinear = { offset = 0.0, slope = 20.0, reference = 0.0 }\n",
        )
    )
    access.write_name(svc, "SIM::target_position", 1, 1_000_000)
    access.step(svc, 2000)
    assert value(svc, "TWIN::residual") == pytest.approx(20, abs=1e-9)  # 20e-6 · 1e6
    access.write_name(svc, "SIM::target_position", 1, 1_200_000)
    access.step(svc, 2000)
    access.write_name(svc, "SIM::target_position", 1, 1_000_000)
    access.step(svc, 2000)
    assert value(svc, "TWIN::residual") == pytest.approx(20 + 80, abs=1e-9)


# ---------------------------------------------------------------------- thermal

THERMAL = """
[twin]
time_scale = 100.0               # 1 ms cycles: 0.1 s of simulated time each
ambient = [[0, 30.0]]            # the room is at 30 °C, the machine starts at 20 °C

[[node]]
name = "screw"
tau = 100.0
initial = 20.0

[[sensor]]
name = "screw"
node = "screw"
axis = "X"
noise = 0.0
resolution = 0.001
period = 0.1

[axis.X]
expansion = { node = "screw", coefficient = 10.0, reference = 0.0 }
"""


def test_the_exponential_at_t_tau(tmp_path):
    """After τ = 100 s (1000 cycles of 0.1 s) the node is 30 − 10·e^−1 = 26.3212 °C; with
    10 µm/m/K about 0, X at 100 mm is 10e-6 · 6.3212 K · 100 mm = 6.3212 µm long."""
    svc = service(one_axis(tmp_path, THERMAL))
    jump(svc, 1_000_000)
    access.step(svc, 999)  # 1000 cycles in all
    assert value(svc, "TWIN::time", 0) == pytest.approx(100.0, abs=1e-9)
    expected_temp = 30 - 10 * math.exp(-1)  # 26.3212
    assert value(svc, "TWIN::sensor_temperature") == pytest.approx(round(expected_temp, 3))
    expected_error = 10e-6 * (expected_temp - 20) * 1_000_000  # increments
    assert round(expected_error) == 63
    assert value(svc, "TWIN::residual") == pytest.approx(expected_error, abs=0.5)
    assert value(svc, "TWIN::ambient_temperature", 0) == 30.0


def test_same_seed_same_numbers_whatever_the_time_scale_option(tmp_path):
    """Noise is seeded and everything counts cycles: two runs are identical, and
    `time_scale` given to the machine replaces the file's."""
    startup = one_axis(tmp_path, THERMAL.replace("noise = 0.0", "noise = 0.05"))
    runs = []
    for _ in range(2):
        svc = service(startup)
        access.write_name(svc, "SIM::target_position", 1, 2_000_000)
        access.step(svc, 3000)
        runs.append([value(svc, n) for n in ("TWIN::sensor_temperature", "TWIN::true_position")])
    assert runs[0] == runs[1]
    fast = service(startup, time_scale=1000.0)
    access.step(fast, 100)
    assert value(fast, "TWIN::time", 0) == pytest.approx(100.0)


# ---------------------------------------------------------------------- the twin file


@pytest.mark.parametrize(
    ("text", "line", "message"),
    [
        ("[axis.X]\nreversl = 3.0\n", 2, "unknown key 'reversl'; did you mean 'reversal'?"),
        (
            "[axis.X]\npitch = { positions = [1.0, 0.0], errors = [0.0, 1.0] }\n",
            2,
            "pitch.positions must ascend",
        ),
        ("[axis.Q]\nreversal = 1.0\n", 1, "no axis 'Q' on this machine (axes: X)"),
        ("[axis.X]\nreversal = -1.0\n", 2, "reversal must be at least 0"),
        ("[twin]\nseed = 1\n[axis.X\n", 3, "not valid TOML"),
        ('[[node]]\nname = "a"\ntau = 0.0\n', 3, "tau must be greater than 0"),
        ('[[sensor]]\nname = "s"\nnode = "nowhere"\n', 3, "sensor on unknown node 'nowhere'"),
    ],
)
def test_twin_file_errors_name_file_and_line(tmp_path, text, line, message):
    path = tmp_path / "twin.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(TwinFileError) as err:
        load_twin(path, ["X"])
    assert err.value.line == line
    assert message in err.value.message
    assert str(err.value).startswith(f"{path}:{line}: ")


def test_a_bad_twin_file_fails_the_start_and_the_reload_keeps_the_old_twin(tmp_path):
    startup = one_axis(tmp_path, "[axis.X]\nreversal = 5.0\n")
    svc = service(startup)
    (tmp_path / "twin.toml").write_text("[axis.X]\nreversal = oops\n", encoding="utf-8")
    with pytest.raises(ListFileError) as err:
        load_machine(startup)
    assert f"{tmp_path / 'twin.toml'}:2:" in str(err.value)
    result = svc.commands.reload()
    assert not result.ok and "twin.toml:2" in result.message
    twin_before = svc.info.config.twin
    assert twin_before is not None and twin_before.axes["X"].reversal == 5.0


def test_a_reload_that_lost_an_axis_to_a_typo_names_the_typo_first(lists_copy):
    """Issue 45 #12, for `reload`: the start-up list's typo `achs_mdz[0]` loses axis X,
    the twin file then names a missing axis; the answer carries the typo's diagnostic
    (with its suggestion) beside the twin file's error, the machine unchanged."""
    svc = service(lists_copy)
    text = lists_copy.read_text(encoding="utf-8")
    lists_copy.write_text(text.replace("achs_mds[0] ", "achs_mdz[0] ", 1), encoding="utf-8")
    result = svc.commands.reload()
    assert not result.ok
    assert "achs_mdz[0]" in result.warnings[0] and "did you mean achs_mds[0]?" in result.warnings[0]
    assert "twin.toml:" in result.errors[0] and "no axis 'X'" in result.errors[0]
    assert 1 in svc.info.config.axes


def test_a_reload_keeps_the_temperatures(tmp_path):
    startup = one_axis(tmp_path, THERMAL)
    svc = service(startup)
    access.step(svc, 500)  # 50 s: 30 − 10·e^−0.5 = 23.935 °C
    warm = value(svc, "TWIN::sensor_temperature")
    assert warm == pytest.approx(round(30 - 10 * math.exp(-0.5), 3))
    assert svc.commands.reload().ok
    access.step(svc, 1)
    assert value(svc, "TWIN::sensor_temperature") == pytest.approx(warm, abs=0.01)


def test_a_reload_keeps_the_ambient_profile_and_the_chamber(tmp_path):
    """After a reload the ambient is the profile's at the current time (not at t = 0),
    so a soak right after it uses the right temperature; a held chamber stays held."""
    startup = one_axis(
        tmp_path, THERMAL.replace("ambient = [[0, 30.0]]", "ambient = [[0, 20.0], [100, 30.0]]")
    )
    svc = service(startup)
    access.step(svc, 500)  # 50 s: the profile says 25 °C
    assert svc.commands.reload().ok
    assert value(svc, "TWIN::ambient_temperature", 0) == pytest.approx(25.0)
    access.write_name(svc, "TWIN::soak", 0, 1)
    access.step(svc, 2)
    assert value(svc, "TWIN::sensor_temperature") == pytest.approx(25.0, abs=0.01)
    access.write_name(svc, "TWIN::ambient_temperature", 0, 40.0)
    access.step(svc, 1)
    assert svc.commands.reload().ok
    access.step(svc, 1000)  # 100 s later the profile would say 30 °C; the chamber holds 40
    assert value(svc, "TWIN::ambient_temperature", 0) == 40.0


# ---------------------------------------------------------------------- the default machine


def test_out_of_the_box_compensation_on_and_off_differ(default_cfg):
    """The default lists are what a commissioning at 20 °C of the default twin gives:
    with them on, X at 123.45 mm is within a few µm; with them off, ~0.5 mm off."""
    svc = ObjectService(Machine(default_cfg, homed=True))
    access.write_name(svc, "SIM::target_position", 1, 1_234_500)
    access.step(svc, 3000)
    on = value(svc, "TWIN::residual")
    svc.nc.run("X[COMP OFF_ALL]")
    access.step(svc, 200)
    off = value(svc, "TWIN::residual")
    assert abs(on) < 30  # 3 µm: cyclic error, scatter, the temperature line's 2nd order
    assert abs(off) > 4000  # 0.4 mm: the manual's 4000 µm/m temperature line, the pitch


def test_twin_objects_over_every_transport(loop_thread, default_cfg):
    """TWIN::true_position of X as REAL64 over ADS (8 bytes), Modbus (4 registers, high
    word first) and Zenoh (JSON) — all the same value."""
    from conftest import free_port

    from geo_server.client.ads_client import AdsClient
    from geo_server.client.modbus_client import ModbusClient
    from geo_server.client.zenoh_client import ZenohClient
    from geo_server.transports.ads.server import AdsOptions, AdsServer
    from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions
    from geo_server.transports.zenoh.options import ZenohOptions
    from geo_server.transports.zenoh.server import ZenohInterface

    svc = ObjectService(Machine(default_cfg, homed=True))
    access.write_name(svc, "SIM::target_position", 1, 654_321)
    access.step(svc, 2000)
    expected = value(svc, "TWIN::true_position")
    ep = f"tcp/127.0.0.1:{free_port()}"
    ifaces = [
        ZenohInterface(svc, ZenohOptions(machine="twin", listen=[ep])),
        ModbusInterface(svc, ModbusOptions(port=0)),
        AdsServer(svc, AdsOptions(port=0)),
    ]
    for iface in ifaces:
        run_in(loop_thread, iface.start())
    try:
        with ZenohClient(machine="twin", connect=[ep], timeout=5) as z:
            assert z.read("TWIN::true_position", 1) == expected
        with ModbusClient(port=ifaces[1].port, timeout=5) as m:
            assert m.read("TWIN::true_position", 1) == expected
            ambient = value(svc, "TWIN::ambient_temperature", 0)  # 20 → 23 °C in 2 h, at 2 s
            assert m.read("TWIN::ambient_temperature", 0) == ambient == 20 + 3 * 2.0 / 7200
        with AdsClient(port=ifaces[2].port, netid="127.0.0.33.1.1.1"[:-2], timeout=5) as a:
            raw = a.read_raw(0x12F300, (1 << 16) | 0x11, 8)
            assert struct.unpack("<d", raw)[0] == expected
        with pytest.raises(AdsError):  # read-only
            access.write_name(svc, "TWIN::true_position", 1, 0)
    finally:
        for iface in reversed(ifaces):
            run_in(loop_thread, iface.close())
