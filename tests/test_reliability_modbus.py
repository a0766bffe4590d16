"""Modbus TCP under a careless or hostile client: pipelining, protocol exceptions,
broken headers, too many connections, frames that never finish.

Raw sockets on 127.0.0.1 against the real server, so the bytes on the wire are what is
asserted; every receive has a timeout. Expected replies are written out by hand from
the Modbus application protocol (v1.1b3): an exception reply is the function code with
its high bit set and the exception code.
"""

from __future__ import annotations

import random
import socket
import struct
import time
from collections.abc import Iterator

import pytest
from conftest import run_in

from geo_server import access
from geo_server.dictionary import load_dictionary
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService, ServiceLimits
from geo_server.transports.modbus.regmap import encode, register_address
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

D = load_dictionary()
COEF = D.by_name("TEMPC::coefficient")
COEF_ADDR = register_address(COEF)  # 4 · 0x43 = 268
TIMEOUT = 5.0


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise EOFError(f"connection closed after {len(buf)} of {n} bytes")
        buf += chunk
    return buf


def recv_adu(sock: socket.socket) -> tuple[int, int, bytes]:
    """(transaction id, unit, PDU) of the next reply."""
    tid, pid, length, unit = struct.unpack(">HHHB", recv_exact(sock, 7))
    assert pid == 0
    return tid, unit, recv_exact(sock, length - 1)


def nothing_more(sock: socket.socket, wait: float = 0.2) -> bool:
    sock.settimeout(wait)
    try:
        return sock.recv(1) == b"" and False
    except TimeoutError:
        return True
    finally:
        sock.settimeout(TIMEOUT)


def closed_by_server(sock: socket.socket, within: float = TIMEOUT) -> bool:
    sock.settimeout(within)
    try:
        while True:
            if sock.recv(4096) == b"":
                return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


def write_coef(value: float) -> bytes:
    regs = encode(COEF, value)
    return struct.pack(">BHHB", 16, COEF_ADDR, 4, 8) + struct.pack(">4H", *regs)


READ_COEF = struct.pack(">BHH", 3, COEF_ADDR, 4)


def connect(iface: ModbusInterface) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", iface.port), timeout=TIMEOUT)
    s.settimeout(TIMEOUT)
    return s


class HandCranked(Scheduler):
    """Cycles "run by themselves" as far as the transports can tell (writes wait for
    the cycle that applies them), but a cycle runs only when the test cranks it."""

    def __init__(self, machine: Machine) -> None:
        super().__init__(machine, mode="stepped")

    @property
    def running(self) -> bool:
        return True

    def crank(self) -> None:
        self.machine.run_cycle()


@pytest.fixture
def stepped(loop_thread, service) -> Iterator[ModbusInterface]:
    iface = ModbusInterface(service, ModbusOptions(port=0))
    run_in(loop_thread, iface.start())
    yield iface
    run_in(loop_thread, iface.close())


# ---------------------------------------------------------------------- pipelining


def test_write_then_read_in_one_segment_get_their_own_replies_in_order(loop_thread, machine):
    """The read queued behind a write is answered after it, and sees the written value."""
    sched = HandCranked(machine)
    service = ObjectService(machine, sched, ServiceLimits(stall_after=3600))
    iface = ModbusInterface(service, ModbusOptions(port=0, write_timeout=TIMEOUT))
    run_in(loop_thread, iface.start())
    try:
        with connect(iface) as s:
            s.sendall(mbap(1, 1, write_coef(42.5)) + mbap(2, 1, READ_COEF))
            deadline = time.monotonic() + TIMEOUT
            while iface.requests < 1 and time.monotonic() < deadline:
                time.sleep(0.005)
            assert nothing_more(s)  # the write waits for its cycle; the read waits for it
            sched.crank()
            tid, unit, pdu = recv_adu(s)
            assert (tid, unit, pdu) == (1, 1, struct.pack(">BHH", 16, COEF_ADDR, 4))
            tid, unit, pdu = recv_adu(s)
            assert (tid, unit, pdu[:2]) == (2, 1, b"\x03\x08")
            assert list(struct.unpack(">4H", pdu[2:])) == encode(COEF, 42.5)
            assert nothing_more(s)  # exactly one reply per request
    finally:
        run_in(loop_thread, iface.close())


