"""The observation-exact engine (docs/design.md §13), piece by piece, without sockets.

- skipping the cycles of a quiescent machine gives, bit for bit, the snapshots that
  running them gives (twin thermal model, sensors with seeded noise, the ambient
  profile's knots, the spindle, a climate chamber);
- cycles computed without publishing, then published, equal cycles published one by one
  (deltas, twin outputs) while axes move, reverse and compensations ramp;
- driven by a virtual clock, the engine shows an observer at time t the cycle
  floor((t − t0)/T) and applies a write arriving at t in the cycle after it: the same
  snapshots, cycle for cycle, as stepped mode with the write queued at that cycle.
"""

from __future__ import annotations

import math
import random
import struct
import threading
import time

import numpy as np
import pytest
from support.fakes import VirtualClock

from geo_server import access
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.nc import parse_program
from geo_server.machine.port import StartProgram, WriteObjects
from geo_server.machine.scheduler import Scheduler
from geo_server.model import Diagnostic
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService, ServiceLimits
from geo_server.twin.laws import ambient_at

P = 1_000_000  # 1 ms in ns
MOVES = "N10 G90 G01 X120 Y-40 F6000\nN20 X-30 Y25\nN30 G04 X0.02\nN40 X60 Z-10\nM30\n"


@pytest.fixture(scope="module")
def cfg():
    return load_machine(default_startup_list())


def same(a, b) -> None:
    """Two snapshots, value for value (bit for bit), counters and stamp included."""
    assert a.cycle == b.cycle
    assert np.array_equal(a.values, b.values), np.argwhere(a.values != b.values)[:5]
    assert np.array_equal(a.machine, b.machine), (a.machine, b.machine)
    assert a.texts == b.texts
    assert a.stamp == b.stamp


def pair(cfg, **kw) -> tuple[Machine, Machine]:
    a, b = Machine(cfg, homed=True, **kw), Machine(cfg, homed=True, **kw)
    b.set_epoch(a.epoch)
    return a, b


@pytest.mark.slow
@pytest.mark.parametrize(
    "time_scale, setup",
    [
        (None, ()),  # the twin file's own time scale: sensors every 0.1 s of 10 ms
        (1000.0, ()),  # 2 h 40 min of twin time: every knot of the ambient profile
        (1000.0, (("TWIN::spindle_on", 0, True),)),  # heat from the spindle
        (50.0, (("TWIN::ambient_temperature", 0, 27.5),)),  # a climate chamber
    ],
)
def test_skipping_a_quiescent_machine_is_running_it(cfg, time_scale, setup) -> None:
    a, b = pair(cfg, time_scale=time_scale)
    for m in (a, b):
        if setup:
            m.submit(WriteObjects(setup))
        m.step(40)
    rng = random.Random(7)
    total = 0
    while total < 10_000:
        n = rng.choice((1, 2, 3, 9, 10, 11, 99, 100, 101, rng.randint(1, 3000)))
        total += n
        a.step(n)
        assert b.quiescent
        b.skip(n)
        same(a.snapshot, b.publish())
    assert a.twin.time == b.twin.time and a.twin.time > 0
    # the run really had the events the skip must reproduce
    assert len(set(a.twin.sensor_value.tolist())) > 1 or setup


def test_a_machine_that_moves_or_ramps_is_not_quiescent(cfg) -> None:
    m = Machine(cfg, homed=True)
    m.step(40)
    assert m.quiescent
    m.start_program(MOVES)
    assert not m.quiescent  # an operation waits
    m.step(2)
    assert not m.quiescent  # a program runs, axes move
    while m.player.running and m.cycle < 30_000:
        m.step(100)
    assert not m.player.running
    assert not m.quiescent  # the friction delay line still carries the last motion
    m.step(250)  # ... for its 249 cycles (000 p.79: delay_cycles < 249)
    assert m.quiescent
    m.submit(WriteObjects((("TEMPC::offset_0", 1, 250),)))
    m.step(3)
    assert not m.quiescent  # the sin² ramp of the new offset runs
    m.step(500)
    assert m.quiescent


