"""Notification sampling yields the event loop.

A sampling pass that would take longer than `AdsOptions.sample_budget` continues in a
later loop iteration, so whatever else is queued on the loop (requests of every
transport) runs in between; the rest of the pass still sends the values and the
timestamp of the cycle it was due at, and the cycles that ran meanwhile are sampled
after it, each in its turn. With a budget of 0 every slice is one small step,
which makes the interleaving deterministic: a coroutine queued behind the cycle's
hand-off runs after the first slice. The machine is stepped by the test.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import time
from collections import defaultdict

import pytest
from conftest import run_in

from geo_server import access
from geo_server.dictionary import load_dictionary
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AmsAddr,
    AmsPacket,
    Command,
    Framer,
    TransMode,
)
from geo_server.transports.ads.server import AdsOptions, AdsServer

TIMEOUT = 5.0
SIM = 0x12F300
CYCLE_COUNT_IO = load_dictionary().by_name("SIM::cycle_count").id  # machine object, axis 0
SERVER = AmsAddr("127.0.0.1.1.1", 551)
CLIENT = AmsAddr("10.5.5.5.1.1", 32100)
N = 100  # registrations: several slices of the sampling pass


@pytest.fixture
def ads(loop_thread, service):
    srv = AdsServer(service, AdsOptions(port=0, sample_budget=0.0))
    run_in(loop_thread, srv.start())
    yield srv
    run_in(loop_thread, srv.close())


def test_a_long_pass_yields_to_the_loop_and_keeps_its_cycle(
    ads, service, machine, loop_thread
) -> None:
    sock = socket.create_connection(("127.0.0.1", ads.port), timeout=TIMEOUT)
    framer = Framer()
    try:
        add = codec.add_notification_request(SIM, CYCLE_COUNT_IO, 4, TransMode.SERVERCYCLE, 0, 1)
        sock.sendall(
            b"".join(
                codec.request_frame(SERVER, CLIENT, Command.ADD_DEVICE_NOTIFICATION, add, i)
                for i in range(N)
            )
        )
        handles = []
        while len(handles) < N:
            for ev in framer.feed(sock.recv(65536)):
                assert isinstance(ev, AmsPacket)
                code, handle = codec.parse_add_notification_response(ev.data)
                assert code == 0
                handles.append(handle)
        seen: dict = {}

        async def probe() -> None:
            # The cycle runs here, on the loop's thread, so nothing of the loop runs
            # between it and the iterations counted below.
            seen["c1"] = access.step(service, 1).cycle  # every registration due: one hand-off
            # One loop iteration runs one slice (each slice queues the next with
            # call_soon): wait, one iteration at a time, until the pass has begun; it
            # must then still be unfinished (N registrations take several slices).
            for _ in range(100):
                if ads.stats.sampling_passes:
                    break
                await asyncio.sleep(0)
            seen["pass_unfinished"] = ads.sampler._pass is not None
            seen["sent"] = ads.stats.notifications_sent
            seen["c6"] = access.step(service, 5).cycle  # the cycle moves on meanwhile

        run_in(loop_thread, probe())
        c1 = seen["c1"]
        assert seen["pass_unfinished"], "the whole pass ran in one loop callback"
        assert 0 < seen["sent"] < N

        # all N samples of the first pass carry cycle c1's value and its time stamp;
        # the cycles that ran meanwhile are each sampled in their turn (late, never lost,
        # none skipped), every sample with its own cycle's value and stamp
        cycles = list(range(c1, seen["c6"] + 1))
        by_value: dict[int, list[tuple[int, int]]] = defaultdict(list)
        deadline = time.monotonic() + TIMEOUT
        while (
            sum(len(v) for v in by_value.values()) < len(cycles) * N and time.monotonic() < deadline
        ):
            for ev in framer.feed(sock.recv(65536)):
                assert isinstance(ev, AmsPacket)
                assert ev.header.command == Command.DEVICE_NOTIFICATION
                for stamp in codec.parse_device_notification(ev.data):
                    for s in stamp.samples:
                        (value,) = struct.unpack("<I", s.data)
                        by_value[value].append((s.handle, stamp.timestamp))
        assert sorted(by_value) == cycles
        epoch = machine.epoch  # FILETIME of cycle 0; 1 ms = 10 000 ticks
        for value in by_value:
            samples = by_value[value]
            assert sorted(h for h, _ts in samples) == sorted(handles)  # once per handle
            assert {ts for _h, ts in samples} == {epoch + value * 10_000}  # its cycle's
        assert ads.stats.sampling_slices >= 2
        run_in(loop_thread, asyncio.sleep(0.05))
        sock.settimeout(0.2)
        with pytest.raises(TimeoutError):
            sock.recv(65536)  # nothing more: no cycle was sampled twice
    finally:
        sock.close()
