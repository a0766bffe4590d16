"""An independent Modbus client: Debian's `mbpoll` (libmodbus) against geo-server.

Flags (docs/design.md §9): `-m tcp -p PORT -a UNIT`, `-0` PDU addressing
(the address is the register number of docs/design.md §8), `-1` poll once, `-o` timeout in
seconds, `-t 4:int -B` a 32-bit integer in holding registers with the high word first,
`-t 0` coils. Values to write follow the host (negative ones after `--`).
"""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest
from conftest import run_in

from geo_server import access
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

MBPOLL = shutil.which("mbpoll")
pytestmark = pytest.mark.skipif(
    MBPOLL is None, reason="mbpoll is not on PATH (Debian: apt-get install -y mbpoll)"
)


@pytest.fixture
def port(loop_thread, service):
    access.write_name(service, "SIM::set_position", 2, -1_234_567)
    access.step(service, 3)
    iface = ModbusInterface(service, ModbusOptions(port=0))
    run_in(loop_thread, iface.start())
    yield iface.port
    run_in(loop_thread, iface.close())


def mbpoll(port: int, unit: int, ref: int, kind: str, *values: str) -> subprocess.CompletedProcess:
    args = [MBPOLL, "-m", "tcp", "-p", str(port), "-a", str(unit), "-0", "-1", "-o", "2"]
    args += ["-r", str(ref), "-t", kind]
    if kind.endswith((":int", ":float")):
        args.append("-B")
    args.append("127.0.0.1")
    if values:
        args += ["--", *values]
    return subprocess.run(args, capture_output=True, text=True, timeout=20, check=False)


def value_at(out: str, ref: int) -> str:
    m = re.search(rf"^\[{ref}\]:\s+(\S+)", out, re.M)
    assert m, out
    return m.group(1)


def test_read_sgn32(port, service):
    ref = 0x4004  # SIM::command_position, unit 2
    r = mbpoll(port, 2, ref, "4:int")
    assert r.returncode == 0, r.stderr
    assert int(value_at(r.stdout, ref)) == access.read_name(service, "SIM::command_position", 2)
    assert access.read_name(service, "SIM::command_position", 2) == -1_234_567
    r = mbpoll(port, 1, 4 * 0x42, "4:int")  # TEMPC::actual_offset
    assert int(value_at(r.stdout, 4 * 0x42)) == access.read_name(service, "TEMPC::actual_offset", 1)


def test_read_machine_unit_zero(port, service):
    r = mbpoll(port, 0, 0x4004, "4:int")  # SIM::cycle_count
    assert r.returncode == 0, r.stderr
    assert int(value_at(r.stdout, 0x4004)) == access.read_name(service, "SIM::cycle_count") == 3


def test_coil_read_and_write(port, service):
    r = mbpoll(port, 1, 0x41, "0")  # TEMPC::activated
    assert r.returncode == 0, r.stderr
    assert value_at(r.stdout, 0x41) == str(int(access.read_name(service, "TEMPC::activated", 1)))
    new = not access.read_name(service, "TEMPC::activated", 1)
    r = mbpoll(port, 1, 0x41, "0", str(int(new)))
    assert r.returncode == 0, r.stderr
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::activated", 1) is new
    assert value_at(mbpoll(port, 1, 0x41, "0").stdout, 0x41) == str(int(new))


def test_write_sgn32(port, service):
    r = mbpoll(port, 3, 4 * 0x44, "4:int", "-250")  # TEMPC::offset_0
    assert r.returncode == 0, r.stderr
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::offset_0", 3) == -250


def test_exceptions_reach_mbpoll(port):
    r = mbpoll(port, 1, 0x40, "0")
    assert r.returncode != 0
    assert "Illegal data address" in r.stderr
    r = mbpoll(port, 42, 0x4004, "4:int")
    assert r.returncode != 0
    assert "Target device failed to respond" in r.stderr
