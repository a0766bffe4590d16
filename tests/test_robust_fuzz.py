"""Bounded fuzzing of every transport against a server whose GEO cycle runs in real time.

`tests/test_modbus_fuzz.py` and `tests/test_ads_fuzz.py` already fuzz the Modbus decoder
and the ADS codec/server; what they do not show is that, *while* the junk arrives, other
clients on all three transports keep being answered with correct values and the GEO cycle
keeps running. Here each test fuzzes one transport with a fixed seed and a fixed number
of cases while three `Checker` threads (one per transport, each owning one object of
axis 4) write, read back and compare, and read the cycle count (it must keep growing).
The fuzzers never address a writable object of axis 4 or the machine commands, so every
mismatch a checker sees is a real failure.
"""

from __future__ import annotations

import json
import random
import socket
import struct
import time

import pytest
import zenoh
from robust.harness import CHECKER_AXIS, TIMEOUT, Checker, FullServer

from geo_server import access
from geo_server.client.zenoh_client import client_config
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsAddr, Command

GEO = 0x120300
SIM = 0x12F300


@pytest.fixture
def full(loop_thread, lists_copy):
    # a private copy of the lists: nothing a fuzzer does can touch the shipped ones
    with FullServer(loop_thread, lists_copy) as srv:
        yield srv


def run_with_checkers(srv: FullServer, fuzz) -> dict:
    """Run `fuzz()` while a checker per transport keeps asking; assert they all passed."""
    checkers = [Checker(srv, via).start() for via in ("zenoh", "modbus", "ads")]
    cycle0 = srv.cycle
    t0 = time.monotonic()
    try:
        stats = fuzz()
    finally:
        for c in checkers:
            c.stop()
    elapsed = time.monotonic() - t0
    for c in checkers:
        assert not c.errors, (c.via, c.errors[:5])
        assert c.rounds >= 5, (c.via, c.rounds)  # answered throughout, not once
    # the cycle kept running: at least a quarter of the nominal 1 kHz (generous)
    assert srv.cycle - cycle0 >= 0.25 * elapsed / srv.machine.cycle_s, (srv.cycle, cycle0)
    assert srv.scheduler.running and srv.scheduler.cycle_errors == 0
    # the fuzzed transport did not change what the checkers own
    for c in checkers:
        assert access.read_name(srv.service, c.name, CHECKER_AXIS) == c.value(c.rounds)
    return stats


# ---------------------------------------------------------------------------- Zenoh

ZENOH_CASES = 400
HUGE = 1024 * 1024  # 1 MiB, far above the server's 64 KiB payload limit


