"""The ADS interface (docs/design.md §9) on loopback: raw AMS/TCP frames and pyads as a real client.

The server runs on an ephemeral port in the `loop_thread`; the machine is stepped by the
test (deterministic) except where a running scheduler is the point. pyads (Beckhoff
AdsLib) keeps one route per NetId in the process, so every server gets its own NetId
(pyads 3.6.0, verified: one NetId <-> one endpoint per process).
"""

from __future__ import annotations

import asyncio
import ctypes
import itertools
import json
import queue
import socket
import struct
import threading
import time
from collections.abc import Iterator

import pyads
import pytest
from conftest import run_in
from pyads.errorcodes import ERROR_CODES
from support.fakes import Wire

from geo_server import access
from geo_server.client.ads_client import AdsClient, close_port_first
from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsError
from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AmsAddr,
    AmsPacket,
    Command,
    Framer,
    SumGroup,
)
from geo_server.transports.ads.server import AdsOptions, AdsServer

TIMEOUT = 5.0
D = load_dictionary()
GEO = 0x120300
COEFFICIENT = D.by_name("TEMPC::coefficient")
ACTUAL_OFFSET = D.by_name("TEMPC::actual_offset")
OFFSET_0 = D.by_name("TEMPC::offset_0")
PLCTYPE = {
    "BOOLEAN": pyads.PLCTYPE_BOOL,
    "UNS16": pyads.PLCTYPE_UINT,
    "UNS32": pyads.PLCTYPE_UDINT,
    "SGN32": pyads.PLCTYPE_DINT,
    "REAL64": pyads.PLCTYPE_LREAL,
    "STRING": pyads.PLCTYPE_STRING,
}
_netids = itertools.count(10)


def next_netid() -> str:
    n = next(_netids)
    return f"127.0.{n // 250}.{n % 250 + 1}.1.1"


def readable(group: str = "geo") -> list:
    return [o for o in D.group_objects(group) if o.readable]


# ---------------------------------------------------------------------- fixtures


def start_server(loop, service: ObjectService, **options) -> AdsServer:
    srv = AdsServer(service, AdsOptions(port=0, **options))
    run_in(loop, srv.start())
    return srv


@pytest.fixture
def ads(loop_thread, service) -> Iterator[AdsServer]:
    srv = start_server(loop_thread, service)
    yield srv
    run_in(loop_thread, srv.close())


@pytest.fixture
def plc(ads) -> Iterator[pyads.Connection]:
    conn = pyads.Connection(next_netid(), 551, ads.address)
    conn.open()
    conn.set_timeout(int(TIMEOUT * 1000))
    yield conn
    close_port_first(conn)  # safe even if a failed test left notifications behind


class Raw:
    """A bare AMS/TCP client: frames in, `AmsPacket`s out, a timeout on every recv."""

    source = AmsAddr("10.1.2.3.1.1", 32905)

    def __init__(self, port: int, netid: str = "127.0.0.1.1.1") -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.target = AmsAddr(netid, 551)
        self.framer = Framer()
        self.pending: list[AmsPacket] = []
        self.invoke = itertools.count(1)

    def close(self) -> None:
        self.sock.close()

    def frame(self, command: int, data: bytes = b"", invoke: int | None = None, port: int = 551):
        target = AmsAddr(self.target.netid, port)
        inv = next(self.invoke) if invoke is None else invoke
        return codec.request_frame(target, self.source, command, data, inv)

    def packet(self) -> AmsPacket:
        while not self.pending:
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed by the server")
            self.pending += [e for e in self.framer.feed(data) if isinstance(e, AmsPacket)]
        return self.pending.pop(0)

    def ask(self, command: int, data: bytes = b"", port: int = 551) -> AmsPacket:
        self.sock.sendall(self.frame(command, data, port=port))
        return self.packet()

    def read(self, ig: int, io: int, n: int) -> tuple[int, bytes]:
        return codec.parse_read_response(self.ask(Command.READ, codec.read_request(ig, io, n)).data)

    def read_write(self, ig: int, io: int, n: int, data: bytes) -> tuple[int, bytes]:
        pkt = self.ask(Command.READ_WRITE, codec.read_write_request(ig, io, n, data))
        return codec.parse_read_response(pkt.data)

    def wait_closed(self) -> bool:
        try:
            while self.sock.recv(65536):
                pass
        except ConnectionResetError:
            pass
        return True


@pytest.fixture
def raw(ads) -> Iterator[Raw]:
    c = Raw(ads.port)
    yield c
    c.close()


def wait_for(loop, predicate, timeout: float = TIMEOUT) -> bool:
    """Evaluate `predicate()` on the loop thread until it is true or `timeout` passes."""

    async def check() -> bool:
        return bool(predicate())

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if run_in(loop, check()):
            return True
        time.sleep(0.005)
    return False


def move_axes(service: ObjectService) -> None:
    """Give the objects non-trivial values: move every axis and retune TEMPC."""
    for i, axis in enumerate(service.info.axes):
        access.write_name(service, "SIM::target_position", axis, 20000 * (i + 1))
    access.write_name(service, "TEMPC::offset_0", 1, 55)
    access.step(service, 60)


