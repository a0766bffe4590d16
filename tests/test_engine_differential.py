"""The engines are unobservable (docs/design.md §13): one scenario — an NC program with
moves, reversals and a dwell, TEMPC writes at chosen moments, sum reads at random
moments, cyclic and on-change ADS notifications — through a real ADS server and pyads,
with the punctual engine, the exact engine on a thread and the exact engine in its own
process. Every value a client observed is then checked, cycle for cycle, against stepped
mode driven with the same operations at the same cycles:

- every sum read is one cycle's snapshot (the cycle count it carries names the cycle);
- every notification sample carries its own cycle's time stamp (epoch + cycle · 1 ms) and
  that cycle's value; cyclic streams have no gap and no duplicate;
- with the exact engine a read sent at t0 + a and answered at t0 + b shows a cycle in
  [floor(a/T), floor(b/T)] — exactly the cycle due, within the round trip.

The program's start and the writes land at whatever cycle wall time gives them; the
samples of `SIM::program_running` and `TEMPC::offset_0` say which, and the stepped run
applies them there.
"""

from __future__ import annotations

import itertools
import queue
import random
import struct
import time
from collections.abc import Iterator

import pyads
import pytest
from conftest import run_in

from geo_server.client.ads_client import close_port_first
from geo_server.dictionary import load_dictionary
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.nc import parse_program
from geo_server.machine.port import StartProgram, WriteObjects
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.transports.ads.server import AdsOptions, AdsServer

D = load_dictionary()
TIMEOUT = 5.0
TICKS = 10_000  # 1 ms in FILETIME ticks
PROGRAM = (
    "N10 G90 G01 X40 Y-20 F12000\nN20 X-25 Y15\nN30 G04 X0.05\nN40 X30 Z-8 F9000\n"
    "N50 X-10 Y0 Z0\nM30\n"
)
#: (object, axis, pyads type, notification: None | ("cyclic", n) | ("change",))
WATCH = [
    ("SIM::cycle_count", 0, pyads.PLCTYPE_UDINT, ("cyclic", 3)),
    ("SIM::command_position", 1, pyads.PLCTYPE_DINT, ("cyclic", 5)),
    ("TWIN::true_position", 2, pyads.PLCTYPE_LREAL, ("cyclic", 7)),
    ("TEMPC::actual_offset", 1, pyads.PLCTYPE_DINT, ("change",)),
    ("TEMPC::offset_0", 1, pyads.PLCTYPE_DINT, ("change",)),
    ("SIM::program_running", 0, pyads.PLCTYPE_BOOL, ("change",)),
    ("BC::delta backlash", 2, pyads.PLCTYPE_DINT, None),
    ("SIM::velocity", 1, pyads.PLCTYPE_DINT, None),
]
FORMAT = {
    pyads.PLCTYPE_UDINT: "<I",
    pyads.PLCTYPE_DINT: "<i",
    pyads.PLCTYPE_LREAL: "<d",
    pyads.PLCTYPE_BOOL: "<?",
}


class Live:
    """A machine served over ADS, its cycle run by one of the engines."""

    def __init__(self, loop, kind: str) -> None:
        self.cfg = load_machine(default_startup_list())
        if kind == "process":
            from geo_server.machine.process import ProcessScheduler, RemoteMachine

            machine = RemoteMachine(self.cfg, cycle_s=0.001, homed=True)
            self.sched = ProcessScheduler(machine, mode="realtime", engine="exact")
        else:
            machine = Machine(self.cfg, cycle_s=0.001, homed=True)
            self.sched = Scheduler(machine, mode="realtime", engine=kind)
        self.machine = machine
        self.service = ObjectService(machine, self.sched)
        self.loop = loop
        self.ads = AdsServer(self.service, AdsOptions(port=0))
        run_in(loop, self.ads.start())
        self.sched.start()

    def t0(self) -> int:
        return self.sched.t0 if isinstance(self.sched, Scheduler) else self.machine.t0

    def epoch(self) -> int:
        snap = self.service.current(stale_ok=True)
        return snap.stamp - snap.cycle * TICKS

    def close(self) -> None:
        self.sched.stop()
        run_in(self.loop, self.ads.close())