def zenoh_cases(rng: random.Random, m: str) -> list[tuple[str, bytes | None]]:
    """(key, payload) pairs: odd keys under cnc/<m>/**, garbage payloads."""
    fields = ["coefficient", "offset_0", "position_0", "activated", "actual_offset", "x", ""]
    axes = ["1", "2", "3", "0", "5", "-1", "65536", "99999999999999999999", "0x1", "one", "*"]
    keys = [
        f"cnc/{m}/axis/{{a}}/tempc/{{f}}",
        f"cnc/{m}/axis/{{a}}/bc/actual_backlash",
        f"cnc/{m}/sim/axis/{{a}}/{{f}}",
        f"cnc/{m}/sim/machine/{{f}}",
        f"cnc/{m}/ads/551/0x120300/0x{{a}}0043",
        f"cnc/{m}/ads/{{p}}/{{ig}}/{{io}}",
        f"cnc/{m}/axis/{{a}}/tempc/{{f}}/extra/chunks",
        f"cnc/{m}/axis/{{a}}",
        f"cnc/{m}/nc",
        f"cnc/{m}/status",
        f"cnc/{m}/errors",
        f"cnc/{m}/cmd/nothing",
        f"cnc/{m}/**",
        f"cnc/{m}/*/{{a}}/**",
        f"cnc/{m}/axis/$*/tempc/{{f}}",
        f"cnc/{m}/axis/{{a}}/tempc/*",
        f"cnc/{m}/" + "x/" * 200 + "y",
        f"cnc/{m}/axis/{{a}}/tempc/coefficient\u00e9\u4e2d",
    ]
    ports = ["551", "552", "0", "-1", "65536", "abc", "5" * 5000]
    groups = ["0x120300", "0x120400", "0x12f300", "0x0", "-0x1", "0xffffffffffffffff", "zz", ""]
    offsets = ["0x10043", "0x40044", "0x10099", "0x0", "0x-1", "0x1" + "0" * 40, "0x"]

    def payload() -> bytes | None:
        kind = rng.randrange(12)
        if kind == 0:
            return None  # a read
        if kind == 1:
            return rng.randbytes(rng.randrange(0, 64))  # binary junk
        if kind == 2:  # garbage JSON
            return rng.choice(
                [b"{", b"}", b"[", b'{"value":', b'{"valu": 1}', b"nul", b"1e99999", b"-", b'"']
            )
        if kind == 3:  # JSON of the wrong shape
            return json.dumps(
                rng.choice([[1, 2], {"value": [1]}, {"value": None}, None, "text", {}, True])
            ).encode()
        if kind == 4:  # wrong byte counts for raw keys
            return bytes(rng.randrange(256) for _ in range(rng.choice([0, 1, 2, 3, 5, 7, 9, 300])))
        if kind == 5:  # deeply nested JSON
            depth = rng.choice([100, 5_000, 30_000])
            return b"[" * depth + b"]" * depth
        if kind == 6:  # just above the limit, or far above it (rarely: it is slow)
            return b"7" * rng.choice(
                [64 * 1024 + 1, 70_000, HUGE if rng.random() < 0.2 else 80_000]
            )
        if kind == 7:  # invalid UTF-8 / NUL bytes
            return b"\xff\xfe\x00" + rng.randbytes(8)
        if kind == 8:  # numbers out of range / not finite
            return rng.choice([b"1e308", b"-1e308", b"NaN", b"Infinity", b"2147483648", b"1e-400"])
        if kind == 9:  # NC junk
            return rng.choice([b"G05 X1", b"N10 $GOTO N10", b"\x00\x01", b"X[COMP ON BOGUS]", b";"])
        return str(rng.randrange(-(1 << 40), 1 << 40)).encode()  # a plain (maybe valid) number

    out = []
    for _ in range(ZENOH_CASES):
        key = rng.choice(keys).format(
            a=rng.choice(axes),
            f=rng.choice(fields),
            p=rng.choice(ports),
            ig=rng.choice(groups),
            io=rng.choice(offsets),
        )
        out.append((key, payload()))
    return out


def axis4_write(key: str, payload: bytes | None, m: str) -> bool:
    """Would this case validly write an object of axis 4 (a checker's) or run a command?"""
    if payload is None:
        return False
    return (
        key.startswith((f"cnc/{m}/axis/4/", f"cnc/{m}/sim/axis/4/", f"cnc/{m}/cmd/"))
        or "0x40043" in key
        or "0x40044" in key
        or "0x40045" in key
    )


