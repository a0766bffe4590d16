"""Real-time scheduler on a virtual clock: catch-up, overruns, skipped cycles (docs/design.md §5).

The loop under test is the production `_run_realtime`; only its clock and sleep are
virtual, so a stall of exactly 5 ms or 30 ms gives exactly the figures worked out below.
"""

from __future__ import annotations

import asyncio
from itertools import pairwise

import pytest

from geo_server import cli
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import CycleStats, Scheduler
from geo_server.service import ObjectService

P = 1_000_000  # 1 ms period in ns
TICK = 1_000  # every clock reading advances virtual time by 1 µs (the spin loop ends)


class VirtualTime:
    def __init__(self) -> None:
        self.t = 10 * P

    def clock(self) -> int:
        self.t += TICK
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += round(seconds * 1e9)


def run_with_stall(cfg, stall_ns: int, stall_at: int = 5, cycles: int = 40):
    """Run `cycles` real-time cycles; cycle `stall_at` takes `stall_ns` of virtual time.
    Returns the scheduler and the virtual start time of every cycle."""
    vt = VirtualTime()
    machine = Machine(cfg, cycle_s=P / 1e9)
    sched = Scheduler(machine, mode="realtime", clock=vt.clock, sleep=vt.sleep)
    starts: list[int] = []
    original = machine.run_cycle

    def cycle():
        starts.append(vt.t)
        snap = original()
        if machine.cycle == stall_at:
            vt.t += stall_ns
        if machine.cycle == cycles:
            sched._stop.set()
        return snap

    machine.run_cycle = cycle  # type: ignore[method-assign]
    t0 = vt.t
    sched._run_realtime()  # the loop itself, in this thread, until the stop above
    return sched, [s - t0 for s in starts]


def test_short_stall_is_caught_up_without_overrun(default_cfg):
    sched, starts = run_with_stall(default_cfg, 5 * P)
    assert sched.machine.cycle == 40
    assert sched.machine.overruns == 0 and sched.skipped == 0
    # Cycle 5 ends 5 ms late; its successors run back to back until the schedule is met
    # again: cycle 6 (deadline 6 ms) starts ≈ 4 ms late, cycle 10 is back on time.
    late = [(s - (i + 1) * P) / 1000 for i, s in enumerate(starts)]  # µs
    assert 3900 < late[5] < 4100
    assert all(x < 100 for x in late[12:])
    st = sched.status()
    assert 3900 < st["lateness_max_us"] < 4100
    assert st["overruns"] == 0 and st["skipped_cycles"] == 0


def test_long_stall_is_one_overrun_and_the_skipped_cycles_are_counted(default_cfg):
    sched, starts = run_with_stall(default_cfg, 30 * P)
    # 30 ms stall: the next deadline is missed by 29 ms > max_catchup (10) periods, so the
    # scheduler resynchronises once and reports the 29 periods it gave up.
    assert sched.machine.overruns == 1
    assert sched.skipped == 29
    assert sched.machine.cycle == 40  # cycles are never dropped silently: all 40 ran
    # After resynchronising, the schedule restarts from the late cycle's start time.
    assert starts[5] - starts[4] > 30 * P  # starts[4] is cycle 5, the stalled one
    assert all(abs(b - a - P) < 100_000 for a, b in pairwise(starts[5:]))
    st = sched.status()
    assert st["overruns"] == 1 and st["skipped_cycles"] == 29


def test_status_reports_kernel_time(default_cfg):
    machine = Machine(default_cfg, cycle_s=0.001, homed=True)
    sched = Scheduler(machine, mode="stepped")
    sched.step(50)
    st = sched.status()
    # The kernel is part of the cycle: it takes time, and less than the whole cycle.
    assert 0 < st["kernel_p50_us"] <= st["cycle_p50_us"]
    assert st["kernel_p50_us"] <= st["kernel_p99_us"]


@pytest.mark.realtime
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_run_ends_with_an_error_when_the_cycle_thread_dies(default_cfg):
    """A defect that kills the cycle thread must not leave `run` serving a frozen
    snapshot: `_serve` raises, `run` exits 1."""

    class Broken:
        count = 0
        generation = 0

        def record(self, *values: float) -> None:
            raise RuntimeError("defect in the cycle thread")

        def summary(self) -> dict[str, float]:
            # `run` may print a status line before it notices the dead thread
            return CycleStats().summary()

    machine = Machine(default_cfg, cycle_s=0.001)
    sched = Scheduler(machine, mode="realtime")
    sched.stats = Broken()  # type: ignore[assignment]
    args = cli.build_parser().parse_args(
        ["run", "--no-zenoh", "--no-modbus", "--no-ads", "--no-opcua", "--status-period", "0.05"]
    )
    with pytest.raises(cli.CycleStoppedError, match="after cycle 1"):
        asyncio.run(cli._serve(args, ObjectService(machine, sched), sched))
    sched.stop()


def test_the_figures_start_again_when_the_compiled_cycle_takes_over(monkeypatch):
    """Issue 45 #17: 300 interpreted cycles of 290 µs, then the machine code loads and
    the cycles take 30 µs: the summary is of the compiled cycles alone (p50 30 µs, not
    290 µs while the machine rests and computes few cycles), the count starts again, and
    a summary taken before any compiled cycle shows none of the interpreted ones."""
    from geo_server import jit

    state = {"loaded": False}
    monkeypatch.setattr(jit, "loaded", lambda: state["loaded"])
    stats = CycleStats(1000)
    for _ in range(300):
        stats.record(5.0, 290.0, 250.0)
    assert stats.summary()["cycle_p50_us"] == 290.0
    state["loaded"] = True
    # a machine at rest records nothing: a summary alone starts the rings again
    assert stats.summary()["cycle_p50_us"] == 0.0 and stats.generation == 1
    for _ in range(3):
        stats.record(1.0, 30.0, 20.0)
    s = stats.summary()
    assert stats.count == 3
    assert (s["cycle_p50_us"], s["kernel_p50_us"], s["lateness_max_us"]) == (30.0, 20.0, 1.0)
