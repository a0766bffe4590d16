"""Repeated reads (docs/design.md §13, *Repeated reads*; `transports/ads/repeats.py`).

A Read a connection sends again is answered from the answer it kept while the machine
still shows the rest it was answered at, and never otherwise. The machine is the
exact engine of the default machine on a virtual clock (the cycle due is the test's to
choose); the connection is the asyncio protocol fed bytes, its answers kept by a
transport without a socket. Every expected value follows from the writes the test
makes (TEMPC::offset_0 of axis 1 is an SGN32 written here) or from the clock (the cycle
counter counts 1 ms cycles).
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Callable, Coroutine
from typing import Any

from support.fakes import VirtualClock, Wire

from geo_server.dictionary import load_dictionary
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.port import WriteObjects
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService, ServiceLimits
from geo_server.transports.ads import codec, repeats
from geo_server.transports.ads.codec import AmsAddr, Command
from geo_server.transports.ads.protocol import AdsConnection
from geo_server.transports.ads.server import AdsOptions, AdsServer

P = 1_000_000  # 1 ms in ns
TARGET = AmsAddr("127.0.0.1.1.1", 551)
SOURCE = AmsAddr("10.9.9.9.1.1", 30000)
VALBYHND, HNDBYNAME, RELEASEHND = 0xF005, 0xF003, 0xF006


class Rig:
    """A machine at rest with TEMPC::offset_0 of axis 1 at -250, its ADS server and one
    connection to it."""

    def __init__(self, requests_per_step: int = 16) -> None:
        self.vc = VirtualClock()
        self.m = Machine(load_machine(default_startup_list()), homed=True)
        self.sched = Scheduler(
            self.m, mode="realtime", engine="exact", clock=self.vc.clock, sleep=self.vc.sleep
        )
        # (a heartbeat counts as fresh for 30 s: a slow host cannot make a read catch up)
        self.svc = ObjectService(self.m, self.sched, ServiceLimits(stall_after=60.0))
        self.sched.drive()
        self.rest_with(-250)
        self.ads = AdsServer(self.svc, AdsOptions(port=0, requests_per_step=requests_per_step))
        self.wire = Wire()
        self.conn = AdsConnection(self.ads)
        self.invoke = 0

    def rest_with(self, offset: int) -> None:
        """Write TEMPC::offset_0 of axis 1 and let the machine come to rest (100 ms)."""
        self.m.submit(WriteObjects((("TEMPC::offset_0", 1, offset),)))
        self.vc.t += 100 * P
        assert self.svc.current().cycle == self.m.cycle
        assert self.sched.shows_rest()

    async def start(self) -> None:
        await self.ads.start()
        self.conn.connection_made(self.wire)

    def frame(self, command: int, data: bytes) -> bytes:
        self.invoke += 1
        return codec.request_frame(TARGET, SOURCE, command, data, self.invoke)

    def send(self, frame: bytes) -> None:
        self.conn.data_received(frame)

    def answers(self) -> list[codec.AmsPacket]:
        framer = codec.Framer()
        got = [e for w in self.wire.out for e in framer.feed(w) if isinstance(e, codec.AmsPacket)]
        self.wire.out.clear()
        return got

    def read(self, ig: int, io: int, length: int = 4) -> tuple[int, bytes]:
        """One Read, answered at once: (result, data)."""
        self.send(self.frame(Command.READ, codec.read_request(ig, io, length)))
        (answer,) = self.answers()
        assert answer.header.invoke_id == self.invoke
        return codec.parse_read_response(answer.data)

    @property
    def repeated(self) -> int:
        return self.ads.stats.repeated_reads


def run(test: Callable[[Rig], Coroutine[Any, Any, None]], **options: Any) -> None:
    async def main() -> None:
        rig = Rig(**options)
        await rig.start()
        try:
            await test(rig)
        finally:
            await rig.ads.close()

    asyncio.run(main())


D = load_dictionary()
_offset_0 = D.by_name("TEMPC::offset_0")
OFFSET_0 = (_offset_0.index_group, _offset_0.index_offset(1))


def test_a_read_sent_again_at_rest_is_answered_from_what_was_kept() -> None:
    """The second Read of the same object is answered from what the first kept: the
    same bytes but its own invoke id, nothing caught up even 5 s later. A write makes
    the next Read go the whole way (the value of the cycle due, then of the cycle that
    applied it); once the machine rests again, repeats are answered again."""

    async def test(rig: Rig) -> None:
        first = rig.frame(Command.READ, codec.read_request(*OFFSET_0, 4))
        rig.send(first)
        (a,) = rig.answers()
        again = first[:34] + struct.pack("<I", 77) + first[38:]
        rig.send(again)
        (b,) = rig.answers()
        assert codec.parse_read_response(a.data) == (0, struct.pack("<i", -250))
        assert rig.repeated == 1
        assert (
            b.header.invoke_id == 77
            and b.data == a.data
            and b.header == a.header._replace(invoke_id=77)
        )

        cycle, computed = rig.m.cycle, rig.sched.computed
        rig.vc.t += 5000 * P
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", -250))
        assert rig.repeated == 2
        assert (rig.m.cycle, rig.sched.computed) == (cycle, computed)  # nothing caught up

        rig.sched.submit(WriteObjects((("TEMPC::offset_0", 1, 125),)))  # the next cycle
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", -250))  # the cycle due: not yet
        rig.vc.t += P
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", 125))  # the cycle applying it
        assert rig.repeated == 2

        rig.vc.t += 100 * P
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", 125))
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", 125))
        assert rig.repeated == 3

    run(test)


def test_a_value_that_varies_at_rest_is_never_kept() -> None:
    """SIM::cycle_count counts cycles at rest too: each Read catches up and answers the
    cycle due, 5000 more after 5 s; nothing is kept for it."""
    count = D.by_name("SIM::cycle_count")
    address = (count.index_group, count.index_offset(0))

    async def test(rig: Rig) -> None:
        code, first = rig.read(*address)
        rig.vc.t += 5000 * P
        n = struct.unpack("<I", first)[0]
        assert code == 0 and rig.read(*address) == (0, struct.pack("<I", n + 5000))
        assert rig.repeated == 0 and rig.conn.repeats == {}

    run(test)


def test_a_read_by_a_handle_given_back_is_not_answered_from_what_was_kept() -> None:
    """A Read by symbol handle is kept like one by address; once the handle is given
    back, the same Read answers 0x710 (no such symbol handle), not the kept value."""

    async def test(rig: Rig) -> None:
        name = b"GEO.X.TEMPC.offset_0\0"
        rig.send(rig.frame(Command.READ_WRITE, codec.read_write_request(HNDBYNAME, 0, 4, name)))
        (created,) = rig.answers()
        code, raw = codec.parse_read_response(created.data)
        assert code == 0
        handle = struct.unpack("<I", raw)[0]
        assert rig.read(VALBYHND, handle) == (0, struct.pack("<i", -250))
        assert rig.read(VALBYHND, handle) == (0, struct.pack("<i", -250))
        assert rig.repeated == 1
        rig.send(rig.frame(Command.WRITE, codec.write_request(RELEASEHND, 0, raw)))
        (released,) = rig.answers()
        assert codec.parse_result(released.data) == 0
        assert rig.read(VALBYHND, handle) == (0x710, b"")
        assert rig.repeated == 1

    run(test)


def test_an_injected_fault_applies_to_a_read_sent_again() -> None:
    """With a fault injected for ADS reads, a Read sent again gets the fault (0x708), not
    the kept answer; once it is cleared, the kept answer is given again."""

    async def test(rig: Rig) -> None:
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", -250))
        fault = rig.svc.faults.inject("ads:error=0x708,ops=read")
        assert rig.read(*OFFSET_0) == (0x708, b"")
        rig.svc.faults.clear()
        assert fault is not None
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", -250))
        assert rig.repeated == 1

    run(test)


def test_reads_sent_again_count_towards_the_machines_turn() -> None:
    """`requests_per_step` = 4, and one Read served already in this step (a machine's
    count starts again in the step after it reached half the limit): of six Reads sent
    again in the same step three are answered at once, the other three wait, in order,
    for the next step as any request does."""

    async def test(rig: Rig) -> None:
        assert rig.read(*OFFSET_0) == (0, struct.pack("<i", -250))
        first = rig.invoke + 1
        for _ in range(6):
            rig.send(rig.frame(Command.READ, codec.read_request(*OFFSET_0, 4)))
        now = [a.header.invoke_id for a in rig.answers()]
        for _ in range(3):
            await asyncio.sleep(0)
        later = [a.header.invoke_id for a in rig.answers()]
        assert now == [first, first + 1, first + 2]
        assert later == [first + 3, first + 4, first + 5]
        assert rig.repeated == 3 and rig.ads.stats.deferred_requests == 1

    run(test, requests_per_step=4)


def test_a_read_in_pieces_and_the_answers_kept_are_bounded() -> None:
    """A Read that arrives in two pieces is framed as always (answered once, in full);
    a connection keeps at most `MAX_REPEATS` answers, however many sources it invents."""

    async def test(rig: Rig) -> None:
        frame = rig.frame(Command.READ, codec.read_request(*OFFSET_0, 4))
        rig.send(frame)
        rig.answers()
        again = rig.frame(Command.READ, codec.read_request(*OFFSET_0, 4))
        rig.send(again[:20])
        assert rig.answers() == []
        rig.send(again[20:])
        (a,) = rig.answers()
        assert a.header.invoke_id == rig.invoke
        assert codec.parse_read_response(a.data) == (0, struct.pack("<i", -250))
        for port in range(1000, 1000 + 3 * repeats.MAX_REPEATS):
            source = AmsAddr(SOURCE.netid, port)
            request = codec.read_request(*OFFSET_0, 4)
            rig.send(codec.request_frame(TARGET, source, Command.READ, request, port))
            (answer,) = rig.answers()
            assert codec.parse_read_response(answer.data) == (0, struct.pack("<i", -250))
            assert 0 < len(rig.conn.repeats) <= repeats.MAX_REPEATS
            await asyncio.sleep(0)

    run(test)


def test_a_frame_under_way_comes_first() -> None:
    """With part of a frame buffered, bytes that are a whole Read sent before belong to
    that frame (the stream is framed in order): they are not answered as a repeat."""

    async def test(rig: Rig) -> None:
        kept = rig.frame(Command.READ, codec.read_request(*OFFSET_0, 4))
        rig.send(kept)
        rig.answers()
        under_way = rig.frame(Command.READ, codec.read_request(*OFFSET_0, 4))
        rig.send(under_way[:20])
        again = kept[:34] + struct.pack("<I", 99) + kept[38:]
        rig.send(again)
        assert 99 not in [a.header.invoke_id for a in rig.answers()]
        assert rig.repeated == 0

    run(test)


def test_what_is_kept_never_keeps_a_snapshot_and_nothing_is_kept_while_moving() -> None:
    """Five rests, each after a write, each with a Read of its own (a read length of its
    own makes a request of its own): five answers kept, and once collected only the
    snapshot the machine shows is still alive among theirs (a connection holds bytes,
    not snapshots). A Read while a write is queued keeps nothing."""

    async def test(rig: Rig) -> None:
        for i in range(5):
            rig.rest_with(10 * i)
            assert rig.read(*OFFSET_0, length=4 + i) == (0, struct.pack("<i", 10 * i))
        assert len(rig.conn.repeats) == 5
        alive = [k.snapshot() for k in rig.conn.repeats.values()]
        assert [s is rig.m.snapshot for s in alive] == [False] * 4 + [True]
        assert alive[:4] == [None] * 4
        rig.sched.submit(WriteObjects((("TEMPC::offset_0", 1, 75),)))
        assert rig.read(*OFFSET_0, length=9) == (0, struct.pack("<i", 40))
        assert len(rig.conn.repeats) == 5

    run(test)
