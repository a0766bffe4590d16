"""Clients that make the ADS server hold memory, on loopback.

Frame headers announcing more than the largest legal request, more connections than the
server admits, frames left unfinished, and the memory of closed connections — each while
a normal pyads client keeps reading. The server runs in the `loop_thread` on an
ephemeral port; the machine is stepped (nothing here depends on cycles).

Bounds: at most 200 connections per test (sequential batches of 50), every socket with a
timeout, every wait with a deadline; behaviour is asserted, never a duration.
"""

from __future__ import annotations

import contextlib
import itertools
import selectors
import socket
import struct
import time
import tracemalloc
from collections.abc import Iterator

import pyads
import pytest
from conftest import run_in

from geo_server import access
from geo_server.client.ads_client import close_port_first
from geo_server.dictionary import load_dictionary
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AmsAddr,
    AmsPacket,
    Command,
    Framer,
)
from geo_server.transports.ads.server import AdsOptions, AdsServer

TIMEOUT = 5.0
GEO = 0x120300
COEFFICIENT_IO = (1 << 16) | load_dictionary().by_name("TEMPC::coefficient").id
SERVER = AmsAddr("127.0.0.1.1.1", 551)
_netids = itertools.count(1)


def next_netid() -> str:
    n = next(_netids)
    return f"127.88.{n // 250}.{n % 250 + 1}.1.1"


def read_frame(invoke: int = 1) -> bytes:
    source = AmsAddr("10.8.8.8.1.1", 32000)
    data = codec.read_request(GEO, COEFFICIENT_IO, 8)
    return codec.request_frame(SERVER, source, Command.READ, data, invoke)


