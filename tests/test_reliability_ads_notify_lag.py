"""Notification sampling after the loop was held: every cycle caught up when a pass is
cheap (docs/design.md §13.1; `AdsOptions.sample_lag`).

A machine runs in real time (1 ms cycles on its own engine thread) with ADS alone; one
client watches SIM::cycle_count every cycle (its value is the cycle's number). The
event loop is then kept busy for 300 ms by a callback that sleeps, as a busy host or a
long request would: the engine goes on and hands about 300 snapshots over. Sampling one
registration costs microseconds a pass, so catching up 300 cycles takes far less than
`sample_lag`: the client receives every cycle, late, with no gap, and nothing is shed.

(Before, every snapshot older than `sample_lag` was skipped whatever the work to catch up:
a loop held 60 ms on a loaded host left gaps in cyclic streams, and the engine
differential test failed under load. Skipping is for when catching up would take longer
than `sample_lag`: hundreds of registrations, tests/test_reliability_ads_notify_flood.py.)
"""

from __future__ import annotations

import socket
import struct
import time

import pytest
from robust.harness import FullServer

from geo_server.dictionary import load_dictionary
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsAddr, AmsPacket, Command, Framer, TransMode
from geo_server.transports.ads.options import AdsOptions

TIMEOUT = 5.0
SIM = 0x12F300
CYCLE_COUNT_IO = load_dictionary().by_name("SIM::cycle_count").id  # machine object, axis 0
SERVER = AmsAddr("127.0.0.1.1.1", 551)
CLIENT = AmsAddr("10.5.5.7.1.1", 32100)
BUSY_S = 0.3  # the loop sleeps this long
LAG_S = 0.25  # AdsOptions.sample_lag (the default, set here so that the test says it)


@pytest.fixture
def full(loop_thread):
    with FullServer(
        loop_thread, zenoh=False, modbus=False, ads_options={"sample_lag": LAG_S}
    ) as srv:
        yield srv


class Watcher:
    """A raw AMS/TCP client with one notification of SIM::cycle_count every cycle."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
        self.framer = Framer()
        self.values: list[int] = []  # the counter of every sample, in arrival order
        add = codec.add_notification_request(SIM, CYCLE_COUNT_IO, 4, TransMode.SERVERCYCLE, 0, 1)
        self.sock.sendall(
            codec.request_frame(SERVER, CLIENT, Command.ADD_DEVICE_NOTIFICATION, add, 1)
        )
        self.code: int | None = None
        while self.code is None:
            self.read()
        assert self.code == 0

    def read(self) -> None:
        for ev in self.framer.feed(self.sock.recv(1 << 16)):
            assert isinstance(ev, AmsPacket)
            if ev.header.command == Command.ADD_DEVICE_NOTIFICATION:
                self.code, _handle = codec.parse_add_notification_response(ev.data)
                continue
            assert ev.header.command == Command.DEVICE_NOTIFICATION
            for stamp in codec.parse_device_notification(ev.data):
                self.values.extend(struct.unpack("<I", s.data)[0] for s in stamp.samples)

    def until(self, predicate) -> None:
        deadline = time.monotonic() + TIMEOUT
        while not predicate():
            assert time.monotonic() < deadline, self.values[-5:]
            self.read()


def test_a_loop_kept_busy_catches_up_every_cycle_when_a_pass_is_cheap(full) -> None:
    ads = full.ads
    assert ads is not None and ads.options.sample_lag == AdsOptions().sample_lag
    w = Watcher(ads.port)
    try:
        w.until(lambda: len(w.values) >= 20)  # sampling runs, one sample per cycle
        before = len(w.values)
        full.loop.call_soon_threadsafe(time.sleep, BUSY_S)
        # the samples go on once the loop is back, well past the busy stretch
        w.until(lambda: len(w.values) > before and w.values[-1] >= w.values[before] + 400)
    finally:
        w.sock.close()
    steps = [b - a for a, b in zip(w.values, w.values[1:], strict=False)]
    status = ads.service.status().get("ads_notifications")
    assert set(steps) == {1}, ([s for s in steps if s != 1], status)
    assert ads.stats.cycles_shed == 0
