"""Machines of a fleet are isolated (issue 30 item 5, docs/design.md §13.1): what one
client does to some machines behind the fleet's ADS port leaves the others served.

- one client holding a machine's connection cap does not shut out another machine's
  clients (before, the 128-connection cap counted the whole port);
- notification and symbol-handle caps hold per machine and for the fleet (0x716);
- with notifications on every machine, every machine answers ADS, Modbus and Zenoh;
- an on-change notification of a value that cannot change at rest does not make its
  machine build snapshots of its quiescent cycles (the scheduler's counters under a
  virtual clock), while one of the cycle counter does, cycle by cycle.

Behaviour, not timing: real sockets on loopback, the fleet of tests/test_fleet.py (a
`geo-server run --fleet` subprocess), in-process servers with small caps where a cap
of the default size would only make the test slow.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import time

import pytest
from conftest import run_in
from test_fleet import TIMEOUT, fleet, zget  # noqa: F401  (the fixture)
from test_virtual_time import VirtualClock

from geo_server.dictionary import GEO_AMS_PORT, load_dictionary
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsAddr, AmsPacket, Command, TransMode
from geo_server.transports.ads.server import AdsOptions, AdsServer
from geo_server.transports.modbus.regmap import register_address

D = load_dictionary()
OFFSET_0 = D.by_name("TEMPC::offset_0")  # constant unless written
CYCLE_COUNT = D.by_name("SIM::cycle_count")  # changes every cycle, also at rest
IG, IO = OFFSET_0.index_group, OFFSET_0.index_offset(1)
MILL, LATHE = "127.0.0.1.1.1", "127.0.0.1.9.1"  # the fixture's machines
NOMOREHDLS = 0x716


class Ads:
    """A raw AMS/TCP connection: one request at a time, notification frames counted."""

    def __init__(self, port: int, source: str) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
        self.framer = codec.Framer()
        self.source = AmsAddr(source, 30000)
        self.invoke = 0
        self.notifications = 0

    def request(self, netid: str, command: int, data: bytes) -> AmsPacket:
        self.invoke += 1
        self.sock.sendall(
            codec.request_frame(
                AmsAddr(netid, GEO_AMS_PORT), self.source, command, data, self.invoke
            )
        )
        while True:
            chunk = self.sock.recv(65536)
            assert chunk, "the server closed the connection"
            for ev in self.framer.feed(chunk):
                assert isinstance(ev, AmsPacket)
                if ev.header.command == Command.DEVICE_NOTIFICATION:
                    self.notifications += 1
                elif ev.header.invoke_id == self.invoke:
                    return ev

    def read(self, netid: str, ig: int = IG, io: int = IO) -> tuple[int, bytes]:
        p = self.request(netid, Command.READ, codec.read_request(ig, io, 4))
        assert p.header.error_code == 0
        code = struct.unpack_from("<I", p.data)[0]
        return code, p.data[8:]

    def notify(self, netid: str, ig: int = IG, io: int = IO) -> int:
        """An on-change notification every cycle (the pyads default): its ADS code."""
        data = codec.add_notification_request(ig, io, 4, TransMode.SERVERONCHA, 0, 1)
        p = self.request(netid, Command.ADD_DEVICE_NOTIFICATION, data)
        return codec.parse_add_notification_response(p.data)[0]

    def handle(self, netid: str, name: str) -> int:
        data = codec.read_write_request(0xF003, 0, 4, name.encode() + b"\0")
        p = self.request(netid, Command.READ_WRITE, data)
        return int(struct.unpack_from("<I", p.data)[0])

    def close(self) -> None:
        self.sock.close()


def modbus_read(port: int) -> int:
    """FC 3 of TEMPC::offset_0's two registers (axis 1): the exception code or 0."""
    with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as s:
        s.sendall(struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, register_address(OFFSET_0), 2))
        buf = b""
        while len(buf) < 9:
            chunk = s.recv(64)
            assert chunk
            buf += chunk
        return 0 if buf[7] == 3 else buf[8]


# ---------------------------------------------------------------------- the fleet