def connect(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def closed_by_server(socks: list[socket.socket], timeout: float = TIMEOUT) -> int:
    """How many of `socks` the server closes (EOF or reset) within `timeout` in all."""
    sel = selectors.DefaultSelector()
    for s in socks:
        sel.register(s, selectors.EVENT_READ)
    closed = 0
    deadline = time.monotonic() + timeout
    try:
        while closed < len(socks) and time.monotonic() < deadline:
            for key, _ in sel.select(max(0.0, deadline - time.monotonic())):
                s = key.fileobj
                assert isinstance(s, socket.socket)
                try:
                    data = s.recv(65536)
                except (ConnectionResetError, BrokenPipeError):
                    data = b""
                if not data:
                    sel.unregister(s)
                    closed += 1
    finally:
        sel.close()
    return closed


def answered(s: socket.socket, invoke: int) -> bool:
    """Send a Read and wait for its answer (True) or the connection's end (False)."""
    try:
        s.sendall(read_frame(invoke))
        f = Framer()
        while True:
            data = s.recv(65536)
            if not data:
                return False
            for ev in f.feed(data):
                if isinstance(ev, AmsPacket) and ev.header.invoke_id == invoke:
                    return codec.parse_read_response(ev.data)[0] == 0
    except (ConnectionResetError, BrokenPipeError):
        return False


@pytest.fixture
def server(loop_thread, service, request) -> Iterator[AdsServer]:
    options = getattr(request, "param", {})
    srv = AdsServer(service, AdsOptions(port=0, **options))
    run_in(loop_thread, srv.start())
    yield srv
    run_in(loop_thread, srv.close())


@pytest.fixture
def plc(server) -> Iterator[pyads.Connection]:
    conn = pyads.Connection(next_netid(), 551, server.address)
    conn.open()
    conn.set_timeout(int(TIMEOUT * 1000))
    yield conn
    close_port_first(conn)


def plc_reads(plc: pyads.Connection, service) -> None:
    expected = access.read_name(service, "TEMPC::coefficient", 1)
    assert plc.read(GEO, COEFFICIENT_IO, pyads.PLCTYPE_LREAL) == expected


def wait_until(loop, predicate, timeout: float = TIMEOUT) -> bool:
    async def check() -> bool:
        return bool(predicate())

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if run_in(loop, check()):
            return True
        time.sleep(0.01)
    return False


def test_headers_announcing_more_than_the_largest_request_close_at_once(
    server, plc, service
) -> None:
    """200 connections announce one byte more than the largest legal request (a sum
    command of 500 sub-requests of the largest object) and send some of it: each is
    closed, none is buffered; the pyads client reads between the batches."""
    limit = server.options.max_frame
    assert limit == codec.MAX_REQUEST_FRAME
    total = 0
    for _batch in range(4):
        socks = [connect(server.port) for _ in range(50)]
        try:
            for s in socks:
                s.sendall(struct.pack("<HI", 0, limit + 1) + b"\0" * 1000)
            total += closed_by_server(socks)
        finally:
            for s in socks:
                s.close()
        plc_reads(plc, service)
    assert total == 200
    assert server.stats.closed_for_framing == 200
    # exactly at the limit the frame is legal: the server waits for the rest
    s = connect(server.port)
    try:
        s.sendall(struct.pack("<HI", 0, limit) + b"\0" * 1000)
        assert closed_by_server([s], timeout=0.3) == 0
    finally:
        s.close()
    assert wait_until(server.loop, lambda: server.connection_count == 1)
    plc_reads(plc, service)


def test_connections_beyond_the_cap_are_closed_at_once(server, plc, service, loop_thread) -> None:
    cap = server.options.max_connections
    assert cap == 128
    held = [connect(server.port) for _ in range(cap - 1)]  # plus pyads' own: the cap
    extra: list[socket.socket] = []
    try:
        assert wait_until(loop_thread, lambda: server.connection_count == cap)
        assert answered(held[0], 1) and answered(held[-1], 2)
        extra = [connect(server.port) for _ in range(20)]
        assert closed_by_server(extra) == 20
        assert server.stats.refused_connections == 20
        assert server.connection_count == cap
        plc_reads(plc, service)
        for s in held[:10]:
            s.close()
        assert wait_until(loop_thread, lambda: server.connection_count == cap - 10)
        again = connect(server.port)  # room again: admitted and answered
        extra.append(again)
        assert answered(again, 3)
        assert server.stats.refused_connections == 20
    finally:
        for s in held + extra:
            s.close()
    assert wait_until(loop_thread, lambda: server.connection_count == 1)
    plc_reads(plc, service)


@pytest.mark.slow
@pytest.mark.parametrize("server", [{"incomplete_frame_timeout": 1.0}], indirect=True)
def test_a_frame_left_unfinished_is_dropped_after_the_timeout(
    server, plc, service, loop_thread
) -> None:
    """A stalled frame and a frame trickled one byte at a time are both dropped (the
    timeout counts from the first byte of the frame); a client whose frames each
    complete within the timeout stays connected however long it talks."""
    frame = read_frame(7)
    stalled, trickler, slow = (connect(server.port) for _ in range(3))
    try:
        stalled.sendall(frame[:20])
        trickler_bytes = codec.request_frame(
            SERVER, AmsAddr("10.8.8.9.1.1", 32001), Command.WRITE, b"\0" * 300, 1
        )
        slow_answers = 0
        for k in range(24):  # 24 × 0.1 s: far longer than the 1 s timeout
            with contextlib.suppress(ConnectionResetError, BrokenPipeError):  # (dropped)
                trickler.sendall(trickler_bytes[k : k + 1])  # a byte every 0.1 s
            if k % 4 == 0:  # a whole frame in two halves, 0.1 s apart
                slow.sendall(frame[:30])
            elif k % 4 == 1:
                slow.sendall(frame[30:])
                slow_answers += answered_pending(slow)
            time.sleep(0.1)
        # Both were closed while the loop ran: had every byte restarted the clock, the
        # trickler would only be closed a whole timeout after its last byte.
        assert closed_by_server([stalled, trickler], timeout=0.2) == 2
        assert slow_answers == 6 and answered(slow, 8)
        assert server.stats.closed_incomplete == 2
        plc_reads(plc, service)
    finally:
        for s in (stalled, trickler, slow):
            s.close()
    assert wait_until(loop_thread, lambda: server.connection_count == 1)


def answered_pending(s: socket.socket) -> int:
    """Wait for the answer to the request just completed on `s` (1 if answered)."""
    f = Framer()
    while True:
        data = s.recv(65536)
        if not data:
            return 0
        if any(isinstance(ev, AmsPacket) for ev in f.feed(data)):
            return 1


def test_receive_buffers_are_released_when_connections_close(
    server, plc, service, loop_thread
) -> None:
    """100 connections each leave 100 kB of a frame unfinished; once they closed, the
    Python heap of the process (server and test alike, via tracemalloc) is back near
    where it was: no buffer outlives its connection."""
    part = struct.pack("<HI", 0, server.options.max_frame) + b"\0" * 100_000
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        socks = [connect(server.port) for _ in range(100)]
        for s in socks:
            s.sendall(part)
        assert wait_until(
            loop_thread,
            lambda: sum(c.framer.buffered for c in server.listener.connections) >= 100 * 100_000,
        )
        held = tracemalloc.get_traced_memory()[0] - base
        assert held >= 100 * 100_000
        plc_reads(plc, service)
        for s in socks:
            s.close()
        assert wait_until(loop_thread, lambda: server.connection_count == 1)
        left = tracemalloc.get_traced_memory()[0] - base
        assert left < 2_000_000, f"{left} bytes still held after closing"
    finally:
        tracemalloc.stop()
    plc_reads(plc, service)