@pytest.fixture(params=["punctual", "exact", "process"])
def live(request, loop_thread) -> Iterator[Live]:
    if request.param == "process":
        from geo_server.machine.process import SUPPORTED

        if not SUPPORTED:
            pytest.skip("the cycle process needs POSIX pipes")
    srv = Live(loop_thread, request.param)
    yield srv
    srv.close()


@pytest.mark.slow
def test_every_observation_is_the_stepped_machine_at_its_cycle(live: Live) -> None:
    plc = pyads.Connection("127.0.0.5.1.1", 551, live.ads.address)
    plc.open()
    plc.set_timeout(int(TIMEOUT * 1000))
    samples: queue.Queue = queue.Queue()
    try:
        for name, axis, plctype, notify in WATCH:
            if notify is None:
                continue
            obj = D.by_name(name)
            cycles = notify[1] if notify[0] == "cyclic" else 1
            mode = pyads.ADSTRANS_SERVERCYCLE if notify[0] == "cyclic" else 4  # SERVERONCHA
            attr = pyads.NotificationAttrib(obj.length, mode, max_delay=0, cycle_time=cycles)

            def callback(notification, _data, name=name, plctype=plctype) -> None:
                stamp = notification.contents.nTimeStamp
                value = plc.parse_notification(notification, plctype)[2]
                samples.put((name, stamp, value))

            plc.add_device_notification((obj.index_group, obj.index_offset(axis)), attr, callback)
        reads = run_scenario(live, plc)
        epoch = live.epoch()
        got = handed_over(samples, epoch, live.service.current(stale_ok=True).cycle)
    finally:
        # Not del_device_notification: pyads frees the ctypes callback at once while
        # AdsLib's dispatcher may still hold samples of a batch for it (a crash); closing
        # the AMS port first ends the dispatch, then nothing is called any more.
        close_port_first(plc)
    while True:
        try:
            got.append(samples.get(timeout=0.3))
        except queue.Empty:
            break
    assert live.service.status()["overruns"] == 0 or live.sched.engine == "punctual"
    check(live, epoch, reads, got)


def handed_over(samples: queue.Queue, epoch: int, end: int) -> list[tuple[str, int, object]]:
    """The samples handed over until the cycle count's stream reaches cycle `end` (the
    scenario's last): closing the AMS port drops the samples AdsLib's dispatcher has not
    handed over yet, and it hands them over in the order they came, so by then every
    sample of an earlier cycle is here. (Closed at once, a run next to four busy
    processes once lost the second write's on-change sample, 0.7 s after it was sent.)"""
    got: list[tuple[str, int, object]] = []
    while True:
        try:
            sample = samples.get(timeout=TIMEOUT)
        except queue.Empty:
            raise AssertionError(f"no sample of cycle {end} or later within {TIMEOUT} s") from None
        got.append(sample)
        name, stamp, _value = sample
        if name == "SIM::cycle_count" and (stamp - epoch) // TICKS >= end:
            return got


def run_scenario(live: Live, plc: pyads.Connection) -> list[tuple[int, int, bytes]]:
    """About 1.6 s: the program, two TEMPC writes, a sum read every few ms — longer when
    an operation's round trip ran past its successor's moment (the second write is made
    even then: once, in the stress check, the first write's round trip ended after 1.6 s
    and the scenario ended with one write, which `check` took for a missing sample)."""
    rng = random.Random(5)
    items = [
        (D.by_name(n).index_group, D.by_name(n).index_offset(a), D.by_name(n).length)
        for n, a, _t, _w in WATCH
    ]
    reads: list[tuple[int, int, bytes]] = []
    offset = plc.read(*items[4][:2], pyads.PLCTYPE_DINT)
    start = time.monotonic()
    done = {"program": False, "w1": False, "w2": False}
    while time.monotonic() - start < 1.6 or not all(done.values()):
        elapsed = time.monotonic() - start
        if not done["program"] and elapsed > 0.1:
            live.service.nc.run(PROGRAM).result(TIMEOUT)
            done["program"] = True
        for key, at, delta in (("w1", 0.45, 60), ("w2", 0.9, -35)):
            if not done[key] and elapsed > at:
                offset += delta
                plc.write(*items[4][:2], offset, pyads.PLCTYPE_DINT)
                done[key] = True
        a = time.monotonic_ns()
        data = bytes(pyads.pyads_ex.adsSumReadBytes(plc._port, plc._adr, items))
        b = time.monotonic_ns()
        reads.append((a, b, data))
        time.sleep(rng.uniform(0.0, 0.006))
    return reads