CYCLE_COUNT_IO = (0 << 16) | D.by_name("SIM::cycle_count").id  # machine object, axis 0
SIM = 0x12F300


def step_sampled(service: ObjectService, loop, n: int = 1) -> list[int]:
    """Step `n` cycles one by one, letting the loop sample each before the next.

    The cycle thread hands the loop only the newest snapshot (coalesced), so a test that
    wants every cycle sampled waits for the loop after each step: a coroutine run on
    the loop is queued behind the hand-off, which has therefore run when it returns.
    """
    cycles = []
    for _ in range(n):
        cycles.append(access.step(service, 1).cycle)
        run_in(loop, asyncio.sleep(0))
    return cycles


# ---------------------------------------------------------------------- pyads: basics


def test_device_info_and_state(plc) -> None:
    name, version = plc.read_device_info()
    assert name == "geo-server"
    import geo_server

    assert f"{version.version}.{version.revision}.{version.build}" == geo_server.__version__
    assert plc.read_state() == (pyads.ADSSTATE_RUN, 0)


def test_read_every_geo_and_sim_object(plc, service) -> None:
    move_axes(service)
    objs = readable("geo") + readable("sim")
    assert len(readable("geo")) >= 24
    for axis in service.info.axes:
        for obj in objs:
            io = obj.index_offset(axis)
            value = plc.read(obj.index_group, io, PLCTYPE[obj.type.name])
            assert value == access.read_name(service, obj.name, axis), (obj.name, axis)
            raw = plc.read(obj.index_group, io, ctypes.c_ubyte * obj.length, return_ctypes=True)
            assert bytes(raw) == service.read(obj.index_group, io), (obj.name, axis)
    for obj in [o for o in D.group_objects("sim", "machine") if o.readable]:
        value = plc.read(obj.index_group, obj.index_offset(0), PLCTYPE[obj.type.name])
        assert value == access.read_name(service, obj.name, 0), obj.name


def test_attribute_groups_of_every_object(plc, service) -> None:
    for obj in D.group_objects("geo"):
        io = obj.index_offset(1)
        for attr, delta in (("name", 0x100), ("type", 0x200), ("unit", 0x400)):
            got = plc.read(GEO + delta, io, ctypes.c_ubyte * 256, return_ctypes=True)
            assert bytes(got) == obj.attribute(attr), (obj.name, attr)
        assert plc.read(GEO + 0x300, io, pyads.PLCTYPE_UDINT) == obj.length
        assert plc.read(GEO + 0x500, io, pyads.PLCTYPE_BOOL) == obj.writable
    raw = plc.read(0x120400, 0x10043, ctypes.c_ubyte * 256, return_ctypes=True)
    assert bytes(raw).split(b"\0")[0] == b"TEMPC::coefficient"
    assert bytes(plc.read(0x120500, 0x10043, ctypes.c_ubyte * 256, return_ctypes=True))[:6] == (
        b"REAL64"
    )


def test_write_writable_tempc_objects(plc, service) -> None:
    axis = 2
    writes = {
        "TEMPC::coefficient": (4321.5, pyads.PLCTYPE_LREAL),
        "TEMPC::offset_0": (-17, pyads.PLCTYPE_DINT),
        "TEMPC::position_0": (1234, pyads.PLCTYPE_DINT),
        "TEMPC::activated": (False, pyads.PLCTYPE_BOOL),
    }
    before = {n: access.read_name(service, n, axis) for n in writes}
    for name, (value, t) in writes.items():
        obj = D.by_name(name)
        plc.write(obj.index_group, obj.index_offset(axis), value, t)
    # stepped mode: acknowledged when queued, applied at the next cycle boundary
    assert {n: access.read_name(service, n, axis) for n in writes} == before
    access.step(service, 1)
    for name, (value, t) in writes.items():
        obj = D.by_name(name)
        assert plc.read(obj.index_group, obj.index_offset(axis), t) == value
        assert access.read_name(service, name, axis) == value


# ---------------------------------------------------------------------- pyads: errors


def err_code(fn, *args) -> int:
    with pytest.raises(pyads.ADSError) as exc:
        fn(*args)
    return exc.value.err_code


def test_every_error_code_via_pyads(plc, ads) -> None:
    lreal = pyads.PLCTYPE_LREAL
    assert err_code(plc.read, 0x120301, 0x10043, lreal) == 0x702
    assert err_code(plc.read, 0x999999, 0x10043, lreal) == 0x702
    assert err_code(plc.read, GEO, 0x1FFFF, lreal) == 0x703  # no such element
    assert err_code(plc.read, GEO, (99 << 16) | 0x43, lreal) == 0x703  # no such axis
    assert err_code(plc.write, GEO, 0x10042, 5, pyads.PLCTYPE_DINT) == 0x704  # read-only
    assert err_code(plc.write, 0x120400, 0x10043, 5, pyads.PLCTYPE_DINT) == 0x704  # attribute
    assert err_code(plc.read, GEO, 0x10043, pyads.PLCTYPE_DINT) == 0x705  # 4 of 8 bytes
    assert err_code(plc.write, GEO, 0x10043, 5, pyads.PLCTYPE_DINT) == 0x705
    assert err_code(plc.write, GEO, 0x10041, 2, pyads.PLCTYPE_BYTE) == 0x706  # BOOLEAN 2
    assert err_code(plc.write, GEO, 0x10043, float("nan"), lreal) == 0x706
    assert err_code(plc.write_control, pyads.ADSSTATE_STOP, 0, 0, pyads.PLCTYPE_INT) == 0x701
    other = pyads.Connection(plc.ams_netid, 852, ads.address)  # same endpoint, wrong port
    other.open()
    try:
        assert err_code(other.read_state) == 0x6
    finally:
        other.close()