def test_a_client_holding_one_machines_connections_does_not_shut_out_another(fleet) -> None:  # noqa: F811
    """128 connections to mill-a (its `max_connections`): the 129th request for mill-a
    is refused (0x716), but lathe-b's clients still connect and are answered — before,
    the cap counted the whole port and every other machine's clients were shut out."""
    held = [Ads(fleet["aport"], f"10.1.{i // 200}.{i % 200 + 1}.1.1") for i in range(128)]
    try:
        for conn in held:
            assert conn.read(MILL)[0] == 0
        extra = Ads(fleet["aport"], "10.2.0.1.1.1")
        try:
            assert extra.read(MILL)[0] == NOMOREHDLS
            assert extra.read(LATHE)[0] == 0  # the same connection, another machine
        finally:
            extra.close()
        other = Ads(fleet["aport"], "10.3.0.1.1.1")
        try:
            assert other.read(LATHE)[0] == 0
        finally:
            other.close()
    finally:
        for conn in held:
            conn.close()


def test_with_notifications_on_every_machine_every_machine_answers(fleet) -> None:  # noqa: F811
    """Notifications on every machine (each machine's per-connection cap over two
    connections, on a constant object and on the cycle counter): ADS, Modbus and Zenoh
    still answer every machine."""
    clients = [Ads(fleet["aport"], f"10.4.0.{i + 1}.1.1") for i in range(2)]
    try:
        for netid in (MILL, LATHE):
            for conn in clients:
                codes = [conn.notify(netid) for _ in range(200)]
                codes += [
                    conn.notify(netid, CYCLE_COUNT.index_group, CYCLE_COUNT.index_offset(0))
                    for _ in range(5)
                ]
                assert codes == [0] * 205
        for _ in range(3):
            for netid in (MILL, LATHE):
                assert clients[0].read(netid)[0] == 0
            for port in fleet["modbus"]:
                assert modbus_read(port) == 0
            for name in ("mill-a", "lathe-b"):
                assert len(zget(fleet["zenoh"], f"cnc/{name}/axis/1/tempc/offset_0")) == 1
        ((_, status),) = zget(fleet["zenoh"], "cnc/fleet/status")
        assert [m["name"] for m in status["machines"]] == ["mill-a", "lathe-b"]  # type: ignore[index]
        assert "loop_lag_ms" in status and "starved" in status  # type: ignore[operator]
    finally:
        for conn in clients:
            conn.close()


# ---------------------------------------------------------------------- in process


@pytest.fixture
def three(loop_thread):
    """Three stepped machines behind one ADS port with small caps: 3 notifications and
    4 symbol handles per machine, 5 of each for the port."""
    cfg = load_machine(default_startup_list())
    services = [ObjectService(Machine(cfg, homed=True)) for _ in range(3)]
    small = {"max_notifications_total": 3, "max_handles_machine": 4}
    head = AdsServer(
        services[0],
        AdsOptions(
            port=0,
            netid="127.0.0.1.1.1",
            max_notifications_fleet=5,
            max_handles_fleet=5,
            **small,  # type: ignore[arg-type]
        ),
    )
    for i in (1, 2):
        head.add_device(services[i], AdsOptions(netid=f"127.0.0.1.{i + 1}.1", **small))  # type: ignore[arg-type]
    run_in(loop_thread, head.start())
    yield head
    run_in(loop_thread, head.close())


def test_notification_caps_hold_per_machine_and_for_the_fleet(three) -> None:
    conn = Ads(three.port, "10.5.0.1.1.1")
    try:
        m1, m2, m3 = "127.0.0.1.1.1", "127.0.0.1.2.1", "127.0.0.1.3.1"
        assert [conn.notify(m1) for _ in range(4)] == [0, 0, 0, NOMOREHDLS]  # machine's 3
        assert [conn.notify(m2) for _ in range(3)] == [0, 0, NOMOREHDLS]  # the fleet's 5
        assert conn.notify(m3) == NOMOREHDLS
        assert conn.read(m3)[0] == 0  # refused registrations, served reads
    finally:
        conn.close()
    # a closed connection gives its registrations back, at every machine
    deadline = time.monotonic() + TIMEOUT
    while three.notifications.pool.count and time.monotonic() < deadline:
        time.sleep(0.01)
    assert three.notifications.pool.count == 0
    again = Ads(three.port, "10.5.0.2.1.1")
    try:
        assert again.notify("127.0.0.1.3.1") == 0
    finally:
        again.close()


