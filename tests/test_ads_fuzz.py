"""Bounded fuzzing of the ADS codec and server (fixed seeds, a few thousand cases).

Properties: the framer never raises and never loses a valid frame that follows garbage it
could skip; `parse_request` only ever raises `PayloadError`; the server answers or drops
mutated frames without dying, and a well-behaved client on another connection keeps
being served throughout.
"""

from __future__ import annotations

import contextlib
import random
import socket
import struct
import time

import pytest
from conftest import run_in

from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AmsAddr,
    AmsPacket,
    Command,
    Framer,
    PayloadError,
    StreamError,
)
from geo_server.transports.ads.server import AdsOptions, AdsServer

SERVER = AmsAddr("127.0.0.1.1.1", 551)
CLIENT = AmsAddr("10.0.0.1.1.1", 30000)
GEO = 0x120300


#: symbol names, real and not (the symbol services by name, docs/design.md §9)
NAMES = [b"GEO.X.TEMPC.coefficient\0", b"geo.c.sim.homed", b"GEO.SIM.last_error\0", b"LREAL\0",
         b"GEO.Q.TEMPC.coefficient\0", b"\xff\xfe\0", b"", b"A" * 300]  # fmt: skip
SYMBOL_GROUPS = [0xF003, 0xF004, 0xF009, 0xF011]
SERVICE_READS = [0xF005, 0xF008, 0xF00B, 0xF00C, 0xF00E, 0xF00F, 0xF100]


def tooling_frame(rng: random.Random, invoke: int) -> bytes:
    """Router commands, the system port and the symbol services."""
    kind = rng.randrange(5)
    if kind == 0:
        command = rng.choice([0x0001, 0x1000, 0x1001, 0x1002])
        return codec.router_frame(
            command, bytes(rng.randrange(256) for _ in range(rng.choice([0, 2, 4])))
        )
    if kind == 1:
        data = codec.read_write_request(
            rng.choice(SYMBOL_GROUPS), 0, rng.choice([0, 4, 8, 0xFFFF]), rng.choice(NAMES)
        )
        return codec.request_frame(SERVER, CLIENT, Command.READ_WRITE, data, invoke)
    if kind == 2:
        data = codec.read_request(
            rng.choice(SERVICE_READS), rng.randrange(4), rng.choice([0, 1, 4, 8, 24, 64, 1 << 20])
        )
        return codec.request_frame(SERVER, CLIENT, Command.READ, data, invoke)
    if kind == 3:
        ig = rng.choice([0xF005, 0xF006])
        data = codec.write_request(
            ig, rng.randrange(4), bytes(rng.randrange(256) for _ in range(rng.choice([0, 4, 8])))
        )
        return codec.request_frame(SERVER, CLIENT, Command.WRITE, data, invoke)
    system = AmsAddr(SERVER.netid, 10000)
    cmd = rng.choice(
        [
            Command.READ_STATE,
            Command.READ_DEVICE_INFO,
            Command.WRITE_CONTROL,
            Command.READ,
            Command.ADD_DEVICE_NOTIFICATION,
        ]
    )
    data = bytes(rng.randrange(256) for _ in range(rng.choice([0, 8, 12, 40])))
    return codec.request_frame(system, CLIENT, cmd, data, invoke)


def valid_frames(rng: random.Random, n: int) -> list[bytes]:
    out = []
    for i in range(n):
        kind = rng.randrange(7)
        if kind == 6:
            out.append(tooling_frame(rng, i + 1))
            continue
        if kind == 0:
            data = codec.read_request(GEO, (rng.randrange(1, 6) << 16) | 0x43, rng.choice([4, 8]))
            cmd = Command.READ
        elif kind == 1:
            data = codec.write_request(GEO, 0x10044, struct.pack("<i", rng.randrange(-99, 99)))
            cmd = Command.WRITE
        elif kind == 2:
            cmd, data = Command.READ_STATE, b""
        elif kind == 3:
            items = [(GEO, (a << 16) | 0x42, 4) for a in range(1, rng.randrange(2, 6))]
            data = codec.read_write_request(
                0xF080, len(items), 8 * len(items), codec.sum_read_request(items)
            )
            cmd = Command.READ_WRITE
        elif kind == 4:
            cmd, data = Command.READ_DEVICE_INFO, b""
        else:
            cmd, data = rng.randrange(0x20, 0x40), bytes(rng.randrange(256) for _ in range(8))
        out.append(codec.request_frame(SERVER, CLIENT, cmd, data, i + 1))
    return out