def test_read_only_option_rejects_writes(loop_thread, service) -> None:
    srv = start_server(loop_thread, service, read_only=True)
    conn = pyads.Connection(next_netid(), 551, srv.address)
    conn.open()
    try:
        assert err_code(conn.write, GEO, 0x10043, 1.0, pyads.PLCTYPE_LREAL) == 0x704
        assert conn.read(GEO, 0x10043, pyads.PLCTYPE_LREAL) == access.read_name(
            service, "TEMPC::coefficient", 1
        )
    finally:
        conn.close()
        run_in(loop_thread, srv.close())


# ---------------------------------------------------------------------- pyads: sum commands


def test_sum_read_all_objects_of_one_axis(plc, service) -> None:
    move_axes(service)
    objs = readable("geo")
    items = [(o.index_group, o.index_offset(3), o.length) for o in objs]
    data = pyads.pyads_ex.adsSumReadBytes(plc._port, plc._adr, items)
    assert len(data) == 4 * len(items) + sum(o.length for o in objs)
    expected = service.read_many([(ig, io, n) for ig, io, n in items])
    parsed = codec.parse_sum_read_response(bytes(data), [n for *_, n in items])
    assert parsed == [(0, e) for e in expected]


def test_sum_read_with_failing_items(plc, service) -> None:
    items = [(GEO, 0x10043, 8), (GEO, 0x1FFFF, 4), (0x777, 0, 4), (GEO, 0x10043, 4)]
    data = pyads.pyads_ex.adsSumReadBytes(plc._port, plc._adr, items)
    parsed = codec.parse_sum_read_response(bytes(data), [8, 4, 4, 4])
    assert [c for c, _ in parsed] == [0, 0x703, 0x702, 0x705]
    assert parsed[0][1] == service.read(GEO, 0x10043)
    assert parsed[1][1] == b"\0" * 4


def test_sum_write_per_item_codes(plc, service) -> None:
    buf = bytearray(
        codec.sum_write_request(
            [
                (GEO, 0x10043, struct.pack("<d", 111.0)),
                (GEO, 0x10042, struct.pack("<i", 1)),  # read-only
                (GEO, 0x20044, struct.pack("<i", 77)),  # offset_0 of axis 2
            ]
        )
    )
    errors = pyads.pyads_ex.adsSumWriteBytes(plc._port, plc._adr, 3, buf)
    assert errors == ["no error", ERROR_CODES[0x704], "no error"]
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::coefficient", 1) == 111.0
    assert access.read_name(service, "TEMPC::offset_0", 2) == 77


# ---------------------------------------------------------------------- pyads: notifications


def test_on_change_notifications_follow_the_service(plc, service, loop_thread) -> None:
    """actual_offset while offset_0 ramps: the received values are exactly the distinct
    consecutive values the service reported at the cycles after the registration."""
    q: queue.Queue = queue.Queue()

    def callback(notification, _data) -> None:
        q.put(plc.parse_notification(notification, pyads.PLCTYPE_DINT, True))

    attr = pyads.NotificationAttrib(4)  # SERVERONCHA, every cycle
    handle, user = plc.add_device_notification((GEO, 0x10042), attr, callback)
    expected: list[int] = []
    offset_0 = access.read_name(service, "TEMPC::offset_0", 1)
    for k in range(60):
        if k % 10 == 0:
            offset_0 += 25
            plc.write(GEO, 0x10044, offset_0, pyads.PLCTYPE_DINT)
        step_sampled(service, loop_thread)  # every cycle sampled (hand-offs coalesce)
        v = service.current(stale_ok=True).value(ACTUAL_OFFSET, 1)
        if not expected or v != expected[-1]:
            expected.append(v)
    assert len(expected) > 10  # the sin² ramps really produced a sequence
    got = [q.get(timeout=TIMEOUT) for _ in expected]
    assert [v for _h, _ts, v in got] == expected
    assert {h for h, _ts, _v in got} == {handle}
    stamps = [ts for _h, ts, _v in got]
    assert stamps == sorted(stamps)
    assert abs(codec.filetime_to_unix(stamps[-1]) - time.time()) < 60
    plc.del_device_notification(handle, user)
    access.step(service, 30)
    with pytest.raises(queue.Empty):
        q.get(timeout=0.2)