def test_symbol_handle_caps_hold_per_machine_and_for_the_fleet(three) -> None:
    a, b = Ads(three.port, "10.6.0.1.1.1"), Ads(three.port, "10.6.0.2.1.1")
    name = "GEO.X.TEMPC.offset_0"
    try:
        m1, m2 = "127.0.0.1.1.1", "127.0.0.1.2.1"
        # 4 at machine 1 over two connections, the 5th refused (per machine)
        got = [a.handle(m1, name) for _ in range(2)] + [b.handle(m1, name) for _ in range(3)]
        assert got == [0, 0, 0, 0, NOMOREHDLS]
        # one more at machine 2 reaches the fleet's 5; the next is refused
        assert [b.handle(m2, name) for _ in range(2)] == [0, NOMOREHDLS]
    finally:
        a.close()
    deadline = time.monotonic() + TIMEOUT
    while three.fleet_handles > 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        assert b.handle(m2, name) == 0  # a's two handles were given back
    finally:
        b.close()


def test_an_on_change_notification_of_a_constant_does_not_make_a_resting_machine_publish(
    loop_thread,
) -> None:
    """The exact engine under a virtual clock: a machine at rest 5000 cycles with an
    on-change notification of TEMPC::offset_0 builds no snapshot for it (the value
    cannot change while the machine is quiescent) and computes no cycle more than the
    same machine without it; one of SIM::cycle_count (which changes every cycle) is
    sampled every cycle — the cost follows what is sampled."""
    cfg = load_machine(default_startup_list())

    def machine_at_rest() -> tuple[VirtualClock, Scheduler, ObjectService]:
        vc = VirtualClock()
        sched = Scheduler(
            Machine(cfg, homed=True),
            mode="realtime",
            engine="exact",
            clock=vc.clock,
            sleep=vc.sleep,
        )
        sched.drive()
        service = ObjectService(sched.machine, sched)
        vc.t += 100 * 1_000_000  # past the homing ramps: quiescent
        service.current(stale_ok=True)
        assert sched.machine.quiescent
        return vc, sched, service

    ref_vc, ref_sched, ref_service = machine_at_rest()
    ref_vc.t += 5000 * 1_000_000
    ref_service.current(stale_ok=True)

    vc, sched, service = machine_at_rest()
    ads = AdsServer(service, AdsOptions(port=0))
    run_in(loop_thread, ads.start())
    conn = Ads(ads.port, "10.7.0.1.1.1")
    try:
        assert conn.notify("127.0.0.1.1.1") == 0
        vc.t += 1_000_000
        service.current(stale_ok=True)  # the first sample's cycle (a registration's first is sent)
        deadline = time.monotonic() + TIMEOUT
        while ads.notifications.wants(sched.machine.cycle + 1, True):
            assert time.monotonic() < deadline, "the first sample was never taken"
            run_in(loop_thread, asyncio.sleep(0.01))
        demanded, computed = sched.demanded, sched.computed
        vc.t += 4999 * 1_000_000
        assert service.current(stale_ok=True).cycle == ref_sched.machine.cycle
        assert sched.demanded == demanded  # no snapshot built for the notification
        assert sched.computed == ref_sched.computed == computed  # none computed either
        # the cycle counter at rest: every cycle is wanted and published
        cc = (CYCLE_COUNT.index_group, CYCLE_COUNT.index_offset(0))
        assert conn.notify("127.0.0.1.1.1", *cc) == 0
        before = sched.demanded
        vc.t += 50 * 1_000_000
        service.current(stale_ok=True)
        assert sched.demanded - before >= 49
        assert sched.computed == computed  # published from skipped cycles, not computed
    finally:
        conn.close()
        run_in(loop_thread, ads.close())