@pytest.mark.realtime
def test_a_hundred_pipelined_requests_in_random_segments(loop_thread, machine):
    """Real-time cycle: 50 writes interleaved with 50 reads, sent as one byte stream cut
    at random places. Every request gets exactly its own reply, in order, and every read
    sees the write sent just before it."""
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    iface = ModbusInterface(service, ModbusOptions(port=0, write_timeout=TIMEOUT))
    run_in(loop_thread, iface.start())
    sched.start()
    values = [round(-500 + 20.25 * i, 2) for i in range(50)]
    stream = b""
    for i, v in enumerate(values):
        stream += mbap(2 * i + 1, 2, write_coef(v)) + mbap(2 * i + 2, 2, READ_COEF)
    rng = random.Random(14)
    try:
        with connect(iface) as s:
            pos = 0
            while pos < len(stream):
                n = rng.randint(1, 40)
                s.sendall(stream[pos : pos + n])
                pos += n
            for i, v in enumerate(values):
                assert recv_adu(s) == (2 * i + 1, 2, struct.pack(">BHH", 16, COEF_ADDR, 4))
                tid, unit, pdu = recv_adu(s)
                assert (tid, unit) == (2 * i + 2, 2)
                assert list(struct.unpack(">4H", pdu[2:])) == encode(COEF, v), i
            assert nothing_more(s)
        assert access.read_name(service, "TEMPC::coefficient", 2) == values[-1]
    finally:
        sched.stop()
        run_in(loop_thread, iface.close())


# ---------------------------------------------------------------------- exceptions

CASES = [
    ("FC 3 quantity 0", struct.pack(">BHH", 3, COEF_ADDR, 0), b"\x83\x03"),
    ("FC 3 quantity 126", struct.pack(">BHH", 3, COEF_ADDR, 126), b"\x83\x03"),
    ("FC 4 quantity 126", struct.pack(">BHH", 4, COEF_ADDR, 126), b"\x84\x03"),
    ("FC 1 quantity 2001", struct.pack(">BHH", 1, 0x41, 2001), b"\x81\x03"),
    ("FC 2 quantity 0", struct.pack(">BHH", 2, 0x41, 0), b"\x82\x03"),
    ("FC 16 quantity 124", struct.pack(">BHHB", 16, COEF_ADDR, 124, 0), b"\x90\x03"),
    ("FC 16 byte count wrong", struct.pack(">BHHB", 16, COEF_ADDR, 4, 6) + bytes(6), b"\x90\x03"),
    ("FC 15 quantity 1969", struct.pack(">BHHB", 15, 0x41, 1969, 247) + bytes(247), b"\x8f\x03"),
    ("FC 5 value 0x1234", struct.pack(">BHH", 5, 0x41, 0x1234), b"\x85\x03"),
    ("FC 5 value 0x0001", struct.pack(">BHH", 5, 0x41, 0x0001), b"\x85\x03"),
    ("FC 3 one byte short", struct.pack(">BHB", 3, COEF_ADDR, 4), b"\x83\x03"),
    ("FC 8 diagnostics", b"\x08\x00\x00\x12\x34", b"\x88\x01"),
    ("FC 0x81", b"\x81\x00\x00\x00\x01", b"\x81\x01"),
    ("FC 0xC3", b"\xc3\x00\x00\x00\x01", b"\xc3\x01"),
    ("FC 0xFF", b"\xff", b"\xff\x01"),
    ("FC 43 other MEI", b"\x2b\x0d\x01\x00", b"\xab\x01"),
    ("FC 43/14 code 5", b"\x2b\x0e\x05\x00", b"\xab\x03"),
    ("FC 3 no object there", struct.pack(">BHH", 3, 0, 1), b"\x83\x02"),
    ("FC 6 read-only object", struct.pack(">BHH", 6, 4 * 0x93, 1), b"\x86\x02"),
]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "pdu", "reply"), CASES, ids=[c[0] for c in CASES])
def test_protocol_exceptions(stepped, name, pdu, reply):
    with connect(stepped) as s:
        s.sendall(mbap(77, 1, pdu))
        assert recv_adu(s) == (77, 1, reply)
        # the connection goes on: a valid request after the exception is answered
        s.sendall(mbap(78, 1, READ_COEF))
        tid, _unit, got = recv_adu(s)
        assert (tid, got[:2]) == (78, b"\x03\x08")