def test_cyclic_notifications_every_n_cycles(plc, service) -> None:
    q: queue.Queue = queue.Queue()

    def callback(notification, _data) -> None:
        q.put(plc.parse_notification(notification, pyads.PLCTYPE_LREAL)[2])

    # 5 ms cycle time = 50000 ticks of 100 ns = 5 GEO cycles of 1 ms
    attr = pyads.NotificationAttrib(8, pyads.ADSTRANS_SERVERCYCLE, max_delay=5, cycle_time=5)
    handles = plc.add_device_notification((GEO, 0x10043), attr, callback)
    # (each pyads write is a round trip through the loop, so the loop samples every cycle)
    for k in range(1, 21):
        plc.write(GEO, 0x10043, 1000.0 + k, pyads.PLCTYPE_LREAL)
        access.step(service, 1)
    # the first sample one cycle after the registration, then every 5 cycles from it
    sent_at = [1001.0, 1006.0, 1011.0, 1016.0]
    got = [q.get(timeout=TIMEOUT) for _ in sent_at]
    assert got == sent_at
    plc.del_device_notification(*handles)
    with pytest.raises(queue.Empty):
        q.get(timeout=0.2)


def test_cyclic_interval_counts_from_the_last_sample(plc, service, loop_thread) -> None:
    """Cycle time 3 ms = 30000 ticks of 100 ns = 3 GEO cycles of 1 ms (docs/design.md §9).

    The first sample goes out at the first cycle boundary after the registration (c0+1),
    every later one when `cycle - last_cycle >= 3`: at c0+4, c0+7, … — never at c0+3
    (counting from the registration, the phase the old modulo rule kept).
    """
    q: queue.Queue = queue.Queue()

    def callback(notification, _data) -> None:
        q.put(plc.parse_notification(notification, pyads.PLCTYPE_UDINT)[2])

    attr = pyads.NotificationAttrib(4, pyads.ADSTRANS_SERVERCYCLE, max_delay=0, cycle_time=3)
    handles = plc.add_device_notification((SIM, CYCLE_COUNT_IO), attr, callback)
    c0 = service.current(stale_ok=True).cycle
    cycles = step_sampled(service, loop_thread, 16)
    assert cycles == list(range(c0 + 1, c0 + 17))
    assert access.read_name(service, "SIM::cycle_count") == cycles[-1]  # the value is the cycle
    expected = [c0 + 1, c0 + 4, c0 + 7, c0 + 10, c0 + 13, c0 + 16]
    assert [q.get(timeout=TIMEOUT) for _ in expected] == expected
    with pytest.raises(queue.Empty):
        q.get(timeout=0.2)  # nothing in between
    plc.del_device_notification(*handles)


def test_cycle_hand_offs_are_coalesced_and_every_cycle_is_sampled(
    plc, ads, service, machine, loop_thread
) -> None:
    """While the loop is busy, 50 cycles queue ONE hand-off; it then samples every
    snapshot handed over, in cycle order, so the stream is the one a punctual loop
    would have sent: every second cycle from the first one after the registration, each
    sample with its own cycle's value and time stamp (docs/design.md §13)."""
    q: queue.Queue = queue.Queue()

    def callback(notification, _data) -> None:
        contents = notification.contents
        q.put((plc.parse_notification(notification, pyads.PLCTYPE_UDINT)[2], contents.nTimeStamp))

    attr = pyads.NotificationAttrib(4, pyads.ADSTRANS_SERVERCYCLE, max_delay=0, cycle_time=2)
    handles = plc.add_device_notification((SIM, CYCLE_COUNT_IO), attr, callback)
    c0 = service.current(stale_ok=True).cycle
    hand_offs = []
    on_cycle = ads.sampler._on_cycle

    def counting(*args) -> None:  # (a per-cycle hand-off passed the snapshot along)
        hand_offs.append(service.current(stale_ok=True).cycle)
        on_cycle(*args)

    ads.sampler._on_cycle = counting  # what the cycle thread queues, looked up at each hand-off
    busy, release = threading.Event(), threading.Event()

    def block() -> None:
        busy.set()
        release.wait(TIMEOUT)

    loop_thread.call_soon_threadsafe(block)
    assert busy.wait(TIMEOUT)
    try:
        access.step(service, 50)
    finally:
        release.set()
    run_in(loop_thread, asyncio.sleep(0))
    assert hand_offs == [c0 + 50]
    epoch = machine.epoch  # FILETIME of cycle 0; 1 ms = 10 000 ticks
    expected = [(c, epoch + c * 10_000) for c in range(c0 + 1, c0 + 51, 2)]
    assert [q.get(timeout=TIMEOUT) for _ in expected] == expected  # late, none lost
    assert step_sampled(service, loop_thread, 4) == [c0 + 51, c0 + 52, c0 + 53, c0 + 54]
    assert [q.get(timeout=TIMEOUT)[0] for _ in range(2)] == [c0 + 51, c0 + 53]
    assert hand_offs == [c0 + 50, c0 + 51, c0 + 52, c0 + 53, c0 + 54]
    with pytest.raises(queue.Empty):
        q.get(timeout=0.2)
    plc.del_device_notification(*handles)