@pytest.mark.slow
def test_zenoh_fuzz_keys_and_payloads(full):
    m = full.machine_name
    rng = random.Random(0x7447)
    cases = [(k, p) for k, p in zenoh_cases(rng, m) if not axis4_write(k, p, m)]
    tally = {"ok": 0, "err": 0, "none": 0, "refused_by_zenoh": 0, "codes": {}}

    def fuzz() -> dict:
        s = zenoh.open(client_config([full.zenoh_endpoint]))
        try:
            for key, payload in cases:
                kwargs: dict = {"timeout": TIMEOUT}
                if payload is not None:
                    kwargs["payload"] = payload
                t0 = time.monotonic()
                try:
                    replies = list(s.get(key, **kwargs))
                except zenoh.ZError:
                    tally["refused_by_zenoh"] += 1  # not a valid key expression at all
                    continue
                # a concrete key always gets a reply; a wildcard may match nothing, but
                # then the server still finishes the query at once (no timeout)
                wildcard = "*" in key
                if (not replies and not wildcard) or time.monotonic() - t0 >= TIMEOUT - 0.5:
                    tally["none"] += 1
                for r in replies:
                    if r.ok is not None:
                        tally["ok"] += 1
                    else:
                        tally["err"] += 1
                        body = json.loads(r.err.payload.to_bytes())  # always JSON
                        code = body["ads_error"]
                        tally["codes"][code] = tally["codes"].get(code, 0) + 1
        finally:
            s.close()
        return tally

    run_with_checkers(full, fuzz)
    # every case reached the server and was answered (no query is left unanswered)
    assert tally["none"] == 0, tally
    assert tally["err"] > 100 and tally["ok"] > 10, tally
    # an internal error (0x700) means an unexpected exception in the server
    assert 0x700 not in tally["codes"], tally
    assert full.zenoh is not None and full.zenoh.queries >= len(cases) - tally["refused_by_zenoh"]


def test_zenoh_deeply_nested_json_is_invalid_data(full):
    """Found by the fuzzer: `json.loads` raises RecursionError (not JSONDecodeError) for
    deeply nested input; the server must answer 0x706 like for any other bad JSON."""
    with full.client("zenoh") as c:
        for depth in (30_000, 2_000):  # 60 000 bytes: within the 64 KiB limit
            nested = b"[" * depth + b"]" * depth
            replies = list(
                c.session.get(
                    f"cnc/{full.machine_name}/axis/1/tempc/coefficient",
                    payload=nested,
                    timeout=TIMEOUT,
                )
            )
            assert len(replies) == 1 and replies[0].err is not None
            assert json.loads(replies[0].err.payload.to_bytes())["ads_error"] == 0x706
        assert c.read("TEMPC::coefficient", 1) == 4000.0


# ---------------------------------------------------------------------------- Modbus

MODBUS_RANDOM = 300
MODBUS_MUTATED = 300
UNITS = [0, 1, 2, 3, 9, 77, 255]  # never 4: the checkers' axis


def mbap(pdu: bytes, unit: int, tid: int, pid: int = 0, length: int | None = None) -> bytes:
    n = len(pdu) + 1 if length is None else length
    return struct.pack(">HHHB", tid & 0xFFFF, pid, n & 0xFFFF, unit) + pdu


def valid_modbus(rng: random.Random, tid: int) -> bytes:
    unit = rng.choice([1, 2, 3])
    kind = rng.randrange(6)
    if kind == 0:  # read TEMPC::coefficient (4 registers)
        pdu = struct.pack(">BHH", 3, 268, 4)
    elif kind == 1:
        pdu = struct.pack(">BHH", 4, 260, 20)
    elif kind == 2:  # write TEMPC::offset_0 (SGN32)
        pdu = struct.pack(">BHHBi", 16, 272, 2, 4, rng.randrange(-999, 999))
    elif kind == 3:
        pdu = struct.pack(">BHH", 1, 0x41, 1)
    elif kind == 4:  # FC 43/14 device identification
        pdu = bytes([43, 14, 1, 0])
    else:
        pdu = struct.pack(">BHH", 5, 0x41, 0xFF00)
    return mbap(pdu, unit, tid)


def mutate_modbus(rng: random.Random, adu: bytes) -> bytes:
    b = bytearray(adu)
    how = rng.randrange(6)
    if how == 0:  # flip PDU bytes
        for _ in range(rng.randrange(1, 4)):
            b[rng.randrange(7, len(b))] = rng.randrange(256)
    elif how == 1:  # truncate (the MBAP length now lies)
        b = b[: rng.randrange(1, len(b))]
    elif how == 2:  # MBAP length lies
        struct.pack_into(">H", b, 4, rng.choice([0, 1, 2, 255, 256, 0xFFFF]))
    elif how == 3:  # protocol id not Modbus
        struct.pack_into(">H", b, 2, rng.randrange(1, 0x10000))
    elif how == 4:  # a junk tail
        b += rng.randbytes(rng.randrange(1, 20))
    else:  # another (non-checker) unit
        b[6] = rng.choice(UNITS)
    if len(b) > 6 and b[6] == 4:
        b[6] = 1
    return bytes(b)