def mutate(rng: random.Random, frame: bytes) -> bytes:
    if frame[:2] != b"\0\0":  # a router command: no AMS header to mutate
        return frame
    b = bytearray(frame)
    how = rng.randrange(5)
    if how == 0 and len(b) > 6:  # flip bytes after the AMS/TCP header (framing survives)
        for _ in range(rng.randrange(1, 6)):
            b[rng.randrange(6, len(b))] = rng.randrange(256)
    elif how == 1:  # truncate the ADS data but keep lengths consistent
        cut = rng.randrange(0, max(1, len(b) - 38))
        data = bytes(b[38 : 38 + cut])
        h = codec.AmsHeader.unpack(bytes(b[6:38]))
        return codec.encode_frame(h, data)
    elif how == 2:  # lie in the AMS data length
        struct.pack_into("<I", b, 6 + 20, rng.randrange(1 << 32))
    elif how == 3:  # random AMS port / command / flags
        struct.pack_into("<H", b, 6 + 6, rng.randrange(1 << 16))
        struct.pack_into("<H", b, 6 + 16, rng.randrange(16))
        struct.pack_into("<H", b, 6 + 18, rng.randrange(1 << 16))
    return bytes(b)


@pytest.mark.parametrize("seed", range(5))
def test_framer_random_bytes_never_raise(seed: int) -> None:
    rng = random.Random(seed)
    for _ in range(300):
        f = Framer(max_frame=4096)
        blob = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 200)))
        pos = 0
        while pos < len(blob):
            step = rng.randrange(1, 40)
            for ev in f.feed(blob[pos : pos + step]):
                if isinstance(ev, AmsPacket):
                    with contextlib.suppress(PayloadError):
                        codec.parse_request(ev)
            pos += step
        assert f.failed is not None or f.buffered <= len(blob)


@pytest.mark.parametrize("seed", range(5))
def test_framer_recovers_every_frame_with_intact_framing(seed: int) -> None:
    """Mutations that keep the AMS/TCP header intact never cost a following frame."""
    rng = random.Random(100 + seed)
    frames = valid_frames(rng, 200)
    stream = b""
    expect = []
    for fr in frames:
        m = mutate(rng, fr)
        stream += m
        # what survives untouched must come out untouched
        if m == fr and fr[:2] == b"\0\0":
            expect.append(fr)
    f = Framer()
    events = []
    pos = 0
    while pos < len(stream):
        step = rng.randrange(1, 300)
        events += f.feed(stream[pos : pos + step])
        pos += step
    assert not any(isinstance(e, StreamError) for e in events)
    got = [codec.encode_frame(e.header, e.data) for e in events if isinstance(e, AmsPacket)]
    for fr in expect:
        assert fr in got
    for e in events:
        if isinstance(e, AmsPacket):
            try:
                codec.parse_request(e)
            except PayloadError as exc:
                assert exc.code == 0x705