def test_failed_registrations_ask_the_engine_for_cycles_once(
    plc, service, loop_thread, monkeypatch
) -> None:
    """The cycles the registrations want are asked of the engine with the first one and
    given back `DEMAND_LINGER_S` after the last one went. With the cycle in its own
    process a new demand waits for the child's next frame (on the event loop): before,
    each AddNotification of a client whose registrations failed one after another (an
    unknown object, 0x703) asked and gave back again, a round trip to the child each."""
    from geo_server.transports.ads import sampling

    monkeypatch.setattr(sampling, "DEMAND_LINGER_S", 0.2, raising=False)
    asked: list[object] = []
    released: list[object] = []
    demand_cycles = service.demand_cycles

    def counted(demand=None):
        asked.append(demand)
        release = demand_cycles(demand)

        def counted_release() -> None:
            released.append(demand)
            release()

        return counted_release

    monkeypatch.setattr(service, "demand_cycles", counted)
    for _ in range(10):
        with pytest.raises(pyads.ADSError) as err:
            plc.add_device_notification((GEO, 0x10FFF), pyads.NotificationAttrib(4), lambda *a: 0)
        assert err.value.err_code == 0x703
    assert len(asked) == 1
    assert wait_for(loop_thread, lambda: len(released) == 1)


def test_notifications_removed_when_client_disconnects(ads, loop_thread, service) -> None:
    conn = pyads.Connection(next_netid(), 551, ads.address)
    conn.open()
    for io in (0x10042, 0x20042, 0x30042):
        conn.add_device_notification((GEO, io), pyads.NotificationAttrib(4), lambda *a: None)
    assert wait_for(loop_thread, lambda: len(ads.notifications) == 3)
    # (pyads' own close() would segfault here: it drops the route before the port)
    close_port_first(conn)  # AdsLib deletes its notifications, then drops the TCP link
    assert wait_for(loop_thread, lambda: len(ads.notifications) == 0)
    assert wait_for(loop_thread, lambda: ads.connection_count == 0)
    access.step(service, 5)  # nothing to send to anyone: no error


# ---------------------------------------------------------------------- running scheduler


@pytest.mark.realtime
def test_write_waits_until_applied_with_running_cycles(loop_thread, machine) -> None:
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    sched.start()
    srv = start_server(loop_thread, service)
    conn = pyads.Connection(next_netid(), 551, srv.address)
    conn.open()
    conn.set_timeout(int(TIMEOUT * 1000))
    try:
        for v in (1.5, 2.5, 3.5):
            conn.write(GEO, 0x10043, v, pyads.PLCTYPE_LREAL)
            # the response came after the cycle applied it: visible at once
            assert conn.read(GEO, 0x10043, pyads.PLCTYPE_LREAL) == v
        q: queue.Queue = queue.Queue()
        conn.add_device_notification(
            (GEO, 0x10043),
            pyads.NotificationAttrib(8),
            lambda n, _d: q.put(conn.parse_notification(n, pyads.PLCTYPE_LREAL)[2]),
        )
        assert q.get(timeout=TIMEOUT) == 3.5  # the first sample is never lost
        conn.write(GEO, 0x10043, 9.25, pyads.PLCTYPE_LREAL)
        assert q.get(timeout=TIMEOUT) == 9.25
    finally:
        close_port_first(conn)
        run_in(loop_thread, srv.close())
        sched.stop()


# ---------------------------------------------------------------------- the project's client


def test_ads_client_by_name_raw_and_sum(ads, service) -> None:
    move_axes(service)
    with AdsClient(port=ads.port, netid=next_netid()) as c:
        assert c.device_info()[0] == "geo-server"
        assert c.read("TEMPC::coefficient", 1) == access.read_name(service, "TEMPC::coefficient", 1)
        assert c.read_raw(GEO, 0x10043, 8) == service.read(GEO, 0x10043)
        assert c.read_raw(GEO, 0x10043, 64) == service.read(GEO, 0x10043)  # never more
        assert c.read_raw(0x120400, 0x10043, 256) == COEFFICIENT.attribute("name")
        assert c.write("TEMPC::coefficient", 1, 77) == 77.0
        access.step(service, 1)
        assert c.read("TEMPC::coefficient", 1) == 77.0
        c.write_raw(GEO, 0x10044, struct.pack("<i", -5))
        access.step(service, 1)
        assert c.read("TEMPC::offset_0", 1) == -5
        assert c.read_axis(2) == access.read_axis(service, 2)
        mixed = c.sum_read_raw([(GEO, 0x10043, 8), (GEO, 0x1FFFF, 4)])
        assert mixed[0] == service.read(GEO, 0x10043)
        assert isinstance(mixed[1], AdsError) and mixed[1].code == 0x703
        with pytest.raises(AdsError) as exc:
            c.write("TEMPC::actual_offset", 1, 3)
        assert exc.value.code == 0x704
        with pytest.raises(AdsError) as exc:
            c.read("TEMPC::coefficient", 9)
        assert exc.value.code == 0x703
        q: queue.Queue = queue.Queue()
        h = c.subscribe("TEMPC::coefficient", 1, lambda v, ts: q.put(v))
        access.step(service, 1)
        assert q.get(timeout=TIMEOUT) == 77.0
        c.write("TEMPC::coefficient", 1, 78.5)
        access.step(service, 1)
        assert q.get(timeout=TIMEOUT) == 78.5
        c.unsubscribe(h)


# ---------------------------------------------------------------------- raw frames


def test_coalesced_requests_are_all_answered(raw, service) -> None:
    frames = [
        raw.frame(Command.READ, codec.read_request(GEO, (a << 16) | 0x43, 8), 100 + a)
        for a in service.info.axes
    ]
    raw.sock.sendall(b"".join(frames))
    got = {}
    for _ in frames:
        p = raw.packet()
        got[p.header.invoke_id] = codec.parse_read_response(p.data)
    assert got == {100 + a: (0, service.read(GEO, (a << 16) | 0x43)) for a in service.info.axes}


