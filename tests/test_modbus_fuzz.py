"""Malformed Modbus/TCP frames over raw sockets: exceptions or a closed connection, never
a crash; the GEO cycle keeps running. Bounded: fixed seed, short socket timeouts."""

from __future__ import annotations

import random
import socket
import struct

import pytest
from conftest import run_in
from pymodbus.client import ModbusTcpClient

from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

RECV_TIMEOUT = 0.3


@pytest.fixture
def running(loop_thread, machine):
    """A server over a machine whose GEO cycle runs in real time."""
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    iface = ModbusInterface(service, ModbusOptions(port=0))
    run_in(loop_thread, iface.start())
    sched.start()
    yield iface, service
    sched.stop()
    run_in(loop_thread, iface.close())


def frame(pdu: bytes, unit: int = 1, tid: int = 7, pid: int = 0, length: int | None = None):
    n = len(pdu) + 1 if length is None else length
    return struct.pack(">HHHB", tid, pid, n, unit) + pdu


def exchange(port: int, data: bytes) -> bytes:
    """Send raw bytes; return what came back within the timeout (b"" = nothing/closed)."""
    with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
        s.sendall(data)
        s.settimeout(RECV_TIMEOUT)
        try:
            return s.recv(512)
        except (TimeoutError, ConnectionResetError):
            return b""


def healthy(iface: ModbusInterface, service: ObjectService) -> None:
    """The server still answers correctly and the cycle still runs."""
    before = service.current(stale_ok=True).cycle
    with ModbusTcpClient("127.0.0.1", port=iface.port, timeout=2, retries=0) as c:
        rr = c.read_holding_registers(0x4004, count=2, device_id=0)  # SIM::cycle_count
        assert not rr.isError(), rr
        assert (rr.registers[0] << 16 | rr.registers[1]) >= before
    assert service.current(stale_ok=True).cycle > before or service.info.running


@pytest.mark.parametrize(
    ("name", "data", "want"),
    [
        # FC 3 quantity 0 / too many → 3; pymodbus' decoder refuses these itself
        ("fc3 count 0", frame(b"\x03\x01\x0c\x00\x00"), None),
        ("unknown fc 0x41", frame(b"\x41\x00\x00"), b"\xc1\x01"),
        ("fc 20 file record", frame(b"\x14\x07\x06\x00\x01\x00\x00\x00\x01"), b"\x94\x01"),
        ("fc 8 diagnostics", frame(b"\x08\x00\x04\x00\x00"), b"\x88\x01"),
        ("fc3 gap", frame(b"\x03\x00\x00\x00\x01"), b"\x83\x02"),
        ("fc16 byte count lies", frame(b"\x10\x01\x0c\x00\x04\x02\x40\xaf"), b"\x90\x03"),
        ("fc3 unknown unit", frame(b"\x03\x01\x0c\x00\x04", unit=77), b"\x83\x0b"),
        ("fc3 truncated pdu", frame(b"\x03\x01"), None),
        ("request with exception fc", frame(b"\x83\x02"), None),
        ("empty pdu", frame(b""), None),
    ],
)
def test_malformed_frames(running, name, data, want):
    iface, service = running
    reply = exchange(iface.port, data)
    if want is not None:
        assert reply[7:] == want, (name, reply.hex())
        assert reply[:2] == data[:2]  # transaction id echoed
    healthy(iface, service)


@pytest.mark.parametrize(
    "data",
    [
        b"\x00",  # truncated MBAP
        b"\x00\x07\x00\x00\x00",
        frame(b"\x03\x01\x0c\x00\x04", pid=1),  # not Modbus (protocol id 1)
        frame(b"\x03\x01\x0c\x00\x04", length=200),  # announces more than it sends
        frame(b"\x03\x01\x0c\x00\x04", length=0),
        b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",
        b"\xff" * 300,
    ],
)
def test_garbage_and_truncated_headers(running, data):
    iface, service = running
    exchange(iface.port, data)  # whatever comes back (usually nothing)
    healthy(iface, service)


def test_random_frames_bounded(running):
    """150 random PDUs behind valid MBAP headers, then random byte soup."""
    iface, service = running
    rng = random.Random(0x120300)
    fcs = [1, 2, 3, 4, 5, 6, 15, 16, 22, 23, 43, rng.randrange(256)]
    with socket.create_connection(("127.0.0.1", iface.port), timeout=2) as s:
        s.settimeout(0.05)
        for i in range(150):
            pdu = bytes([rng.choice(fcs)]) + rng.randbytes(rng.randrange(0, 12))
            unit = rng.choice([0, 1, 2, 3, 4, 9, 255])
            try:
                s.sendall(frame(pdu, unit=unit, tid=i))
                s.recv(512)
            except TimeoutError:
                pass
            except OSError:
                break  # the server closed the connection: allowed
    for _ in range(20):
        exchange(iface.port, rng.randbytes(rng.randrange(1, 40)))
    healthy(iface, service)
    assert service.info.running
