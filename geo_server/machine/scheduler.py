"""When GEO cycles run: stepped, free-running or real time (docs/design.md §5).

- **stepped**: no thread; cycles run only when `step(n)` is called (tests: deterministic).
- **free**: a thread runs cycles back to back as fast as it can (benchmarks).
- **realtime**: a thread runs one cycle per period on a monotonic-clock deadline.
  The wait sleeps until a *spin margin* before the deadline and then spins: a sleep
  alone wakes up hundreds of µs late on a loaded host (docs/design.md §5). The margin
  adapts, because how far `time.sleep` overshoots differs from host to host: a sleep
  that overshoots into the margin widens it (up to 60 % of the period), a long run of
  punctual wake-ups narrows it again. When it is late the scheduler
  runs the missed cycles back to back; beyond `max_catchup` missed cycles it
  resynchronises to the clock and counts an **overrun** — never a silent drop.

Filters and timings are counted in cycles, so every mode yields the same object values
at the same cycle numbers.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from geo_server.machine.machine import Machine

log = logging.getLogger(__name__)

SPIN_NS = 400_000  # initial spin margin; adapted to the sleeps this machine delivers
SPIN_MIN_NS = 150_000
MODES = ("stepped", "free", "realtime")


class CycleStats:
    """Ring buffers of lateness, whole-cycle time and kernel time (µs) for percentiles."""

    def __init__(self, size: int = 10_000) -> None:
        self.lateness = np.zeros(size)
        self.cycle_time = np.zeros(size)
        self.kernel_time = np.zeros(size)
        self.count = 0
        self.max_lateness = 0.0

    def record(self, lateness_us: float, cycle_us: float, kernel_us: float = 0.0) -> None:
        i = self.count % len(self.lateness)
        self.lateness[i] = lateness_us
        self.cycle_time[i] = cycle_us
        self.kernel_time[i] = kernel_us
        self.count += 1
        self.max_lateness = max(self.max_lateness, lateness_us)

    def summary(self) -> dict[str, float]:
        n = min(self.count, len(self.lateness))
        if n == 0:
            return {
                "lateness_p50_us": 0.0,
                "lateness_p99_us": 0.0,
                "lateness_max_us": 0.0,
                "cycle_p50_us": 0.0,
                "cycle_p99_us": 0.0,
                "kernel_p50_us": 0.0,
                "kernel_p99_us": 0.0,
            }
        lat50, lat99 = np.percentile(self.lateness[:n], (50, 99))
        cyc50, cyc99 = np.percentile(self.cycle_time[:n], (50, 99))
        ker50, ker99 = np.percentile(self.kernel_time[:n], (50, 99))
        return {
            "lateness_p50_us": float(lat50),
            "lateness_p99_us": float(lat99),
            "lateness_max_us": float(self.max_lateness),
            "cycle_p50_us": float(cyc50),
            "cycle_p99_us": float(cyc99),
            "kernel_p50_us": float(ker50),
            "kernel_p99_us": float(ker99),
        }


class Scheduler:
    """Runs a `Machine`'s cycles in one of `MODES`."""

    def __init__(
        self,
        machine: Machine,
        mode: str = "realtime",
        max_catchup: int = 10,
        clock: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], None] = time.sleep,
        max_cycles: int = 0,
    ) -> None:
        """`clock` (ns) and `sleep` (s) are the real-time loop's view of time; tests pass
        a virtual clock to make catch-up and overruns deterministic. With `max_cycles` the
        cycle thread ends by itself once the machine has run that many cycles."""
        if mode not in MODES:
            raise ValueError(f"scheduler mode must be one of {MODES}, not {mode!r}")
        self.machine = machine
        self.mode = mode
        self.max_catchup = max_catchup
        self.max_cycles = max_cycles
        #: Called on the cycle thread right before each cycle (the process mode drains
        #: its command channel here, so queued writes land in this cycle).
        self.before_cycle: Callable[[], None] | None = None
        self._clock = clock
        self._sleep = sleep
        self.stats = CycleStats()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.spin_ns = SPIN_NS
        self.cycle_errors = 0
        self.skipped = 0
        self._summary: tuple[int, dict[str, float]] = (-1, {})
        self._punctual = 0

    @property
    def period_ns(self) -> int:
        return round(self.machine.cycle_s * 1e9)

    # ------------------------------------------------------------------ control

    def start(self) -> None:
        """Start the cycle thread (free / realtime); nothing to do when stepped."""
        if self.mode == "stepped" or self._thread is not None:
            return
        # A short GIL switch interval keeps the cycle thread from being starved by the
        # transports' threads (docs/design.md §5).
        sys.setswitchinterval(0.0002)
        self._stop.clear()
        target = self._run_free if self.mode == "free" else self._run_realtime
        self._thread = threading.Thread(target=target, name="geo-cycle", daemon=True)
        self._thread.start()

    def run_here(self) -> None:
        """Run the free / real-time loop in the calling thread until `stop()` or
        `max_cycles` (the GEO-cycle process runs it in its main thread)."""
        self._stop.clear()
        (self._run_free if self.mode == "free" else self._run_realtime)()

    def request_stop(self) -> None:
        """Ask the loop to end after its current cycle (from any thread; no waiting)."""
        self._stop.set()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def step(self, n: int = 1) -> None:
        """Run `n` cycles now (stepped mode; also allowed while paused)."""
        if self.running:
            raise RuntimeError("step() needs the stepped mode (the cycle thread is running)")
        for _ in range(n):
            t0 = time.perf_counter_ns()
            self.machine.run_cycle()
            self.stats.record(
                0.0, (time.perf_counter_ns() - t0) / 1000, self.machine.kernel_ns / 1000
            )

    # ------------------------------------------------------------------ loops

    def _run_free(self) -> None:
        rec, clock = self.stats.record, time.perf_counter_ns
        while not self._stop.is_set() and not self._done():
            t0 = clock()
            self._guarded_cycle()
            rec(0.0, (clock() - t0) / 1000, self.machine.kernel_ns / 1000)

    def _done(self) -> bool:
        return bool(self.max_cycles) and self.machine.cycle >= self.max_cycles

    def _guarded_cycle(self) -> None:
        """One cycle; an unexpected exception is logged and counted, the cycle goes on."""
        try:
            if self.before_cycle is not None:
                self.before_cycle()
            self.machine.run_cycle()
        except Exception:
            self.cycle_errors += 1
            log.exception("GEO cycle %d failed", self.machine.cycle)

    def _run_realtime(self) -> None:
        period = self.period_ns
        clock = self._clock
        deadline = clock() + period
        while not self._stop.is_set() and not self._done():
            self._wait_until(deadline)
            now = clock()
            late = now - deadline
            if late > self.max_catchup * period:
                # Too far behind to catch up: resynchronise and say so (an overrun), and
                # count the cycles given up so that status shows the whole stall.
                self.machine.overruns += 1
                self.skipped += late // period
                deadline = now
            t0 = time.perf_counter_ns()
            self._guarded_cycle()
            self.stats.record(
                late / 1000, (time.perf_counter_ns() - t0) / 1000, self.machine.kernel_ns / 1000
            )
            deadline += period

    def _wait_until(self, deadline: int) -> None:
        clock = self._clock
        wake = deadline - self.spin_ns
        delay = wake - clock()
        if delay > 0:
            self._sleep(delay / 1e9)
            self._adapt(clock() - wake)
        while clock() < deadline:
            pass

    def _adapt(self, oversleep: int) -> None:
        """Widen the spin margin after a sleep that ate most of it; narrow it slowly."""
        if oversleep > self.spin_ns * 0.8:
            self.spin_ns = min(int(self.spin_ns * 1.5), int(self.period_ns * 0.6))
            self._punctual = 0
            return
        self._punctual += 1
        if self._punctual >= 2000:
            self._punctual = 0
            self.spin_ns = max(int(self.spin_ns * 0.9), SPIN_MIN_NS)

    def _cached_summary(self) -> dict[str, float]:
        """Percentiles cost ~1 ms of GIL time: recompute at most every 250 cycles."""
        count = self._summary[0]
        if count < 0 or self.stats.count - count >= 250 or self.mode == "stepped":
            self._summary = (self.stats.count, self.stats.summary())
        return self._summary[1]

    def status(self) -> dict[str, Any]:
        """Cycle count, cycle time, lateness percentiles, overruns (docs/design.md §7 `status`)."""
        m = self.machine
        return {
            "cycle": m.cycle,
            "cycle_time_us": round(m.cycle_s * 1e6),
            "mode": self.mode,
            "overruns": m.overruns,
            "spin_margin_us": round(self.spin_ns / 1000),
            "cycle_errors": self.cycle_errors,
            "skipped_cycles": self.skipped,
            "axes": list(m.axes),
            **self._cached_summary(),
        }