def test_unknown_unit_is_exception_11(stepped):
    with connect(stepped) as s:
        s.sendall(mbap(5, 9, READ_COEF))  # the default machine has axes 1…3
        assert recv_adu(s) == (5, 9, b"\x83\x0b")


@pytest.mark.parametrize(
    "header",
    [
        struct.pack(">HHHB", 9, 1, 6, 1),  # protocol id 1
        struct.pack(">HHHB", 9, 0, 0, 1),  # length 0
        struct.pack(">HHHB", 9, 0, 1, 1),  # length 1: no function code
        struct.pack(">HHHB", 9, 0, 300, 1),  # longer than any Modbus PDU
    ],
    ids=["protocol-id", "length-0", "length-1", "length-300"],
)
def test_a_broken_header_closes_the_connection_after_the_replies_due(stepped, header):
    with connect(stepped) as s:
        s.sendall(mbap(8, 1, READ_COEF) + header + b"\x03\x01\x0c\x00\x04")
        tid, _unit, pdu = recv_adu(s)
        assert (tid, pdu[:2]) == (8, b"\x03\x08")  # the request before it is answered
        assert closed_by_server(s)
    with connect(stepped) as s:  # and the server serves the next client
        s.sendall(mbap(10, 1, READ_COEF))
        assert recv_adu(s)[0] == 10


# ---------------------------------------------------------------------- resources


def test_connections_beyond_the_cap_are_closed(loop_thread, service):
    iface = ModbusInterface(service, ModbusOptions(port=0, max_connections=4))
    run_in(loop_thread, iface.start())
    socks = []
    try:
        for _ in range(4):
            socks.append(connect(iface))
        for s in socks:  # all four work
            s.sendall(mbap(1, 1, READ_COEF))
            assert recv_adu(s)[0] == 1
        with connect(iface) as fifth:
            assert closed_by_server(fifth)
        assert iface.refused_connections == 1
        socks.pop().close()
        deadline = time.monotonic() + TIMEOUT
        while iface.connection_count > 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        with connect(iface) as again:  # a freed place is taken again
            again.sendall(mbap(2, 1, READ_COEF))
            assert recv_adu(again)[0] == 2
    finally:
        for s in socks:
            s.close()
        run_in(loop_thread, iface.close())


@pytest.mark.slow
def test_an_unfinished_frame_is_dropped_after_the_timeout(loop_thread, service):
    iface = ModbusInterface(service, ModbusOptions(port=0, incomplete_frame_timeout=0.3))
    run_in(loop_thread, iface.start())
    try:
        with connect(iface) as s:
            s.sendall(mbap(3, 1, READ_COEF)[:9])  # header and two bytes of the PDU
            assert closed_by_server(s)
        with connect(iface) as s:  # frames that do complete keep the connection
            for i in range(5):
                s.sendall(mbap(i, 1, READ_COEF))
                assert recv_adu(s)[0] == i
                time.sleep(0.1)
            assert nothing_more(s)
    finally:
        run_in(loop_thread, iface.close())