def test_compiled_ambient_is_np_interp() -> None:
    """The twin's ambient profile follows `np.interp` (linear, held outside), compiled."""
    xp = [0.0, 7200.0, 14400.0, 20000.5]
    fp = [20.0, 23.0, 23.0, 19.25]
    amb = np.array([xp, fp])
    rng = random.Random(3)
    xs = [*xp, -1.0, 1e9, *(rng.uniform(-100, 21000) for _ in range(5000))]
    xs += [math.nextafter(x, math.inf) for x in xp] + [math.nextafter(x, -math.inf) for x in xp]
    for x in xs:
        assert ambient_at(x, amb) == float(np.interp(x, xp, fp)), x
    assert ambient_at(5.0, np.array([[1.0], [4.0]])) == float(np.interp(5.0, [1.0], [4.0]))


def test_unpublished_cycles_then_published_are_the_same_snapshots(cfg) -> None:
    a, b = pair(cfg)
    for m in (a, b):
        m.step(5)
        m.start_program(MOVES)
        m.submit(WriteObjects((("TEMPC::offset_0", 1, 40),)))  # a ramp while moving
    rng = random.Random(11)
    published = 0
    while a.player is None or a.player.running or published < 3:
        n = rng.randint(1, 9)
        for _ in range(n - 1):
            b.run_cycle(publish=False)
        b.run_cycle()
        a.step(n)
        same(a.snapshot, b.snapshot)
        published += 1
    assert np.any(a.snapshot.values != 0)


def driven(cfg) -> tuple[VirtualClock, Machine, Scheduler]:
    """A homed machine under the exact engine, driven by a virtual clock (observers
    catch up on their own thread): the clock, the machine, its scheduler."""
    vc = VirtualClock()
    m = Machine(cfg, homed=True)
    sched = Scheduler(m, mode="realtime", engine="exact", clock=vc.clock, sleep=vc.sleep)
    sched.drive()
    return vc, m, sched