def is_command_write(adu: bytes) -> bool:
    """FC 6/16 on unit 0 at SIM::reload/SIM::save (0x4010…0x4017): skipped."""
    if len(adu) < 10 or adu[6] != 0 or adu[7] not in (6, 16):
        return False
    return 0x4008 <= struct.unpack(">H", adu[8:10])[0] <= 0x4017


@pytest.mark.slow
def test_modbus_fuzz_with_clients_on_every_transport(full):
    assert full.modbus is not None
    port = full.modbus.port
    rng = random.Random(0x5020)
    frames: list[bytes] = []
    fcs = [1, 2, 3, 4, 5, 6, 7, 8, 11, 15, 16, 17, 20, 22, 23, 24, 43, 0x80, 0]
    for i in range(MODBUS_RANDOM):
        pdu = bytes([rng.choice(fcs)]) + rng.randbytes(rng.randrange(0, 260))
        frames.append(mbap(pdu, rng.choice(UNITS), i))
    for i in range(MODBUS_MUTATED):
        frames.append(mutate_modbus(rng, valid_modbus(rng, 1000 + i)))
    frames = [f for f in frames if not is_command_write(f)]
    tally = {"replies": 0, "reconnects": 0}

    def connect() -> socket.socket:
        s = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
        s.settimeout(0.01)  # a late answer is read with the next frame: only liveness counts
        return s

    def fuzz() -> dict:
        s = connect()
        try:
            for i, f in enumerate(frames):
                try:
                    s.sendall(f)
                    if s.recv(4096):
                        tally["replies"] += 1
                except TimeoutError:
                    pass
                except OSError:
                    s.close()  # the server dropped us: allowed; go on with a new one
                    s = connect()
                    tally["reconnects"] += 1
                if i % 50 == 49:  # and a new connection now and then anyway
                    s.close()
                    s = connect()
        finally:
            s.close()
        return tally

    run_with_checkers(full, fuzz)
    assert tally["replies"] > 100, tally


# ---------------------------------------------------------------------------- ADS

ADS_ROUNDS = 40
ADS_FRAMES = 26
SERVER = AmsAddr("127.0.0.1.1.1", 551)
CLIENT = AmsAddr("10.9.9.9.1.1", 31000)
#: Byte patterns a frame must not contain: an axis-4 writable offset (a checker's object)
#: or the emulator group (SIM::reload / SIM::save).
FORBIDDEN = [struct.pack("<I", (CHECKER_AXIS << 16) | i) for i in (0x41, 0x43, 0x44, 0x45)] + [
    struct.pack("<I", SIM)
]


def valid_ads(rng: random.Random, invoke: int) -> bytes:
    axis = rng.choice([1, 2, 3])
    kind = rng.randrange(7)
    if kind == 0:
        cmd, data = Command.READ, codec.read_request(GEO, (axis << 16) | 0x43, 8)
    elif kind == 1:
        value = struct.pack("<i", rng.randrange(-99, 99))
        cmd, data = Command.WRITE, codec.write_request(GEO, (axis << 16) | 0x44, value)
    elif kind == 2:
        items = [(GEO, (a << 16) | 0x42, 4) for a in (1, 2, 3)]
        req = codec.sum_read_request(items)
        cmd, data = Command.READ_WRITE, codec.read_write_request(0xF080, 3, 24, req)
    elif kind == 3:
        cmd, data = (
            Command.ADD_DEVICE_NOTIFICATION,
            codec.add_notification_request(GEO, (axis << 16) | 0x42, 4),
        )
    elif kind == 4:
        cmd, data = (
            Command.DELETE_DEVICE_NOTIFICATION,
            codec.delete_notification_request(rng.randrange(1, 50)),
        )
    elif kind == 5:
        cmd, data = Command.READ_STATE, b""
    else:
        cmd, data = rng.randrange(0, 0x30), rng.randbytes(rng.randrange(0, 40))
    return codec.request_frame(SERVER, CLIENT, cmd, data, invoke)


