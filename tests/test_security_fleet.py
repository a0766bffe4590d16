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
import threading
import time

import pytest
from conftest import run_in
from support import probes
from test_fleet import TIMEOUT, fleet, served_fleet, zget  # noqa: F401  (the fixture)
from test_virtual_time import VirtualClock

from geo_server.dictionary import GEO_AMS_PORT, load_dictionary
from geo_server.fleet import Served, fleet_status, status_line
from geo_server.fleetfile import Member
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsAddr, AmsPacket, Command, TransMode
from geo_server.transports.ads.server import AdsOptions, AdsServer
from geo_server.transports.modbus.regmap import register_address
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions
from geo_server.transports.share import LoopShare

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
    """FC 3 of TEMPC::offset_0 (axis 1): the exception code or 0."""
    return probes.modbus_read(port, OFFSET_0, TIMEOUT)


# ---------------------------------------------------------------------- the fleet


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.realtime
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


# ---------------------------------------------------------------------- a flood on one machine


class Clock:
    """A loop-share clock the test holds still, then lets run a thousand times as fast
    as wall time: a machine's share of the loop fills only when the test says, so
    whether its requests wait is not a matter of timing."""

    def __init__(self) -> None:
        self.since: float | None = None

    def __call__(self) -> float:
        return 0.0 if self.since is None else (time.monotonic() - self.since) * 1000

    def run(self) -> None:
        self.since = time.monotonic()


@pytest.fixture
def shared(loop_thread):
    """Three stepped machines behind one ADS port, each with a Modbus port of its own,
    and a share of the loop per machine (drawn on by both): machine 1's on a clock of
    the test and small, the others' on the real clock with room for what they are
    asked."""
    cfg = load_machine(default_startup_list())
    clock = Clock()
    services = [ObjectService(Machine(cfg, homed=True)) for _ in range(3)]
    shares = [LoopShare(rate=0.05, burst=0.0005, clock=clock)]
    shares += [LoopShare(rate=0.05, burst=0.1) for _ in range(2)]
    head = AdsServer(services[0], AdsOptions(port=0, netid="127.0.0.1.1.1"), share=shares[0])
    for i in (1, 2):
        head.add_device(services[i], AdsOptions(netid=f"127.0.0.1.{i + 1}.1"), shares[i])
    modbus = [
        ModbusInterface(s, ModbusOptions(port=0), share)
        for s, share in zip(services, shares, strict=True)
    ]
    run_in(loop_thread, head.start())
    for mb in modbus:
        run_in(loop_thread, mb.start())
    yield clock, head, modbus, services, shares
    for mb in modbus:
        run_in(loop_thread, mb.close())
    run_in(loop_thread, head.close())


def ads_flood(port: int, netid: str, n: int) -> socket.socket:
    """`n` Reads of TEMPC::offset_0 pipelined to `netid` in one send (invoke ids 1…n)."""
    s = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
    src, dst = AmsAddr("10.8.0.1.1.1", 30000), AmsAddr(netid, GEO_AMS_PORT)
    s.sendall(
        b"".join(
            codec.request_frame(dst, src, Command.READ, codec.read_request(IG, IO, 4), i)
            for i in range(1, n + 1)
        )
    )
    return s


def ads_answers(s: socket.socket, framer: codec.Framer, want: int, block: bool) -> list[int]:
    """The invoke ids answered on `s` (each answer's ADS code must be 0): until `want`
    of them (`block`), or those already there."""
    got: list[int] = []
    s.settimeout(TIMEOUT if block else 0.05)
    while len(got) < want:
        try:
            chunk = s.recv(1 << 16)
        except TimeoutError:
            if block:
                raise
            break
        assert chunk, "the server closed the flooding connection"
        for ev in framer.feed(chunk):
            assert isinstance(ev, AmsPacket) and struct.unpack_from("<I", ev.data)[0] == 0
            got.append(ev.header.invoke_id)
    return got


def wait_for(what: str, cond) -> None:
    deadline = time.monotonic() + TIMEOUT
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def test_a_flood_on_one_machine_waits_for_its_share_while_the_others_are_answered(shared) -> None:
    """Issue 30 item 5: 400 ADS Reads pipelined to machine 1 take more of the loop than
    its share: machine 1 is held (its connection's reading paused, the requests read
    waiting) while machines 2 and 3 are answered at once on ADS and Modbus; once its
    share fills again every flooding Read is answered, once each, in order; machine 1's
    status and the fleet's say it was throttled, and nobody else was."""
    clock, head, modbus, services, shares = shared
    flood = ads_flood(head.port, "127.0.0.1.1.1", 400)
    framer = codec.Framer()
    try:
        wait_for("machine 1 held", lambda: shares[0].holds > 0)
        # machine 1's share does not fill while the clock stands: the flood waits...
        other = Ads(head.port, "10.8.0.2.1.1")
        try:
            for _ in range(3):
                for netid in ("127.0.0.1.2.1", "127.0.0.1.3.1"):
                    assert other.read(netid)[0] == 0
                for mb in modbus[1:]:
                    assert modbus_read(mb.port) == 0
        finally:
            other.close()
        early = ads_answers(flood, framer, 400, block=False)
        assert len(early) < 400  # ...while the other machines were answered
        assert head.stats.held_requests > 0
        # ...and is served once the share fills again
        clock.run()
        got = early + ads_answers(flood, framer, 400 - len(early), block=True)
        assert got == list(range(1, 401))
    finally:
        flood.close()
    assert shares[1].holds == shares[2].holds == 0
    assert services[0].status()["loop_share"]["holds"] == shares[0].holds > 0
    assert services[1].status()["loop_share"]["holds"] == 0
    # the fleet's status names the machine held back since its last status
    served = [
        Served(Member(f"m{i + 1}", default_startup_list(), f"127.0.0.1.{i + 1}.1", 0), s, None)
        for i, s in enumerate(services)
    ]
    status = fleet_status(served)
    assert status["throttled"] == ["m1"]
    assert [m["loop_share_holds"] > 0 for m in status["machines"]] == [True, False, False]
    assert fleet_status(served)["throttled"] == []  # nothing held since


