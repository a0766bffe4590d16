"""One cycle thread for a fleet (issue 43 #1, docs/design.md §5.10 *Threads*): the exact
engines of many machines run on the one `geo-cycles` thread of `Engines`, a write to
any machine is applied in its next cycle as with a thread of its own, a machine whose
lock a request holds does not hold up the others, and a machine whose cycle raises
stops alone."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from geo_server import access
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import BATCH, Engines, Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService

pytestmark = pytest.mark.realtime

#: the longest a write waits for its cycle here: a bound of the test's patience, never
#: an assertion about time (the write is applied in the next cycle, 1 ms)
APPLIED_S = 10.0
MACHINES = 3


@pytest.fixture
def fleet() -> Iterator[tuple[Engines, list[ObjectService], list[Scheduler]]]:
    cfg = load_machine(default_startup_list())
    before = set(threading.enumerate())
    engines = Engines()
    services, schedulers = [], []
    for _ in range(MACHINES):
        machine = Machine(cfg, cycle_s=0.001, homed=True)
        schedulers.append(Scheduler(machine, mode="realtime", engine="exact"))
        services.append(ObjectService(machine, schedulers[-1]))
    engines.start()
    for scheduler in schedulers:
        scheduler.start(engines)
    try:
        # the threads these machines run on (not another test's, on this worker)
        started = sorted(t.name for t in set(threading.enumerate()) - before)
        assert started == ["geo-cycles"], started
        yield engines, services, schedulers
    finally:
        for scheduler in schedulers:
            scheduler.stop()
        engines.stop()


def write_coefficient(service: ObjectService, value: float) -> float:
    """TEMPC::coefficient of X written (applied in the machine's next cycle), then read."""
    access.write_name(service, "TEMPC::coefficient", 1, value).result(timeout=APPLIED_S)
    return float(access.read_name(service, "TEMPC::coefficient", 1))


def test_a_fleet_runs_on_one_thread_and_every_machine_applies_its_writes(fleet) -> None:
    _, services, _ = fleet  # (on one thread: the fixture checks it)
    for i, service in enumerate(services):
        assert service.info.running
        assert write_coefficient(service, 4100.0 + i) == 4100.0 + i
    # every machine's time goes on: its cycle counter follows the wall clock, each on
    # its own time line (the machines started one after the other, so one machine's
    # next cycle is no other's: a write to machine 0 may take less than a period, and
    # a read of machine 1 right after it may still be due in the same cycle)
    before = [int(access.read_name(s, "SIM::cycle_count", 0)) for s in services]
    assert write_coefficient(services[0], 4200.0) == 4200.0
    for service, scheduler, cycle in zip(services, fleet[2], before, strict=True):
        while scheduler.due() <= cycle:  # (a period at most: bounded by the clock)
            time.sleep(0.0005)
        assert int(access.read_name(service, "SIM::cycle_count", 0)) > cycle


def test_a_machine_held_by_a_request_does_not_hold_up_the_others(fleet) -> None:
    """Machine 0's engine lock held (a request's long catch-up): the shared thread skips
    it and machines 1 and 2 still apply their writes."""
    _, services, schedulers = fleet
    held = schedulers[0]._engine_lock
    held.acquire()
    try:
        assert write_coefficient(services[1], 4321.0) == 4321.0
        assert write_coefficient(services[2], 4322.0) == 4322.0
    finally:
        held.release()
    assert write_coefficient(services[0], 4323.0) == 4323.0


def test_a_machine_whose_cycle_raises_stops_alone(fleet, monkeypatch, caplog) -> None:
    _, services, schedulers = fleet
    broken = schedulers[1]

    def fail(blocking: bool) -> int:
        raise RuntimeError("a broken cycle")

    monkeypatch.setattr(broken, "run_pass", fail)
    broken._poke()  # (looked at at once)
    for _ in range(1000):  # the thread takes it out at its next pass
        if not broken.running:
            break
        threading.Event().wait(0.01)
    assert not broken.running
    assert "the GEO cycle of a machine failed" in caplog.text
    assert schedulers[0].running and schedulers[2].running
    assert write_coefficient(services[2], 4400.0) == 4400.0


def test_a_machine_whose_cycles_fail_is_not_looked_at_again_at_once(fleet, monkeypatch) -> None:
    """Machine 1's cycle fails every time (logged and counted; the machine stays where it
    is) while observers want every cycle of machines 0 and 1: the broken machine's
    engine looks again a batch later, not at once, so the healthy machine keeps
    getting its passes (a busy loop on the broken one starved it: 2 passes to the
    broken one's thousands, review) and the other machines still apply their writes."""
    _, services, schedulers = fleet
    healthy, broken = schedulers[0], schedulers[1]

    def fail(*args: object, **kwargs: object) -> None:
        raise RuntimeError("a broken cycle")

    monkeypatch.setattr(broken.machine, "run_cycle", fail)
    monkeypatch.setattr(broken.machine, "run_batch", fail)
    releases = [healthy.demand_every_cycle(), broken.demand_every_cycle()]
    try:
        start, wakes = broken.due(), (healthy.wakes, broken.wakes)
        while broken.due() < start + 200:  # (200 periods of its time line)
            threading.Event().wait(0.01)
        passes = (healthy.wakes - wakes[0], broken.wakes - wakes[1])
        elapsed = broken.due() - start
        assert broken.cycle_errors > 0
        # the broken one: once a batch; the healthy one, observed every cycle and asked
        # nothing: once a batch too (its snapshots published in the batch), at least
        # half of those
        assert passes[1] <= 2 * (elapsed // BATCH) + 10, passes
        assert passes[0] >= elapsed // BATCH // 2, passes
        assert write_coefficient(services[0], 4500.0) == 4500.0
        assert write_coefficient(services[2], 4501.0) == 4501.0
    finally:
        for release in releases:
            release()