@pytest.mark.parametrize("seed", [7, 11])
def test_server_survives_mutated_and_random_traffic(loop_thread, lists_copy, seed: int) -> None:
    # a private copy of the lists: a mutated write could in principle hit SIM::save
    service = ObjectService(Machine(load_machine(lists_copy), cycle_s=0.001, homed=True))
    srv = AdsServer(service, AdsOptions(port=0, max_frame=64 * 1024))
    run_in(loop_thread, srv.start())
    rng = random.Random(seed)
    good = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
    good_framer = Framer()

    def good_read(invoke: int) -> None:
        good.sendall(
            codec.request_frame(
                SERVER, CLIENT, Command.READ, codec.read_request(GEO, 0x10043, 8), invoke
            )
        )
        while True:
            pkts = [e for e in good_framer.feed(good.recv(65536)) if isinstance(e, AmsPacket)]
            if pkts:
                assert pkts[0].header.invoke_id == invoke
                assert codec.parse_read_response(pkts[0].data) == (0, service.read(GEO, 0x10043))
                return

    try:
        for round_ in range(30):
            bad = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
            try:
                frames = [mutate(rng, fr) for fr in valid_frames(rng, 20)]
                if round_ % 3 == 0:  # and some raw noise, which may end the connection
                    frames.insert(
                        rng.randrange(len(frames)), bytes(rng.randrange(256) for _ in range(50))
                    )
                blob = b"".join(frames)
                pos = 0
                while pos < len(blob):
                    step = rng.randrange(1, 500)
                    try:
                        bad.sendall(blob[pos : pos + step])
                    except (BrokenPipeError, ConnectionResetError):
                        break
                    pos += step
                # drain until the server has dealt with everything and closed
                with contextlib.suppress(OSError):
                    bad.shutdown(socket.SHUT_WR)
                    while bad.recv(65536):
                        pass
            finally:
                bad.close()
            good_read(round_ + 1)
        assert srv.stats.requests > 0
    finally:
        good.close()
        run_in(loop_thread, srv.close())


@pytest.mark.parametrize("seed", range(3))
def test_udp_parse_random_and_mutated_datagrams(seed: int) -> None:
    """`discovery.answer` only ever raises `UdpError`."""
    from geo_server.transports.ads import discovery

    rng = random.Random(300 + seed)
    valid = struct.pack("<III6sHI", 0x71146603, 1, 1, bytes(6), 10000, 0)
    for _ in range(2000):
        if rng.random() < 0.5:
            d = bytearray(valid + bytes(rng.randrange(256) for _ in range(rng.randrange(40))))
            for _ in range(rng.randrange(1, 4)):
                d[rng.randrange(len(d))] = rng.randrange(256)
            data = bytes(d)
        else:
            data = bytes(rng.randrange(256) for _ in range(rng.randrange(60)))
        with contextlib.suppress(discovery.UdpError):
            discovery.answer(data, "1.2.3.4.1.1", "h", (1, 2, 3))


def test_udp_port_survives_garbage(loop_thread) -> None:
    from geo_server.listfile import load_machine as _load
    from geo_server.paths import data_dir

    service = ObjectService(Machine(_load(data_dir("lists") / "hochlauf.lis"), homed=True))
    srv = AdsServer(service, AdsOptions(port=0, udp_port=0))
    run_in(loop_thread, srv.start())
    rng = random.Random(5)
    try:
        port = srv.udp_port
        assert port
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for i in range(300):
                junk = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 3000)))
                s.sendto(junk, ("127.0.0.1", port))
                if i % 20 == 19:
                    time.sleep(0.01)  # UDP: a full receive buffer would drop datagrams
            s.settimeout(1)
            request = struct.pack("<III6sHI", 0x71146603, 9, 1, bytes(6), 10000, 0)
            reply = b""
            for _ in range(5):  # a datagram may still be lost: ask again
                s.sendto(request, ("127.0.0.1", port))
                with contextlib.suppress(TimeoutError):
                    while True:  # garbage that happened to be a request is answered too
                        reply, _ = s.recvfrom(4096)
                        if struct.unpack_from("<I", reply, 4)[0] == 9:
                            break
                    break
            assert struct.unpack_from("<I", reply, 4)[0] == 9
        assert srv.stats.udp_dropped >= 200
    finally:
        run_in(loop_thread, srv.close())