def test_request_split_into_single_bytes(raw, service) -> None:
    frame = raw.frame(Command.READ, codec.read_request(GEO, 0x10043, 8), 42)
    for i in range(len(frame)):
        raw.sock.sendall(frame[i : i + 1])
    p = raw.packet()
    assert p.header.invoke_id == 42
    assert codec.parse_read_response(p.data) == (0, service.read(GEO, 0x10043))


def test_response_addressing(raw) -> None:
    p = raw.ask(Command.READ_STATE)
    assert p.header.source == raw.target and p.header.target == raw.source
    assert p.header.state_flags == 0x0005 and p.header.error_code == 0
    assert codec.parse_read_state_response(p.data) == (0, 5, 0)


def test_wrong_ams_port_is_ams_error_6(raw) -> None:
    p = raw.ask(Command.READ, codec.read_request(GEO, 0x10043, 8), port=552)
    assert p.header.error_code == 0x6 and p.data == b""


def test_a_group_on_the_other_tasks_port_is_0x702(raw) -> None:
    """Port 553 is the COM task (004 p.19): it serves 0x120100, not the GEO group."""
    p = raw.ask(Command.READ, codec.read_request(GEO, 0x10043, 8), port=553)
    assert p.header.error_code == 0 and p.data[:4] == (0x702).to_bytes(4, "little")
    p = raw.ask(Command.WRITE, codec.write_request(0x120100, 0x291, b"\0\0"), port=551)
    assert p.data[:4] == (0x702).to_bytes(4, "little")
    # the GEO task's name and symbol services are not the COM task's either
    name = b"GEO.X.TEMPC.coefficient\0"
    p = raw.ask(Command.READ_WRITE, codec.read_write_request(0xF003, 0, 4, name), port=553)
    assert p.data[:4] == (0x702).to_bytes(4, "little")
    p = raw.ask(Command.READ, codec.read_request(0xF00C, 0, 24), port=553)
    assert p.data[:4] == (0x702).to_bytes(4, "little")
    p = raw.ask(Command.READ_WRITE, codec.read_write_request(0xF003, 0, 4, name), port=551)
    assert p.data[:4] == b"\0\0\0\0"


def test_unknown_command_and_write_control_0x701(raw) -> None:
    p = raw.ask(0x0055, b"whatever")
    assert p.header.command == 0x55 and codec.parse_result(p.data) == 0x701
    assert p.header.error_code == 0x701
    p = raw.ask(Command.WRITE_CONTROL, struct.pack("<HHI", 6, 0, 0))
    assert codec.parse_result(p.data) == 0x701 and p.header.error_code == 0


def test_truncated_payload_is_0x705(raw) -> None:
    p = raw.ask(Command.READ, b"\x00" * 8)
    assert codec.parse_read_response(p.data) == (0x705, b"")
    p = raw.ask(Command.WRITE, codec.write_request(GEO, 0x10043, b"12345678")[:-2])
    assert codec.parse_result(p.data) == 0x705


def test_never_more_bytes_than_requested(raw, service) -> None:
    assert raw.read(GEO, 0x10043, 100) == (0, service.read(GEO, 0x10043))
    assert raw.read(GEO, 0x10043, 7) == (0x705, b"")
    assert raw.read(0x120400, 0x10043, 1000) == (0, COEFFICIENT.attribute("name"))
    # a sum read whose answer does not fit the read length
    req = codec.sum_read_request([(GEO, 0x10043, 8)])
    assert raw.read_write(SumGroup.READ, 1, 11, req) == (0x705, b"")
    assert raw.read_write(SumGroup.READ, 1, 12, req)[0] == 0
    # a sub-request asking for gigabytes is refused before anything is built
    huge = codec.sum_read_request([(GEO, 0x10043, 0xC000_0000)])
    assert raw.read_write(SumGroup.READ, 1, 0xFFFF_FFFF, huge) == (0x705, b"")
    assert raw.read_write(SumGroup.READ_EX, 1, 0xFFFF_FFFF, huge) == (0x705, b"")


def test_read_write_plain_and_with_data(raw, service) -> None:
    assert raw.read_write(GEO, 0x10043, 8, b"") == (0, service.read(GEO, 0x10043))
    code, data = raw.read_write(GEO, 0x10044, 4, struct.pack("<i", 12))
    assert code == 0 and len(data) == 4  # stepped: read back before the cycle applies it
    access.step(service, 1)
    assert raw.read(GEO, 0x10044, 4) == (0, struct.pack("<i", 12))
    assert raw.read_write(GEO, 0x10042, 4, struct.pack("<i", 12))[0] == 0x704