def mutate_ads(rng: random.Random, frame: bytes, keep_framing: bool) -> bytes:
    """A mutated frame; with `keep_framing` the AMS/TCP header stays intact (the server
    must answer or skip it and go on with the next frame), else anything goes (the
    server may close the connection)."""
    b = bytearray(frame)
    how = rng.randrange(4) if keep_framing else rng.randrange(4, 8)
    if how == 0:  # flip bytes behind the AMS/TCP header
        for _ in range(rng.randrange(1, 6)):
            b[rng.randrange(6, len(b))] = rng.randrange(256)
    elif how == 1:  # AMS data length lies
        struct.pack_into("<I", b, 26, rng.randrange(1 << 32))
    elif how == 2:  # target port, command, state flags
        struct.pack_into("<HHH", b, 12, rng.randrange(1 << 16), 0, 0)
        struct.pack_into("<HH", b, 22, rng.randrange(16), rng.randrange(1 << 16))
    elif how == 3:  # ADS data cut short, lengths consistent
        cut = rng.randrange(0, max(1, len(b) - 38))
        return codec.encode_frame(codec.AmsHeader.unpack(bytes(b[6:38])), bytes(b[38 : 38 + cut]))
    elif how == 4:  # AMS/TCP length lies
        struct.pack_into("<I", b, 2, rng.choice([0, 1, 31, 33, 200, 1 << 31]))
    elif how == 5:  # half a frame (the rest never comes on this connection)
        return bytes(b[: rng.randrange(1, len(b))])
    elif how == 6:  # a junk tail
        b += rng.randbytes(rng.randrange(1, 30))
    else:  # AMS/TCP reserved bytes (header kind) not 0
        b[0], b[1] = rng.randrange(256), rng.randrange(1, 256)
    return bytes(b)


def test_ads_fuzz_with_clients_on_every_transport(full):
    assert full.ads is not None
    port = full.ads.port
    rng = random.Random(0xADE)
    tally = {"frames": 0, "bytes_back": 0}

    def fuzz() -> dict:
        for round_ in range(ADS_ROUNDS):
            # 25 frames whose framing survives (some untouched), then one that may not
            frames = []
            while len(frames) < ADS_FRAMES:
                last = len(frames) == ADS_FRAMES - 1
                f = valid_ads(rng, round_ * 100 + len(frames))
                if last or rng.random() < 0.8:
                    f = mutate_ads(rng, f, keep_framing=not last)
                if last and round_ % 4 == 0:
                    f = rng.randbytes(rng.randrange(1, 80))  # or raw noise
                if not any(p in f for p in FORBIDDEN):
                    frames.append(f)
            blob = b"".join(frames)
            with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as s:
                s.settimeout(0.2)
                pos = 0
                try:
                    while pos < len(blob):
                        step = rng.randrange(1, 300)
                        s.sendall(blob[pos : pos + step])
                        pos += step
                    s.shutdown(socket.SHUT_WR)
                    while chunk := s.recv(65536):
                        tally["bytes_back"] += len(chunk)
                except (TimeoutError, OSError):
                    pass  # nothing more, or the server closed a framing failure: allowed
            tally["frames"] += len(frames)
        return tally

    run_with_checkers(full, fuzz)
    assert tally["bytes_back"] > 0, tally
    # most frames reached the dispatcher (a framing failure ends only its round)
    assert full.ads.stats.requests > ADS_ROUNDS * ADS_FRAMES // 2, full.ads.stats
