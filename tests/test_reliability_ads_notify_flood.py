"""A notification flood against the complete server.

One geo-server in this process (real-time 1 ms GEO cycle, Zenoh, Modbus and ADS on
ephemeral loopback ports, default ADS options). Flood connections register as many
notifications as the server grants — one connection beyond its own cap, others beyond
the server's total cap — all due every cycle, and read every notification frame. Readers
on all three transports run meanwhile. Asserted: exactly the caps are granted (0x716
beyond), every read on every transport succeeds within the client timeout, every
granted registration delivers samples, and closing the flood frees every registration.

Bounds: the registrations are the caps (550 by default, pipelined on 3 connections), the
flood runs for `FLOOD_CYCLES` GEO cycles (at most `FLOOD_SECONDS`), every socket has a
timeout.
"""

from __future__ import annotations

import math
import selectors
import socket
import threading
import time
from collections import Counter

import pytest
from robust.harness import TIMEOUT, FullServer, Reader

from geo_server.dictionary import load_dictionary
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AmsAddr,
    AmsPacket,
    Command,
    TransMode,
)

FLOOD_CYCLES = 1500  # GEO cycles the readers run while the flood is registered
FLOOD_SECONDS = 30.0  # … but at most this long
EXTRA = 10  # registrations each flood connection asks for beyond what it can get
SERVER = AmsAddr("127.0.0.1.1.1", 551)


def addresses(axes: int) -> list[tuple[int, int, int]]:
    """Every readable value address (IG, IO, length) of a machine with `axes` axes."""
    out = []
    for obj in load_dictionary().objects:
        if obj.readable:
            for a in range(1, axes + 1) if obj.scope == "axis" else [0]:
                out.append((obj.index_group, obj.index_offset(a), obj.length))
    return out


class FloodConnection:
    """A raw AMS/TCP client that registers notifications in one pipelined burst."""

    def __init__(self, port: int, n: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.source = AmsAddr(f"10.66.0.{n + 1}.1.1", 30000 + n)
        self.framer = codec.Framer()
        self.codes: list[int] = []
        self.handles: list[int] = []
        self.samples: Counter[int] = Counter()

    def register(self, addrs: list[tuple[int, int, int]], count: int, offset: int) -> None:
        frames = []
        for i in range(count):
            ig, io, length = addrs[(offset + i) % len(addrs)]
            # every 10th cyclic every 10 ms, the others on change checked every cycle
            if i % 10 == 0:
                data = codec.add_notification_request(
                    ig, io, length, TransMode.SERVERCYCLE, 0, 100_000
                )
            else:
                data = codec.add_notification_request(ig, io, length, TransMode.SERVERONCHA, 0, 1)
            frames.append(
                codec.request_frame(
                    SERVER, self.source, Command.ADD_DEVICE_NOTIFICATION, data, i + 1
                )
            )
        self.sock.sendall(b"".join(frames))
        while len(self.codes) < count:
            data = self.sock.recv(1 << 16)
            assert data, "the server closed a flood connection"
            self._feed(data)

    def _feed(self, data: bytes) -> None:
        for ev in self.framer.feed(data):
            assert isinstance(ev, AmsPacket), ev
            if ev.header.command == Command.DEVICE_NOTIFICATION:
                for stamp in codec.parse_device_notification(ev.data):
                    self.samples.update(s.handle for s in stamp.samples)
            else:
                assert ev.header.command == Command.ADD_DEVICE_NOTIFICATION
                code, handle = codec.parse_add_notification_response(ev.data)
                self.codes.append(code)
                if code == 0:
                    self.handles.append(handle)

    def drain(self) -> bool:
        """Read what is there (non-blocking); False once the server closed."""
        try:
            data = self.sock.recv(1 << 18, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return True
        if not data:
            return False
        self._feed(data)
        return True


class Drainer:
    """A thread reading every flood connection until stopped (so no frame is dropped)."""

    def __init__(self, conns: list[FloodConnection]) -> None:
        self.conns = conns
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="flood-drain", daemon=True)

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        for c in self.conns:
            sel.register(c.sock, selectors.EVENT_READ, c)
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(0.05):
                    if not key.data.drain():
                        sel.unregister(key.fileobj)
        except BaseException as exc:  # asserted by the test
            self.error = exc
        finally:
            sel.close()

    def __enter__(self) -> Drainer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(TIMEOUT)


@pytest.fixture
def full(loop_thread, lists_copy):
    with FullServer(loop_thread, lists_copy) as srv:
        yield srv


@pytest.mark.slow
def test_notification_flood_is_capped_and_every_transport_keeps_answering(full) -> None:
    ads = full.ads
    assert ads is not None
    per, total = ads.options.max_notifications, ads.options.max_notifications_total
    addrs = addresses(len(full.service.info.axes))
    readers = [Reader(full, via).start() for via in ("ads", "modbus", "zenoh")]
    n_conns = math.ceil(total / per) + 1  # enough to hit the total cap, and one more
    conns = [FloodConnection(ads.port, n) for n in range(n_conns)]
    try:
        for n, c in enumerate(conns):
            c.register(addrs, per + EXTRA, n * per)
        granted = [c.codes.count(0) for c in conns]
        # each connection gets at most its own cap, all of them together the total cap;
        # everything beyond either is 0x716 (ADSERR_DEVICE_NOMOREHDLS), nothing else
        assert all(g <= per for g in granted), granted
        assert sum(granted) == total, granted
        assert granted[0] == per and conns[0].codes[per:] == [0x716] * EXTRA
        assert granted[-1] == 0 and set(conns[-1].codes) == {0x716}
        assert all(set(c.codes) <= {0, 0x716} for c in conns)
        assert len(ads.notifications) == total

        with Drainer(conns) as drainer:
            c0, t0 = full.cycle, time.monotonic()
            while full.cycle < c0 + FLOOD_CYCLES and time.monotonic() < t0 + FLOOD_SECONDS:
                time.sleep(0.05)
                assert all(not r.errors for r in readers), [r.errors for r in readers]
            assert full.cycle >= c0 + FLOOD_CYCLES, "the GEO cycle stalled under the flood"
            requests_before = [r.requests for r in readers]
            time.sleep(0.3)  # and the readers still get answers at the end
        assert drainer.error is None, drainer.error
    finally:
        for r in readers:
            r.stop()
    for r in readers:
        assert not r.errors, (r.via, r.errors[:3])
    assert all(r.requests > b for r, b in zip(readers, requests_before, strict=True)), [
        (r.via, r.requests) for r in readers
    ]
    # every granted registration delivered samples (on-change: at least its first one)
    for c in conns:
        missing = [h for h in c.handles if c.samples[h] == 0]
        assert not missing, f"{len(missing)} of {len(c.handles)} registrations sent nothing"
    assert ads.stats.notifications_dropped == 0

    for c in conns:
        c.sock.close()
    deadline = time.monotonic() + TIMEOUT
    while len(ads.notifications) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert len(ads.notifications) == 0