def test_sum_read_ex2_and_sum_read_write(raw, service) -> None:
    req = codec.sum_read_request([(GEO, 0x10043, 8), (GEO, 0x10041, 4), (GEO, 0x1FFFF, 4)])
    code, data = raw.read_write(SumGroup.READ_EX2, 3, 1000, req)
    assert code == 0
    assert codec.parse_sum_read_ex_response(data, 3) == [
        (0, service.read(GEO, 0x10043)),
        (0, service.read(GEO, 0x10041)),
        (0x703, b""),
    ]
    code, data = raw.read_write(SumGroup.READ_EX, 3, 1000, req)
    assert code == 0 and len(data) == 3 * 8 + 16
    rw = codec.sum_read_write_request(
        [
            (GEO, 0x10043, 8, b""),
            (GEO, 0x20043, 8, struct.pack("<d", 5.0)),
            (GEO, 0x10042, 4, b"1234"),
        ]
    )
    code, data = raw.read_write(SumGroup.READ_WRITE, 3, 1000, rw)
    assert code == 0
    results = codec.parse_sum_read_ex_response(data, 3)
    assert results[0] == (0, service.read(GEO, 0x10043))
    assert results[1][0] == 0 and results[2] == (0x704, b"")
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::coefficient", 2) == 5.0
    # unsupported sum group
    assert raw.read_write(SumGroup.ADD_DEVICE_NOTIFICATION, 0, 8, b"")[0] == 0x702


def test_bad_frames_are_skipped_or_answered(raw, service) -> None:
    s = raw.sock
    s.sendall(struct.pack("<HI", 0x1001, 2) + b"\0\0")  # router note from a client: skipped
    s.sendall(struct.pack("<HI", 0, 4) + b"abcd")  # shorter than an AMS header: skipped
    bad = bytearray(raw.frame(Command.READ, codec.read_request(GEO, 0x10043, 8), 7))
    struct.pack_into("<I", bad, 6 + 20, 1234)  # AMS data length lies
    s.sendall(bytes(bad))
    p = raw.packet()
    assert p.header.invoke_id == 7 and p.header.error_code == 0xE
    assert raw.read(GEO, 0x10043, 8) == (0, service.read(GEO, 0x10043))


def test_responses_and_notifications_sent_to_the_server_are_ignored(raw, service) -> None:
    req = codec.AmsHeader(raw.target, raw.source, Command.READ, 4, 0, 0, 1)
    raw.sock.sendall(codec.response_frame(req, codec.read_response(0, b"x")))
    note = codec.device_notification([codec.Stamp(1, (codec.Sample(1, b"ab"),))])
    raw.sock.sendall(codec.notification_frame(raw.source, raw.target, note))
    assert raw.read(GEO, 0x10043, 8) == (0, service.read(GEO, 0x10043))


def test_garbage_closes_only_that_connection(ads, service) -> None:
    bad, good = Raw(ads.port), Raw(ads.port)
    try:
        assert good.read(GEO, 0x10043, 8)[0] == 0
        bad.sock.sendall(bad.frame(Command.READ_STATE) + b"\xff" * 64)
        assert codec.parse_read_state_response(bad.packet().data)[0] == 0  # answered first
        assert bad.wait_closed()
        assert good.read(GEO, 0x10043, 8) == (0, service.read(GEO, 0x10043))
    finally:
        bad.close()
        good.close()


def test_oversized_frame_closes_the_connection(ads) -> None:
    c = Raw(ads.port)
    try:
        c.sock.sendall(struct.pack("<HI", 0, (1 << 20) + 1) + b"\0" * 100)
        assert c.wait_closed()
        assert ads.stats.closed_for_framing >= 1
    finally:
        c.close()
    ok = Raw(ads.port)
    try:
        assert ok.read(GEO, 0x10043, 8)[0] == 0
    finally:
        ok.close()


def test_notification_frames_on_the_wire(raw, ads, service, loop_thread) -> None:
    # registered length 8 for an SGN32 object: every sample is 8 bytes, zero-padded
    add = codec.add_notification_request(GEO, 0x10042, 8, codec.TransMode.SERVERONCHA)
    code, handle = codec.parse_add_notification_response(
        raw.ask(Command.ADD_DEVICE_NOTIFICATION, add).data
    )
    assert code == 0 and handle > 0
    access.write_name(service, "TEMPC::offset_0", 1, 500)
    snap = access.step(service, 1)
    p = raw.packet()
    assert p.header.command == Command.DEVICE_NOTIFICATION
    assert p.header.source == raw.target and p.header.target == raw.source
    assert p.header.state_flags == 0x0004
    (stamp,) = codec.parse_device_notification(p.data)
    (sample,) = stamp.samples
    assert sample.handle == handle and len(sample.data) == 8
    assert sample.data == snap.encode(ACTUAL_OFFSET, 1) + b"\0" * 4
    # errors of Add/Delete
    bad_mode = codec.add_notification_request(GEO, 0x10042, 4, codec.TransMode.CLIENT1REQ)
    assert codec.parse_add_notification_response(
        raw.ask(Command.ADD_DEVICE_NOTIFICATION, bad_mode).data
    ) == (0x713, 0)
    for ig, io, n, code in ((GEO, 0x1FFFF, 4, 0x703), (0x1, 0, 4, 0x702), (GEO, 0x10043, 4, 0x705)):
        req = codec.add_notification_request(ig, io, n)
        assert (
            codec.parse_add_notification_response(
                raw.ask(Command.ADD_DEVICE_NOTIFICATION, req).data
            )[0]
            == code
        )
    delete = codec.delete_notification_request(handle + 1000)
    assert codec.parse_result(raw.ask(Command.DELETE_DEVICE_NOTIFICATION, delete).data) == 0x714
    delete = codec.delete_notification_request(handle)
    assert codec.parse_result(raw.ask(Command.DELETE_DEVICE_NOTIFICATION, delete).data) == 0
    assert wait_for(loop_thread, lambda: len(ads.notifications) == 0)