def check(live: Live, epoch: int, reads, got) -> None:
    # the cycles of the operations, from the samples
    cycle_of = lambda stamp: (stamp - epoch) // TICKS  # noqa: E731
    by_name: dict[str, list[tuple[int, object]]] = {}
    for name, stamp, value in got:
        assert (stamp - epoch) % TICKS == 0, "a time stamp that is not a cycle's"
        by_name.setdefault(name, []).append((cycle_of(stamp), value))
    running = by_name["SIM::program_running"]
    start = next(c for c, v in running if v)
    writes = [(c, v) for c, v in by_name["TEMPC::offset_0"][1:]]  # (first: at registration)
    assert len(writes) == 2 and start > 0, (writes, start)
    # the stepped machine with the same operations at the same cycles
    ref = Machine(live.cfg, cycle_s=0.001, homed=True)
    ops = {start: StartProgram(parse_program(PROGRAM, ref.names, mdi=True), True)}
    for c, v in writes:
        ops[c] = WriteObjects((("TEMPC::offset_0", 1, v),))
    last = max(max(c for c, _ in by_name[n]) for n in by_name)
    last = max(last, *(struct.unpack_from("<I", d, 4 * len(WATCH))[0] for _a, _b, d in reads))
    # (a registration made before the first cycle samples cycle 0: the snapshot the
    # machine is built with)
    snaps = {ref.cycle: ref.snapshot}
    while ref.cycle < last:
        op = ops.get(ref.cycle + 1)
        if op is not None:
            ref.submit(op)
        snap = ref.run_cycle()
        snaps[snap.cycle] = snap

    def expected(name: str, axis: int, cycle: int) -> object:
        return snaps[cycle].value(D.by_name(name), axis)

    # notifications: every sample is its cycle's value; cyclic streams are complete
    for name, axis, _t, notify in WATCH:
        if notify is None:
            continue
        stream = by_name[name]
        for c, v in stream:
            assert v == pytest.approx(expected(name, axis, c), abs=0), (name, c)
        cyc = [c for c, _ in stream]
        if notify[0] == "cyclic":
            assert all(b - a == notify[1] for a, b in itertools.pairwise(cyc)), (name, cyc)
            assert len(cyc) > 1500 // notify[1] // 2
        else:  # on change: the sample at each change, nothing in between
            values = [expected(name, axis, c) for c in range(cyc[0], cyc[-1] + 1)]
            changes = [cyc[0]] + [
                cyc[0] + i for i in range(1, len(values)) if values[i] != values[i - 1]
            ]
            assert cyc == changes, name
    assert [v for _c, v in by_name["SIM::cycle_count"]] == [
        c for c, _ in by_name["SIM::cycle_count"]
    ]
    # sum reads: one cycle each, that cycle's values; with the exact engine the cycle due
    t0 = live.t0()
    n = len(WATCH)
    for a, b, data in reads:
        codes = struct.unpack_from(f"<{n}I", data)
        assert codes == (0,) * n
        pos = 4 * n
        values = []
        for _name, _axis, plctype, _w in WATCH:
            fmt = FORMAT[plctype]
            values.append(struct.unpack_from(fmt, data, pos)[0])
            pos += struct.calcsize(fmt)
        cycle = values[0]
        for (name, axis, _t, _w), v in zip(WATCH, values, strict=True):
            assert v == expected(name, axis, cycle), (name, cycle)
        if live.sched.engine == "exact":
            assert (a - t0) // 1_000_000 <= cycle <= (b - t0) // 1_000_000, (a, b, cycle)