@pytest.mark.realtime
def test_exact_engine_shows_the_cycle_due_and_applies_writes_in_the_next(cfg) -> None:
    """Observations at chosen (virtual) instants against a stepped twin of the machine."""
    vc = VirtualClock()
    live = Machine(cfg, homed=True)
    ref = Machine(cfg, homed=True)
    sched = Scheduler(live, mode="realtime", engine="exact", clock=vc.clock, sleep=vc.sleep)
    sched.drive()
    ref.set_epoch(live.epoch)
    t0 = sched.t0
    assert t0 == vc.t and live.cycle == 0

    def look(at_us: int):
        """An observer at t0 + at_us µs: the snapshot it is served."""
        vc.t = t0 + at_us * 1000
        sched.sync()
        return live.snapshot

    def ref_at(cycle: int):
        ref.step(cycle - ref.cycle)
        return ref.snapshot

    # idle: cycle floor(t/T), whatever was skipped
    for at in (999, 1000, 1001, 12_500, 250_000, 250_999):
        snap = look(at)
        assert snap.cycle == at // 1000
        same(snap, ref_at(snap.cycle))
    # a program arriving at 250.9995 ms is started in cycle 251, a write at 400.2 ms
    # is applied in cycle 401 — in both machines
    vc.t = t0 + 250_999_500
    start = StartProgram(parse_program(MOVES, live.names))
    done = sched.submit(start)
    assert not done.done()
    ref.submit(start)
    snap = look(251_000)
    assert done.done() and snap.cycle == 251
    same(snap, ref_at(251))
    for at in range(251_300, 400_000, 7_300):
        snap = look(at)
        same(snap, ref_at(at // 1000))
    vc.t = t0 + 400_200_000
    write = WriteObjects((("TEMPC::offset_0", 1, 75),))
    w = sched.submit(write)
    ref_at(400)
    ref.submit(write)
    assert look(400_999).cycle == 400 and not w.done()
    snap = look(401_000)
    assert w.done() and snap.value(live.dictionary.by_name("TEMPC::offset_0"), 1) == 75
    same(snap, ref_at(401))
    for at in (401_001, 402_000, 433_333, *range(900_000, 5_000_000, 777_777)):
        snap = look(at)
        same(snap, ref_at(at // 1000))


def test_every_cycle_is_published_while_someone_samples_every_cycle(cfg) -> None:
    vc, m, sched = driven(cfg)
    seen: list[tuple[int, int]] = []
    m.subscribe(lambda snap: seen.append((snap.cycle, snap.stamp)))
    vc.t += 50 * P
    sched.sync()
    assert [c for c, _ in seen] == [50]  # at rest and unobserved: one snapshot
    release = sched.demand_every_cycle()
    vc.t += 30 * P
    sched.sync()
    assert seen[1:] == [(c, m.epoch + c * 10_000) for c in range(51, 81)]
    release()
    release()  # (twice is harmless)
    vc.t += 30 * P
    sched.sync()
    assert [c for c, _ in seen[31:]] == [110]


def test_a_cycle_the_engine_computed_unpublished_is_published_to_the_observer(cfg) -> None:
    """The engine's own wake-up computes cycles without publishing them (a moving
    machine, nobody looking); an observer arriving in the cycle the engine reached must
    still be served that cycle, not the last one published (it was once served the
    cycle before under load: the sync found nothing left to compute and published
    nothing)."""
    vc, m, sched = driven(cfg)
    m.submit(WriteObjects((("SIM::target_position", 1, 50_000.0),)))  # X moves 5 mm
    vc.t += 10 * P
    sched.sync()
    assert m.snapshot.cycle == 10 and not m.quiescent
    vc.t += 7 * P
    with sched._engine_lock:  # what `_run_exact` does on its wake-up
        sched.advance(sched.due(), publish=False)
    assert m.cycle == 17 and m.snapshot.cycle < 17
    sched.sync()
    assert m.snapshot.cycle == 17


def test_an_axis_without_friction_stops_inside_a_thermal_window(cfg) -> None:
    """Y has no friction (nothing in the kernel's delay line): the machine is at rest as
    soon as Y stands, but the motion heat Y gathered since the last thermal update is
    still to be applied — the skip must wait for it to be, or the node differs."""
    a, b = pair(cfg)
    for m in (a, b):
        m.step(40)
        m.submit(WriteObjects((("SIM::target_position", 2, 20_000.0),)))  # 2 mm
    for _ in range(5000):
        a.step(1)
        b.step(1)
        if b.quiescent:
            break
    assert b.quiescent and a.cycle == b.cycle
    for n in (3, 7, 250, 999):
        a.step(n)
        b.skip(n)
        same(a.snapshot, b.publish())
    assert a.twin.node_temp.tolist() == b.twin.node_temp.tolist()


def test_a_catch_up_that_cannot_happen_in_time_is_not_served_as_current(cfg) -> None:
    """Another thread holds the engine (a long catch-up after the host stalled): a read
    is refused with 0x707 instead of being served an old snapshot, a write is refused
    instead of landing in a cycle of the past."""
    import threading

    from geo_server.errors import AdsError
    from geo_server.service import ObjectService

    vc, m, sched = driven(cfg)
    svc = ObjectService(m, sched)
    vc.t += 5 * P
    assert access.read_name(svc, "SIM::cycle_count") == 5
    held, release = threading.Event(), threading.Event()

    def hold() -> None:
        with sched._engine_lock:
            held.set()
            release.wait(5)

    t = threading.Thread(target=hold)
    t.start()
    try:
        assert held.wait(5)
        vc.t += 5 * P
        with pytest.raises(AdsError) as err:
            access.read_name(svc, "SIM::cycle_count")
        assert err.value.code == 0x707
        with pytest.raises(AdsError) as err:
            access.write_name(svc, "TEMPC::offset_0", 1, 60)
        assert err.value.code == 0x707
    finally:
        release.set()
        t.join(5)
    assert access.read_name(svc, "SIM::cycle_count") == 10


def test_a_status_is_an_observation_too(cfg) -> None:
    """`status()` (Zenoh `cnc/<m>/status`, `cnc/fleet/status`, the run's status line)
    tells the cycle due now, not the last one the sleeping engine happened to compute:
    a machine at rest for 610.5 periods reads cycle 610; a server's own error is
    listed with the cycle due when it came."""
    from geo_server.service import ObjectService

    vc, m, sched = driven(cfg)
    svc = ObjectService(m, sched)
    vc.t += 10 * P
    assert svc.status()["cycle"] == 10
    vc.t += 600 * P + P // 2
    assert m.cycle == 10  # nobody looked since
    assert svc.status()["cycle"] == 610
    vc.t += 66 * P
    assert svc.status()["cycle"] == 676
    # so is an error the server itself reports: it carries the cycle due when it came
    vc.t += 123 * P
    svc.report("a second server answers for this machine")
    assert svc.errors()[-1]["cycle"] == 799


def test_a_machine_at_rest_far_behind_is_skipped_not_given_up(cfg) -> None:
    """A freshly homed machine is not yet quiescent: its temperature compensation ramps
    in over 20 cycles (a sin² ramp), then two cycles at rest make it so. Found more
    than `max_lag` (a second) behind — a fleet starting a hundred machines at once — it
    computes those cycles and skips the rest: the cycle due, no overrun. A moving
    machine that far behind still gives its cycles up (one overrun)."""
    vc, m, sched = driven(cfg)
    assert not m.quiescent and sched.max_lag == 1000
    vc.t += 5000 * P + P // 2
    sched.sync()
    assert (m.cycle, m.overruns, sched.skipped) == (5000, 0, 0)
    # the same machine moving (X to 100 mm at 100 mm/s takes a second), 3 s behind
    _moving_and_behind(vc, m, sched, 3000)
    assert m.overruns == 1 and sched.skipped > 0


def test_a_machine_settled_after_a_stall_publishes_what_its_observers_want(cfg) -> None:
    """Far behind, a freshly homed machine computes the cycles that make it quiescent
    before it skips the rest (above) — and those cycles are published like any other
    to an observer of every cycle (ADS cyclic notifications in the cycle process) and
    to one of chosen cycles: a cyclic stream keeps no gap. (Before, the settling cycles
    were computed unpublished: a notification every 3 cycles, its cycle process held 60
    ms by a busy host, sampled cycles 26, 29, 32, 37.)"""
    vc, m, sched = driven(cfg)
    seen: list[int] = []
    m.subscribe(lambda snap: seen.append(snap.cycle))
    release = sched.demand_every_cycle()
    vc.t += 1500 * P + P // 2
    sched.sync()
    assert (m.cycle, m.overruns) == (1500, 0)
    assert seen == list(range(1, 1501))
    release()

    class EveryThird:  # a `CycleDemand`: cycles 3, 6, 9, ... (at rest too)
        def wants(self, cycle: int, quiescent: bool) -> bool:
            return cycle % 3 == 0

        def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
            return cycle + 3 - cycle % 3

    vc, m, sched = driven(cfg)
    seen.clear()
    m.subscribe(lambda snap: seen.append(snap.cycle))
    sched.demand_cycles(EveryThird())
    vc.t += 1500 * P + P // 2
    sched.sync()
    assert (m.cycle, m.overruns) == (1500, 0)
    assert [c for c in seen if c % 3 == 0] == list(range(3, 1501, 3))


def _moving_and_behind(vc: VirtualClock, m: Machine, sched: Scheduler, cycles: int) -> None:
    """X set moving to 100 mm (a second at 100 mm/s), two cycles on, then the clock
    `cycles` periods ahead and one catch-up."""
    m.submit(WriteObjects((("SIM::target_position", 1, 1_000_000.0),)))
    vc.t += 2 * P
    sched.sync()
    assert not m.quiescent
    vc.t += cycles * P
    sched.sync()


def test_while_interpreted_a_catch_up_computes_a_twentieth_of_a_second(cfg, monkeypatch) -> None:
    """While the cycle still runs interpreted, one catch-up computes at most 0.05 s of
    cycles (50 of 1 ms): a moving machine 0.2 s behind gives the cycles up (one overrun)
    instead of holding the engine for 200 interpreted cycles, longer than a write waits
    for it on a busy host (before: a second of cycles, and a write right after the
    start was refused 0x707). Compiled, the same lag is computed."""
    from geo_server import jit

    loaded = [False]
    monkeypatch.setattr(jit, "loaded", lambda: loaded[0])
    # (cycles computed, overruns, cycles given up): 199 of the 200 given up, the time
    # line slipped by them (the machine's count is of computed cycles)
    for compiled, outcome in ((False, (3, 1, 199)), (True, (202, 0, 0))):
        loaded[0] = compiled
        vc, m, sched = driven(cfg)
        assert sched.max_lag == (1000 if compiled else 50)
        _moving_and_behind(vc, m, sched, 200)
        assert (m.cycle, m.overruns, sched.skipped) == outcome


@pytest.mark.realtime
def test_a_machine_at_rest_wakes_every_second_compiled_every_tenth_interpreted(
    cfg, monkeypatch
) -> None:
    """At rest the engine sleeps `IDLE_WAKE` (1 s) between catch-ups; while the laws
    still run interpreted a second of rest is slow to catch up, so it wakes every 0.1 s
    (what a request or the stall watch would otherwise wait for)."""
    from geo_server import jit

    vc = VirtualClock()
    sched = Scheduler(
        Machine(cfg, homed=True), mode="realtime", engine="exact", clock=vc.clock, sleep=vc.sleep
    )
    sched.drive()
    for _ in range(100):  # a homed machine comes to rest within a few cycles
        vc.t += 10 * P
        sched.sync()
        if sched.machine.quiescent:
            break
    assert sched.machine.quiescent
    now = vc.t
    assert sched._next_wake(now) == now + 1_000_000_000
    monkeypatch.setattr(jit, "loaded", lambda: False)
    assert sched._next_wake(now) == now + 100_000_000


def test_a_read_of_a_value_that_cannot_change_at_rest_catches_nothing_up(cfg) -> None:
    """docs/design.md §13, *Reads at rest*: on a quiescent machine whose snapshot was
    published at rest, a read of an object that cannot vary at rest (TEMPC::offset_0) is
    answered from that snapshot without catching up — no cycle skipped, none computed —
    with the value of the cycle due; a read of the cycle counter catches up to that
    cycle; a write queued at rest is seen in the very cycle it is applied in."""
    vc, m, sched = driven(cfg)
    # (a heartbeat counts as fresh for 30 s: a slow host cannot make the read catch up)
    svc = ObjectService(m, sched, ServiceLimits(stall_after=60.0))
    offset = m.dictionary.by_name("TEMPC::offset_0")
    count = m.dictionary.by_name("SIM::cycle_count")
    addr = (offset.index_group, offset.index_offset(1))
    m.submit(WriteObjects((("TEMPC::offset_0", 1, -250),)))
    vc.t += 100 * P  # the write applied, the ramps run out: quiescent
    assert svc.current().cycle == m.cycle
    assert m.quiescent and sched.shows_rest()

    cycle, computed = m.cycle, sched.computed
    vc.t += 5000 * P
    assert svc.read(*addr) == struct.pack("<i", -250)
    assert (m.cycle, sched.computed) == (cycle, computed)  # nothing caught up
    assert svc.read(count.index_group, count.index_offset(0)) == struct.pack("<I", cycle + 5000)
    assert m.cycle == cycle + 5000 and sched.computed == computed  # skipped, not computed

    sched.submit(WriteObjects((("TEMPC::offset_0", 1, 125),)))  # lands in the next cycle
    assert not sched.shows_rest()
    assert svc.read(*addr) == struct.pack("<i", -250)  # the cycle due now: not yet
    vc.t += P
    assert svc.read(*addr) == struct.pack("<i", 125)  # the cycle that applied it
    assert m.cycle == cycle + 5001 and sched.computed == computed + 1


def test_the_rest_snapshot_is_the_published_one_only_while_the_machine_shows_its_rest(
    cfg,
) -> None:
    """docs/design.md §13, *Repeated reads*: `Machine.rest_snapshot` is what a read at
    rest is answered from, kept by the cycle instead of looked up on every request. It
    is the published snapshot while the machine shows its rest and None from the moment
    anything could change that: an operation queued (before any cycle), a cycle
    computed. A snapshot re-issued at rest (an error recorded) is the rest snapshot at
    once, and a read of its error id takes it without catching up."""
    vc, m, sched = driven(cfg)
    svc = ObjectService(m, sched, ServiceLimits(stall_after=60.0))
    error_id = m.dictionary.by_name("SIM::last_error_id")
    vc.t += 100 * P
    assert svc.current().cycle == m.cycle
    first = m.snapshot
    assert m.rest_snapshot is first

    m.record(Diagnostic("warning", "a warning", error_id=70435)).result(timeout=1)
    assert m.snapshot is not first and m.rest_snapshot is m.snapshot
    cycle, computed = m.cycle, sched.computed
    vc.t += 5000 * P
    assert svc.read(error_id.index_group, error_id.index_offset(0)) == struct.pack("<I", 70435)
    assert (m.cycle, sched.computed) == (cycle, computed)  # from the rest snapshot

    pending = sched.submit(WriteObjects((("TEMPC::offset_0", 1, 125),)))
    assert m.rest_snapshot is None and not sched.shows_rest()  # queued, not yet applied
    vc.t += P
    svc.current()
    assert pending.done() and m.rest_snapshot is None  # computed: not at rest yet
    vc.t += 100 * P
    assert svc.current() is m.snapshot is m.rest_snapshot  # at rest again
    m.run_cycle(publish=False)  # a cycle computed (of a batch: nothing published)
    assert not m.shows_rest() and m.rest_snapshot is None


def test_an_operation_queued_while_a_snapshot_is_published_is_never_missed(cfg) -> None:
    """`Machine._show` sets the rest snapshot after it found the machine at rest; an
    operation queued in between (another thread's `submit`, which clears the rest
    snapshot after queueing) leaves it None all the same: a read after `submit` returned
    never takes the snapshot of a machine with something queued."""
    vc, m, sched = driven(cfg)
    vc.t += 100 * P
    sched.sync()
    assert m.quiescent
    shows_rest = m.shows_rest
    queued = []

    def racing() -> bool:
        at_rest = shows_rest()
        if at_rest and not queued:  # a submit lands after the look, before the setting
            queued.append(m.submit(WriteObjects((("TEMPC::offset_0", 1, 125),))))
        return at_rest

    m.shows_rest = racing  # type: ignore[method-assign]
    vc.t += 1000 * P
    sched.sync()  # (skips to the cycle due and publishes its snapshot: `_show`)
    assert queued and m.rest_snapshot is None


@pytest.mark.realtime
def test_a_read_at_rest_with_an_old_heartbeat_waits_for_the_wake_under_way(cfg) -> None:
    """The engine on its thread, at rest, wakes once a second (docs/design.md §13, *Reads
    at rest*). A read of a constant that arrives while the heartbeat is older than half
    of `stall_after` and the engine holds its lock (a wake under way; here the test holds
    it for 50 ms) catches up, waiting for it, and answers — it is no stall (0x707)."""
    m = Machine(cfg, homed=True)
    sched = Scheduler(m, mode="realtime", engine="exact")
    svc = ObjectService(m, sched)
    sched.start()
    try:
        sched.submit(WriteObjects((("TEMPC::offset_0", 1, -250),))).result(timeout=5)
        deadline = time.monotonic() + 10
        while not sched.shows_rest():
            assert time.monotonic() < deadline, "the machine never came to rest"
            time.sleep(0.01)
            svc.current()
        time.sleep(0.6)  # longer than stall_after since the service's first look
        offset = m.dictionary.by_name("TEMPC::offset_0")
        held = threading.Event()

        old: list[float] = []

        def wake_under_way() -> None:
            with sched._engine_lock:
                m.heartbeat -= 10.0  # (under the lock: the engine cannot refresh it)
                old.append(m.heartbeat)
                held.set()
                time.sleep(0.05)

        waker = threading.Thread(target=wake_under_way)
        waker.start()
        assert held.wait(5)
        assert svc.read(offset.index_group, offset.index_offset(1)) == struct.pack("<i", -250)
        assert m.heartbeat > old[0]  # caught up: the cycle advanced since
        waker.join()
    finally:
        sched.stop()


def test_current_if_due_never_catches_up(cfg) -> None:
    """`ObjectService.current_if_due` (what OPC UA's niced thread asks, docs/design.md
    §9.1): at t0 + 0.5 ms, cycle 0 is due and published, so it is answered without a
    catch-up; at t0 + 3.5 ms cycle 3 is due and not computed: None, and nothing was
    computed by asking (the machine is still at cycle 0); after `current()` (which
    catches up) cycle 3 again. A stepped machine (no engine) always is."""
    vc, m, sched = driven(cfg)
    service = ObjectService(m, sched)
    t0 = sched.t0
    vc.t = t0 + 500_000
    snap = service.current_if_due()
    assert snap is not None and snap.cycle == 0
    vc.t = t0 + 3_500_000
    assert service.current_if_due() is None
    assert m.cycle == 0  # (asking computed nothing)
    assert service.current().cycle == 3
    assert service.current_if_due() is service.current()
    still = Machine(cfg, homed=True)
    assert ObjectService(still).current_if_due() is still.snapshot


def test_a_catch_up_hands_its_snapshots_out_together_after_its_last_cycle(cfg) -> None:
    """A catch-up's snapshots reach the listeners in their order, each one, but only once
    its last cycle is reached (`Machine.held_back`): a listener that wakes a thread of
    its own (OPC UA's process, ADS notifications) wakes it once per catch-up — woken at
    the first cycle, that thread took the interpreter lock at each later cycle's
    compiled calls. At rest (skipped cycles, a `CycleDemand` of every cycle) and moving
    (computed cycles, an observer of every cycle) alike. (Before, each listener was
    called as its cycle was published: the machine stood at that cycle.)"""

    class EveryCycle:  # a `CycleDemand`: every cycle, at rest too
        def wants(self, cycle: int, quiescent: bool) -> bool:
            return True

        def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
            return cycle + 1

    vc, m, sched = driven(cfg)
    vc.t += 30 * P + P // 2  # (quiescent from cycle 22 on)
    sched.sync()
    assert m.quiescent and m.cycle == 30
    calls: list[tuple[int, int]] = []  # (the snapshot's cycle, the machine's then)
    m.subscribe(lambda snap: calls.append((snap.cycle, m.cycle)))
    release = sched.demand_cycles(EveryCycle())
    vc.t += 16 * P
    sched.sync()
    assert calls == [(c, 46) for c in range(31, 47)]
    release()

    calls.clear()
    every = sched.demand_every_cycle()
    m.submit(WriteObjects((("SIM::target_position", 1, 1_000_000.0),)))
    vc.t += P
    sched.sync()  # (the write's cycle: handed out at once, its acknowledgement waits)
    assert calls == [(47, 47)]
    calls.clear()
    vc.t += 8 * P
    sched.sync()
    assert not m.quiescent
    assert calls == [(c, 55) for c in range(48, 56)]
    every()


def test_a_cycle_that_applies_an_operation_hands_out_the_held_snapshots_first(cfg) -> None:
    """Inside `held_back`, a cycle that applies an operation hands the snapshots held so
    far to the listeners before the operation is acknowledged, and its own right after:
    the cycle process sends each acknowledgement with the next snapshot it hands out,
    and the snapshot that shows a write must not come after its acknowledgement's."""
    m = Machine(cfg, homed=True)
    for _ in range(5):
        m.run_cycle()
    order: list[object] = []
    m.subscribe(lambda snap: order.append(snap.cycle))
    with m.held_back():
        for _ in range(2):
            m.skip(1)
            m.publish()
        assert order == []
        with m.held_back():  # (nested: the outermost hands out)
            m.skip(1)
            m.publish()
        assert order == []
        pending = m.submit(WriteObjects((("SIM::target_position", 1, 1000.0),)))
        pending.add_done_callback(lambda _p: order.append("ack"))
        m.run_cycle()
        assert order == [6, 7, 8, "ack", 9]
        m.run_cycle()
        assert order == [6, 7, 8, "ack", 9]
    assert order == [6, 7, 8, "ack", 9, 10]


class _EveryCycle:  # a `CycleDemand`: every cycle, at rest too
    def wants(self, cycle: int, quiescent: bool) -> bool:
        return True

    def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
        return cycle + 1


def test_a_long_catch_up_hands_out_every_held_max_snapshots(cfg) -> None:
    """A catch-up holds back at most `seam.HELD_MAX` (16) snapshots: a long one (a host
    that stalled) hands them out every 16 — what waits for a listener stays bounded,
    and its own count of it (ADS's `sample_backlog`) lags by at most that many."""
    vc, m, sched = driven(cfg)
    vc.t += 30 * P + P // 2
    sched.sync()
    calls: list[tuple[int, int]] = []
    m.subscribe(lambda snap: calls.append((snap.cycle, m.cycle)))
    release = sched.demand_cycles(_EveryCycle())
    vc.t += 40 * P
    sched.sync()
    assert calls == (
        [(c, 46) for c in range(31, 47)]
        + [(c, 62) for c in range(47, 63)]
        + [(c, 70) for c in range(63, 71)]
    )
    release()


def test_a_listener_that_catches_up_again_misses_nothing(cfg) -> None:
    """A listener may read through the service on the engine's thread, and that catch-up
    (the engine lock is re-entrant) publishes inside the hand-out: its snapshots are
    held and handed out too, after the others, none lost."""
    vc, m, sched = driven(cfg)
    vc.t += 30 * P + P // 2
    sched.sync()
    seen: list[int] = []

    def reads_again(snap) -> None:
        seen.append(snap.cycle)
        if snap.cycle == 31:
            vc.t += 2 * P
            sched.sync()

    m.subscribe(reads_again)
    release = sched.demand_cycles(_EveryCycle())
    vc.t += 4 * P
    sched.sync()
    assert seen == [31, 32, 33, 34, 35, 36]
    release()


def test_a_listener_that_raises_past_exception_does_not_stop_the_hand_out_for_good(cfg) -> None:
    """A listener that raises a BaseException (a KeyboardInterrupt on the thread that
    drives the machine) ends that hand-out, not the next ones: a later snapshot reaches
    the listeners at once again."""
    m = Machine(cfg, homed=True)
    for _ in range(5):
        m.run_cycle()
    seen: list[int] = []

    def interrupted(snap) -> None:
        seen.append(snap.cycle)
        if snap.cycle == 6:
            raise KeyboardInterrupt

    m.subscribe(interrupted)
    with pytest.raises(KeyboardInterrupt), m.held_back():
        m.skip(1)
        m.publish()
    m.skip(1)
    m.publish()
    assert seen == [6, 7]