def test_raw_disconnect_drops_notifications(ads, loop_thread, service) -> None:
    c = Raw(ads.port)
    add = codec.add_notification_request(GEO, 0x10042, 4)
    assert (
        codec.parse_add_notification_response(c.ask(Command.ADD_DEVICE_NOTIFICATION, add).data)[0]
        == 0
    )
    c.close()
    assert wait_for(loop_thread, lambda: len(ads.notifications) == 0)
    access.step(service, 3)


def test_strict_netid(loop_thread, service) -> None:
    srv = start_server(loop_thread, service, netid="5.6.7.8.1.1", strict_netid=True)
    try:
        wrong, right = Raw(srv.port), Raw(srv.port, "5.6.7.8.1.1")
        assert wrong.ask(Command.READ_STATE).header.error_code == 0x7
        assert right.ask(Command.READ_STATE).header.error_code == 0
        wrong.close()
        right.close()
    finally:
        run_in(loop_thread, srv.close())


def test_geo_client_via_ads(ads, service, capsys) -> None:
    from geo_server.client.cli import main as client_main

    host, port = ads.address.rsplit(":", 1)
    base = ["--via", "ads", "--connect", f"{host}:{port}", "--netid", next_netid()]
    assert client_main([*base, "read", "--axis", "1", "TEMPC::coefficient"]) == 0
    assert capsys.readouterr().out.strip() == "axis 1 (X) TEMPC::coefficient = 4000.0 µm/m"
    assert client_main([*base, "--json", "read", "0x120300", "0x10045"]) == 0
    row = json.loads(capsys.readouterr().out)  # position_0 100 increments = 0.01 mm
    assert (row["value"], row["unit"], row["raw"]) == (0.01, "mm", 100)
    assert client_main([*base, "write", "--axis", "3", "TEMPC::position_0", "-5"]) == 0
    capsys.readouterr()
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::position_0", 3) == -5
    assert client_main([*base, "write", "--axis", "1", "BC::actual backlash", "1"]) == 1
    assert "ADS 0x704" in capsys.readouterr().err
    # by address: attribute groups answer their attribute, writes to them get 0x704
    assert client_main([*base, "read", "0x120700", "0x10043"]) == 0
    assert capsys.readouterr().out.strip() == "axis 1 (X) TEMPC::coefficient unit = [um/m]"
    assert client_main([*base, "read", "0x120600", "0x10044"]) == 0
    assert capsys.readouterr().out.strip() == "axis 1 (X) TEMPC::offset_0 length = 4"
    assert client_main([*base, "write", "0x120800", "0x10043", "1"]) == 1
    assert "ADS 0x704" in capsys.readouterr().err


def test_a_machine_serves_at_most_requests_per_step_in_one_loop_step(service) -> None:
    """`requests_per_step` = 4: ten Reads pipelined in one segment are answered 4, 4 and
    2 in three loop steps, in order. A count carried over from earlier steps (a machine's
    count starts again only in the step after it reached half the limit) lowers what a
    step serves: after one single Read, the next ten go 3, 4, 3."""
    from geo_server.transports.ads.protocol import AdsConnection

    def reads(first: int, n: int) -> bytes:
        return b"".join(
            codec.request_frame(
                AmsAddr("127.0.0.1.1.1", 551),
                AmsAddr("10.9.9.9.1.1", 30000),
                Command.READ,
                codec.read_request(0x120300, 0x10043, 8),
                invoke,
            )
            for invoke in range(first, first + n)
        )

    async def steps(wire: Wire, expected: int) -> list[list[int]]:
        """The invoke ids answered in each loop step until `expected` have been."""
        out: list[list[int]] = []
        seen = 0
        while seen < expected:
            framer = codec.Framer()
            got = [
                ev.header.invoke_id
                for w in wire.out
                for ev in framer.feed(w)
                if isinstance(ev, codec.AmsPacket)
            ]
            wire.out.clear()
            out.append(got)
            seen += len(got)
            assert len(out) < 20, "the answers never came"
            await asyncio.sleep(0)
        return out

    async def run() -> tuple[list[list[int]], list[list[int]]]:
        ads = AdsServer(service, AdsOptions(port=0, requests_per_step=4))
        await ads.start()
        try:
            wire = Wire()
            conn = AdsConnection(ads)
            conn.connection_made(wire)
            conn.data_received(reads(1, 10))
            first = await steps(wire, 10)
            for _ in range(3):
                await asyncio.sleep(0)  # (the count's reset, whenever it was scheduled)
            conn.data_received(reads(11, 1))
            await steps(wire, 1)
            conn.data_received(reads(12, 10))
            return first, await steps(wire, 10)
        finally:
            await ads.close()

    first, second = asyncio.run(run())
    assert first == [[1, 2, 3, 4], [5, 6, 7, 8], [9, 10]]
    assert second == [[12, 13, 14], [15, 16, 17, 18], [19, 20, 21]]