def test_a_modbus_flood_on_one_machine_waits_for_its_share(shared) -> None:
    """The same share holds a machine's Modbus requests: 200 pipelined reads to machine
    1's port wait (the connection stops reading at `max_pipeline` queued), machine 2's
    port answers meanwhile, and every read is answered in order once the share is back."""
    clock, _head, modbus, _services, shares = shared
    req = struct.pack(">HHBBHH", 0, 6, 1, 3, register_address(OFFSET_0), 2)
    with socket.create_connection(("127.0.0.1", modbus[0].port), timeout=TIMEOUT) as s:
        s.sendall(b"".join(struct.pack(">H", tid) + req for tid in range(1, 201)))
        wait_for("machine 1 held", lambda: modbus[0].held_requests > 0)
        assert modbus_read(modbus[1].port) == 0
        clock.run()
        buf = b""
        while len(buf) < 200 * 13:
            chunk = s.recv(1 << 16)
            assert chunk
            buf += chunk
    tids = [struct.unpack_from(">H", buf, i * 13)[0] for i in range(200)]
    assert tids == list(range(1, 201))
    assert all(buf[i * 13 + 7] == 3 for i in range(200))  # FC 3 answers, no exception
    assert shares[0].holds > 0 and shares[1].holds == 0


@pytest.mark.slow
def test_a_flooded_machine_of_a_running_fleet_is_throttled_and_says_so(tmp_path) -> None:
    """`geo-server run --fleet` of three machines, a client keeping 64 ADS Reads in
    flight to the first: the others answer ADS, Modbus and Zenoh meanwhile, the flood is
    answered too (at its machine's share of the loop), and `cnc/fleet/status` lists the
    flooded machine as throttled, with its holds, and no other; once the flood stops
    nobody is."""
    names = [("m-a", None), ("m-b", "127.0.0.1.2.1"), ("m-c", "127.0.0.1.3.1")]
    with served_fleet(tmp_path, names) as served:
        stop = threading.Event()
        answered = [0]

        def flood() -> None:
            s = ads_flood(served["aport"], MILL, 64)
            framer = codec.Framer()
            with s:
                while not stop.is_set():
                    got = ads_answers(s, framer, 64, block=False)
                    answered[0] += len(got)
                    if got:  # as many again: 64 in flight
                        src, dst = AmsAddr("10.8.0.1.1.1", 30000), AmsAddr(MILL, GEO_AMS_PORT)
                        frame = codec.request_frame(
                            dst, src, Command.READ, codec.read_request(IG, IO, 4), 1
                        )
                        s.sendall(frame * len(got))

        flooding = threading.Thread(target=flood, daemon=True)
        flooding.start()
        try:
            status: dict = {}

            def throttled() -> bool:
                nonlocal status
                got = zget(served["zenoh"], "cnc/fleet/status")
                status = got[0][1] if got else {}  # type: ignore[assignment]
                return status.get("throttled") == ["m-a"]

            other = Ads(served["aport"], "10.8.0.3.1.1")
            try:
                deadline = time.monotonic() + 4 * TIMEOUT
                while not throttled():
                    assert time.monotonic() < deadline, status
                    for netid in ("127.0.0.1.2.1", "127.0.0.1.3.1"):
                        assert other.read(netid)[0] == 0
                    for port in served["modbus"][1:]:
                        assert modbus_read(port) == 0
                    for name in ("m-b", "m-c"):
                        assert len(zget(served["zenoh"], f"cnc/{name}/axis/1/tempc/offset_0")) == 1
            finally:
                other.close()
            holds = [m["loop_share_holds"] for m in status["machines"]]
            assert holds[0] > 0 and holds[1:] == [0, 0]
            # the status line of this very status says so too: a status is printed
            # before Zenoh (or the web HMI) has it (fleet._serve)
            line = status_line(status)
            assert line.endswith("throttled 1")
            assert line in served["out"].read_text().splitlines()
        finally:
            stop.set()
            flooding.join(TIMEOUT)
        assert answered[0] > 64
        deadline = time.monotonic() + 4 * TIMEOUT
        while throttled():
            assert time.monotonic() < deadline, "still throttled after the flood"
            time.sleep(0.2)
        assert status["throttled"] == []
