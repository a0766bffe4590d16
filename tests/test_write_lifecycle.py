"""A write is answered once a cycle applied it (geo_server/service.py *Writes*): a read
sent after the answer sees the value. Also before cycles that run by themselves have
started: `geo-server run` starts its interfaces first and the cycle after them, and a
write that came in between was answered at once, unapplied — a read right after it
showed the old value (found when OPC UA's start took longer: tests/test_robust_exposure.py
wrote over Modbus as soon as ADS was up)."""

from __future__ import annotations

import asyncio

import pytest
from conftest import run_in

from geo_server import access
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService


@pytest.mark.realtime
def test_a_write_before_the_cycles_start_is_answered_once_applied(
    machine: Machine, loop_thread: asyncio.AbstractEventLoop
) -> None:
    sched = Scheduler(machine, mode="realtime")  # not started yet
    service = ObjectService(machine, sched)
    before = access.read_name(service, "TEMPC::offset_0", 1)
    write = access.write_name_applied(service, "TEMPC::offset_0", 1, before + 5)
    answered = asyncio.run_coroutine_threadsafe(write, loop_thread)
    try:
        while not machine.has_queued():  # (queued on the loop's thread)
            run_in(loop_thread, asyncio.sleep(0))
        for _ in range(3):  # (turns of the loop in which the old code answered)
            run_in(loop_thread, asyncio.sleep(0))
        assert not answered.done()  # nobody ran a cycle: it cannot have been applied
        sched.start()
        assert answered.result(10) == before + 5
        assert access.read_name(service, "TEMPC::offset_0", 1) == before + 5
    finally:
        sched.stop()
