"""When GEO cycles run: stepped, free-running or real time (docs/design.md §5, §13).

- **stepped**: no thread; cycles run only when `step(n)` is called (tests: deterministic).
- **free**: a thread runs cycles back to back as fast as it can (benchmarks).
- **realtime**, engine **exact** (the default): *observation-exact virtual time*
  (docs/design.md §13). Cycle c belongs to the instant t0 + c·T; whoever looks at the
  machine at wall time t — a read, a write's acknowledgement, a publication, a
  notification sample — sees the state after cycle floor((t − t0)/T), and a write that
  arrives at t is applied in the cycle after that one. When the cycles are computed is
  the engine's business: it sleeps, computes in batches (`sync()` before every answer,
  every `batch` cycles while something moves, every `idle_wake` at rest) and skips the
  cycles of a quiescent machine without computing them (`Machine.skip`: the same
  numbers, the cost of the twin's events only). While someone samples every cycle
  (`demand_every_cycle`: ADS notifications) every cycle's snapshot is published, in the
  batch, with its own time stamp.
- **realtime**, engine **punctual**: a thread runs one cycle per period on a
  monotonic-clock deadline.
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

import heapq
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from geo_server import jit, timeslice
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.machine.machine import Machine
from geo_server.machine.port import CycleDemand, Operation, Pending
from geo_server.snapshot import filetime_now

log = logging.getLogger(__name__)

SPIN_NS = 400_000  # initial spin margin; adapted to the sleeps this machine delivers
SPIN_MIN_NS = 150_000
MODES = ("stepped", "free", "realtime")
ENGINES = ("exact", "punctual")
#: exact engine: cycles computed per wake while the machine is not quiescent, so the
#: most a request ever catches up (docs/design.md §13). A steady stretch of motion costs
#: one pass of about 300 µs plus 4 µs per cycle on the default machine (§13.2), but a
#: pass right after the engine slept finds cold caches and takes about 900 µs on a VM:
#: the wake-ups, not the cycles, are the cost, so a moving machine wakes every 16 cycles
BATCH = 16
#: exact engine: while requests come (one in the last `OBSERVED_S` seconds) a machine that
#: is not quiescent is kept up to date every `BATCH_OBSERVED` cycles instead, so the next
#: request finds (almost) nothing to compute. It costs no more CPU than the catch-ups it
#: saves (bench/engine.py: the server's CPU while asked every few milliseconds is the
#: same with 1 and with 4) and halves what a request waits for
BATCH_OBSERVED = 1
OBSERVED_S = 0.02
#: exact engine: the most cycles of a steady stretch computed in one pass
#: (`Machine.run_batch`)
BATCH_MAX = 64
#: exact engine: how long it sleeps at rest (seconds). Catching up at rest is the
#: twin's events of the stretch (a thermal update every 10 ms, the sensor samples) in
#: one compiled call — tens of microseconds for a second — so waking more often would
#: buy a request no latency, while each wake costs the thread's wake-up and the Python
#: around the call (the engine alone at rest: 0.15 % of a core at 0.25 s, 2026-11-28).
#: An older heartbeat is no stall: the stall watch (`ServiceLimits.stall_after`) first
#: catches up without waiting. The cycle process wakes every `IDLE_WAKE_PROCESS`: its
#: server counts it dead after `SYNC_DEAD`.
IDLE_WAKE = 1.0
IDLE_WAKE_PROCESS = 0.1
#: at rest while the laws still run interpreted (the machine code loading, docs/design.md
#: §13.3): a second of rest then takes tens of milliseconds to catch up, more while the
#: compiler holds the interpreter lock, and a request (or the stall watch) arriving
#: meanwhile would wait for it, up to `SYNC_WAIT`
IDLE_WAKE_INTERPRETED = 0.1
#: exact engine: the most cycle time one catch-up computes while the cycle runs
#: interpreted, before the time line slips (`Scheduler.max_lag`): 50 interpreted cycles
#: take about 15 ms, well inside `SYNC_WAIT` also on a host several times as busy
INTERPRETED_LAG_S = 0.05
#: exact engine: the most cycles computed to let a standing machine become quiescent
#: (a ramp runs out) before a long catch-up would give its cycles up (`_reachable`)
SETTLE_CYCLES = 64
#: the interpreter's GIL switch interval (seconds): short while a cycle thread runs, so
#: it is not starved by the transports' threads (and a request's catch-up is not kept
#: waiting for the lock by an engine thread); longer while more than `FEW_ENGINES` cycle
#: threads run in the process (a fleet of punctual engines: a fleet's exact engines
#: share one thread, `Engines`), which would otherwise spend the cores on handing the
#: lock around (docs/design.md §13.1)
SWITCH_SHORT = 0.0002
SWITCH_FLEET = 0.001
FEW_ENGINES = 4


def switch_interval(engines: int) -> float:
    """The GIL switch interval for a process whose cycles run on `engines` threads (the
    composition root sets it, once: `geo-server run`, a fleet, the test suite; library
    code never changes it)."""
    return SWITCH_FLEET if engines > FEW_ENGINES else SWITCH_SHORT


#: exact engine: the longest a request waits for a catch-up another thread is running
#: (a VM pausing the engine thread for tens of milliseconds is not a stall; a longer
#: wait is answered 0x707)
SYNC_WAIT = 0.25
#: exact engine: the longest an operation (a write, a command) waits for a catch-up
#: another thread is running before it is refused 0x707. Longer than a read's wait: a
#: read answered late shows a stale cycle, a write queued late only lands later, and
#: right after a start the loading of the cycle's machine code holds the interpreter
#: lock in stretches that, on a loaded 2-core runner, kept the catch-up of 50 cycles
#: from finishing within `SYNC_WAIT` (a write at start refused, CI)
WRITE_SYNC_WAIT = 1.0
#: `_next_overrun` while no overrun is injected: a cycle never reached
_NEVER = 1 << 62


class CycleStats:
    """Ring buffers of lateness, whole-cycle time and kernel time (µs) for percentiles.

    Recorded from any thread (a catch-up's time is recorded by whichever thread asked:
    the loop, a Zenoh thread, a worker), so a record takes `_lock`; `summary` reads
    without it (a ring slot being written shows its old or its new value).

    The rings start again when the cycle's machine code takes over (`jit.loaded`): the
    interpreted start-up cycles (≈300 µs) would otherwise stay in the figures for as long
    as a machine at rest computes too few cycles to replace them (issue 45 #17)."""

    def __init__(self, size: int = 10_000) -> None:
        self.lateness = np.zeros(size)
        self.cycle_time = np.zeros(size)
        self.kernel_time = np.zeros(size)
        self.count = 0
        self.max_lateness = 0.0
        self._lock = threading.Lock()
        self._compiled = jit.loaded()
        #: how often the rings started again (a cached summary of an older one is stale)
        self.generation = 0

    def _restart_when_compiled(self) -> None:
        """(under `_lock`) The rings start again once the machine code runs: checked at
        every record and every summary, so a machine at rest, which records nothing,
        shows no interpreted figures either."""
        if not self._compiled and jit.loaded():
            self._compiled = True
            self.count, self.max_lateness = 0, 0.0
            self.generation += 1

    def record(self, lateness_us: float, cycle_us: float, kernel_us: float = 0.0) -> None:
        with self._lock:
            self._restart_when_compiled()
            i = self.count % len(self.lateness)
            self.lateness[i] = lateness_us
            self.cycle_time[i] = cycle_us
            self.kernel_time[i] = kernel_us
            self.count += 1
            self.max_lateness = max(self.max_lateness, lateness_us)

    def summary(self) -> dict[str, float]:
        if not self._compiled:
            with self._lock:
                self._restart_when_compiled()
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


def sync_summary(stats: CycleStats) -> dict[str, float]:
    """Exact engine: what catching up added to requests (p50/p99 µs of the last ones; the
    times are kept in the `cycle_time` ring)."""
    n = min(stats.count, len(stats.cycle_time))
    if not n:
        return {"syncs": 0, "sync_p50_us": 0.0, "sync_p99_us": 0.0}
    p50, p99 = np.percentile(stats.cycle_time[:n], (50, 99))
    return {"syncs": stats.count, "sync_p50_us": float(p50), "sync_p99_us": float(p99)}


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
        engine: str = "exact",
    ) -> None:
        """`clock` (ns) and `sleep` (s) are the real-time loop's view of time; tests pass
        a virtual clock to make catch-up and overruns deterministic. With `max_cycles` the
        cycle thread ends by itself once the machine has run that many cycles. `engine`
        chooses how real time is kept (module docstring)."""
        if mode not in MODES:
            raise ValueError(f"scheduler mode must be one of {MODES}, not {mode!r}")
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {ENGINES}, not {engine!r}")
        self.machine = machine
        self.mode = mode
        self.engine = engine
        # (`exact`, fixed with mode and engine: an attribute, for the paths every request
        # takes — a property's call costs more than the rest of them after a pause)
        self._exact = mode == "realtime" and engine == "exact"
        #: exact engine: the monotonic ns at which cycle 0 ended (cycle c at t0 + c·T)
        self.t0 = 0
        self.batch = BATCH
        self.batch_observed = BATCH_OBSERVED
        self._observed_at = -(1 << 62)  # clock (ns) of the latest sync or submit
        self.idle_wake = IDLE_WAKE
        #: exact engine: called with the seconds to wait; returns early when woken (the
        #: cycle process waits on its command pipe instead)
        self.waiter: Callable[[float], None] | None = None
        self._engine_lock = threading.RLock()
        self._wake = threading.Event()
        self._every = 0  # observers that sample every cycle (`demand_every_cycle`)
        self._every_lock = threading.Lock()
        #: observers of chosen cycles (`demand_cycles`); replaced, never mutated
        self._demands: tuple[CycleDemand, ...] = ()
        #: exact engine: snapshots published because a `CycleDemand` wanted them
        self.demanded = 0
        self.computed = 0  # exact engine: cycles computed (the rest were skipped at rest)
        self.sync_stats = CycleStats(2000)  # exact engine: time of each catch-up (µs)
        self.wakes = 0
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
        self._summary: tuple[tuple[int, int], dict[str, float]] = ((0, -1), {})
        self._punctual = 0
        self._here = False  # the exact loop runs in the caller's thread (`run_here`)
        #: the one thread a fleet's exact engines share (`Engines`), instead of a thread
        #: of this scheduler's own
        self._shared: Engines | None = None
        # an injected overrun (geo_server/faults.py): after cycle `_next_overrun` the
        # time line slips by `_overrun_cycles` periods, every `_overrun_every` cycles
        self._next_overrun = _NEVER
        self._overrun_cycles = 0
        self._overrun_every = 0
        self._on_overrun: Callable[[], bool] | None = None
        #: set when overruns are cleared: a punctual wait for one ends at once
        self._overrun_cut = threading.Event()

    @property
    def period_ns(self) -> int:
        return round(self.machine.cycle_s * 1e9)

    # ------------------------------------------------------------------ injected overruns

    def set_overrun(
        self, cycles: int, every: int, on_overrun: Callable[[], bool] | None = None
    ) -> None:
        """Inject GEO-cycle overruns (docs/faults.md): from now on every `every`-th
        cycle overruns by `cycles` periods — the next cycle starts that much late, the
        cycles in between are lost (counted in `overruns` and `skipped_cycles`), as a
        TwinCAT task that exceeds its cycle. Both real-time engines slip their time line
        the same way, so every observer sees the same thing; stepped and free-running
        cycles have no time line and only count. `on_overrun` is called at each one
        and ends them by returning False. `cycles` 0 ends them now — an overrun under way
        included: the next cycle is due at once (docs/faults.md §2), not when the cleared
        overrun would have ended."""
        with self._engine_lock:
            if cycles <= 0 or every <= 0:
                self._next_overrun, self._on_overrun = _NEVER, None
                self._overrun_cut.set()
                if self.running_exact:
                    # the time line slipped ahead of the machine: take back what is left
                    self._give_back(self.machine.cycle - self.due())
            else:
                self._overrun_cut.clear()
                self._overrun_cycles, self._overrun_every = cycles, every
                self._on_overrun = on_overrun
                self._next_overrun = self.machine.cycle + every
        self._poke()

    def _give_back(self, periods: int) -> None:
        """An overrun cut short: `periods` of its slip were not lost after all."""
        if periods <= 0:
            return
        self.t0 -= periods * self.period_ns
        self.skipped -= periods
        if self.mode == "realtime":
            self.machine.slip(-periods, overrun=False)

    def _wait_overrun(self, deadline: int) -> int:
        """Punctual engine: wait out an injected overrun until `deadline` (ns); cleared
        meanwhile, it ends at once. The deadline of the next cycle."""
        clock = self._clock
        while not self._overrun_cut.is_set() and not self._stop.is_set():
            delay = deadline - clock()
            if delay <= 0:
                return deadline
            if self._sleep is time.sleep:
                self._overrun_cut.wait(delay / 1e9)
            else:  # a virtual clock (tests)
                self._sleep(delay / 1e9)
        now = clock()
        if now < deadline:
            self._give_back((deadline - now) // self.period_ns)
            return now
        return deadline

    def _overrun(self) -> int:
        """At the boundary after cycle `_next_overrun`: count the overrun and return the
        periods the time line slips (0 when the fault is used up). Under the engine lock,
        as `set_overrun` (the punctual engine takes it for this alone), so a fault
        cleared meanwhile is never re-armed by this cycle's `+=`."""
        with self._engine_lock:
            return self._overrun_locked()

    def _overrun_locked(self) -> int:
        if self._next_overrun == _NEVER:  # cleared since the cycle looked
            return 0
        if self._on_overrun is not None and not self._on_overrun():
            self._next_overrun, self._on_overrun = _NEVER, None
            return 0
        k = self._overrun_cycles
        # (stepped, there is no wall time line to slip: only the overrun is counted)
        self.machine.slip(k if self.mode == "realtime" else 0)
        self.skipped += k
        self._next_overrun += self._overrun_every
        return k

    # ------------------------------------------------------------------ control

    def start(self, shared: Engines | None = None) -> None:
        """Start the cycle thread (free / realtime); nothing to do when stepped. With
        `shared` (the exact engine), join that thread instead of starting one."""
        if self.mode == "stepped" or self._thread is not None or self._shared is not None:
            return
        self._stop.clear()
        if self.mode == "realtime":
            self._begin_timeline()  # before any request can sync against it
        if shared is not None and self._exact:
            self._shared = shared
            shared.add(self)
            return
        self._thread = threading.Thread(target=self._loop(), name="geo-cycle", daemon=True)
        self._thread.start()

    def _poke(self) -> None:
        """Make the engine look again now (its plans changed: an operation queued, an
        observer came or went, an overrun armed)."""
        self._wake.set()
        if self._shared is not None:
            self._shared.poke(self)

    def run_here(self) -> None:
        """Run the free / real-time loop in the calling thread until `stop()` or
        `max_cycles` (the GEO-cycle process runs it in its main thread)."""
        self._stop.clear()
        if self.mode == "realtime":
            self._begin_timeline()
        self._loop()()

    def _loop(self) -> Callable[[], None]:
        if self.mode == "free":
            return self._run_free
        return self._run_exact if self.exact else self._run_punctual

    def _run_punctual(self) -> None:
        """`_run_realtime` on the thread that runs it (the cycle's thread, or the main
        thread of the cycle's process), at the kernel's slice: the loop spins before each
        deadline, and with the short slice the server asks for, the kernel handed its
        core to any other ready task every 100 µs of the spin (bench/scheduler.py, 250 µs
        cycle in its own process, idle: lateness p99 0.16 → 23 µs; docs/design.md §5.11)."""
        timeslice.request(0, process=False)
        self._run_realtime()

    @property
    def exact(self) -> bool:
        """Real time kept by the observation-exact engine."""
        return self._exact

    def request_stop(self) -> None:
        """Ask the loop to end after its current cycle (from any thread; no waiting)."""
        self._stop.set()
        self._poke()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the cycles: a thread of its own is joined (up to `timeout`); on a shared
        thread (`Engines`) the machine leaves at that thread's next look, and a pass
        running meanwhile ends after its batch (`Engines.stop` joins the thread)."""
        self._stop.set()
        self._poke()
        self._shared = None  # (`running` False from now on; a `start` may join again)
        self._overrun_cut.set()  # a punctual engine waiting out an overrun stops too
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @property
    def running(self) -> bool:
        if self._shared is not None:
            return self._shared.runs(self)
        return self._thread is not None and self._thread.is_alive()

    def step(self, n: int = 1) -> None:
        """Run `n` cycles now (stepped mode; also allowed while paused)."""
        if self.running:
            raise RuntimeError("step() needs the stepped mode (the cycle thread is running)")
        for _ in range(n):
            if self.machine.cycle >= self._next_overrun:
                self._overrun()  # counted; stepped cycles have no time to lose
            t0 = time.perf_counter_ns()
            self.machine.run_cycle()
            self.stats.record(
                0.0, (time.perf_counter_ns() - t0) / 1000, self.machine.kernel_ns / 1000
            )

    # ------------------------------------------------------------------ exact engine

    def drive(self) -> None:
        """Exact engine without its thread: the time line starts now (on `clock`) and
        `sync`/`submit` catch up on the caller's thread — a virtual clock makes every
        observation deterministic (tests)."""
        if not self.exact:
            raise RuntimeError("drive() needs the exact engine in real-time mode")
        self._begin_timeline()
        self._here = True

    def _begin_timeline(self) -> None:
        """Put the machine's present cycle at now on both clocks: t0 on the monotonic
        clock, the FILETIME epoch on the wall clock (the notification stamps)."""
        m = self.machine
        now, wall = self._clock(), filetime_now()
        self.t0 = now - m.cycle * self.period_ns
        m.set_epoch(wall - m.cycle * m.period_ticks)

    def due(self, now: int | None = None) -> int:
        """The cycle an observer at monotonic time `now` (ns) must see."""
        t = self._clock() if now is None else now
        return (t - self.t0) // self.period_ns

    def sync(self, wait: float = SYNC_WAIT, record: bool = True) -> bool:
        """Exact engine: compute (or skip) the cycles up to now before an observer looks
        (from any thread; the caller computes them). False when that was not possible
        within `wait` seconds: another thread holds the engine (a long catch-up after the
        host stalled, or a cycle that hangs) — the machine's snapshot is then not the
        one due. `record`: time it as what catching up added to a request (status
        `sync_p50_us`/`sync_p99_us`; a status's own catch-up is not one). Other modes:
        nothing to do (True)."""
        if not self._engine_started():
            return True
        t0 = time.perf_counter_ns()
        now = self._observed_at = self._clock()
        if self._published_due(now):
            # the cycle due is computed and published already (requests faster than the
            # cycle): nothing to take the engine for (the engine never runs ahead of due)
            if record:
                self.sync_stats.record(0.0, (time.perf_counter_ns() - t0) / 1000)
            return True
        if not self._engine_lock.acquire(timeout=wait if wait > 0 else -1, blocking=wait > 0):
            return False
        try:
            self.advance(self.due())
        finally:
            self._engine_lock.release()
        if record:
            self.sync_stats.record(0.0, (time.perf_counter_ns() - t0) / 1000)
        return True

    def _engine_started(self) -> bool:
        # (started, not `running`: a thread's liveness costs more than the rest of the
        # fast path; an engine thread that died is caught up by its observers instead)
        return self._exact and (self._thread is not None or self._here or self._shared is not None)

    def _published_due(self, now: int) -> bool:
        m = self.machine
        return bool(m.snapshot.cycle == m.cycle == (now - self.t0) // self.period_ns)

    def shows_due(self) -> bool:
        """Whether `sync` has nothing to compute now: not the exact engine (or not
        started), or the cycle due is computed and published already. A look without
        the engine's lock, for a caller that must not take it (OPC UA's niced thread,
        docs/design.md §9.1)."""
        return not self._engine_started() or self._published_due(self._clock())

    def shows_rest(self) -> bool:
        """The published snapshot holds every object that cannot vary at rest as it is
        in the cycle due now (`Machine.rest_snapshot`), so a read of only such objects
        needs no catch-up (docs/design.md §13, *Reads at rest*)."""
        return self.machine.rest_snapshot is not None

    @property
    def running_exact(self) -> bool:
        return self.exact and (self.running or self._here)

    def submit(self, op: Operation) -> Pending:
        """Queue `op` so that it is applied in the cycle after the one due now (docs/
        design.md §13): the machine first catches up to now, so an op never lands in a
        cycle that belongs to the past; the engine is then woken to run the next cycle
        on its deadline."""
        if not self.running_exact:
            return self.machine.submit(op)
        self._observed_at = self._clock()
        if not self._engine_lock.acquire(timeout=WRITE_SYNC_WAIT):
            # queued now it could land in a cycle that belongs to the past
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY,
                "the GEO cycle is busy catching up (the host stalled): nothing queued",
            )
        try:
            self.advance(self.due())
            pending = self.machine.submit(op)
        finally:
            self._engine_lock.release()
        self._poke()
        return pending

    def demand_every_cycle(self) -> Callable[[], None]:
        """An observer samples every cycle (ADS notifications): until the returned
        function is called, every cycle's snapshot is published, also at rest."""
        with self._every_lock:
            self._every += 1
        released = False

        def release() -> None:
            nonlocal released
            with self._every_lock:
                if not released:
                    released = True
                    self._every -= 1

        return release

    @property
    def every_held(self) -> bool:
        """Someone samples every cycle (`demand_every_cycle`, `hold_every`)."""
        return self._every > 0

    def hold_every(self, count: int) -> None:
        """The cycle process: its server holds `count` every-cycle demands (that
        server's `demand_every_cycle`), set here, not counted. A demand that begins is
        served from the next cycle on, not a batch later: the server waits for it."""
        with self._every_lock:
            self._every = count
        if count:
            self._observed_at = self._clock()

    def demand_cycles(self, demand: CycleDemand) -> Callable[[], None]:
        """An observer needs the snapshots of the cycles `demand` wants (ADS
        notifications, docs/design.md §13): until the returned function is called, the
        exact engine publishes each such cycle it computes or skips — and only those, so
        the cost follows what is sampled, not the cycle rate — and wakes for the next.
        The other engines publish every cycle anyway."""
        with self._every_lock:
            self._demands = (*self._demands, demand)

        def release() -> None:
            with self._every_lock:
                self._demands = tuple(d for d in self._demands if d is not demand)

        self._poke()
        return release

    def _next_demanded(self, cycle: int, quiescent: bool) -> int | None:
        """The first cycle after `cycle` a `CycleDemand` wants (None: none)."""
        best: int | None = None
        for d in self._demands:
            c = d.next_wanted(cycle, quiescent)
            if c is not None and (best is None or c < best):
                best = c
        return best

    def _demanded(self, cycle: int, quiescent: bool) -> bool:
        wanted = False
        for d in self._demands:
            wanted = d.wants(cycle, quiescent) or wanted  # each one counts its own
        return wanted

    def advance(self, target: int, publish: bool = True) -> None:
        """Bring the machine to cycle `target` (call with the engine lock held): compute
        the cycles that do something, skip those of a quiescent machine, publish the
        snapshot reached (unless `publish` is False: the engine's own wake-ups publish
        nothing; whoever looks syncs, and a sync publishes). Behind by more than
        `max_lag` cycles that must be computed
        (the host cannot keep up) the time line moves on instead: an overrun, counted
        with the cycles given up, as the punctual engine does."""
        with self.machine.held_back():  # (its snapshots to the listeners in one go)
            self._advance(target, publish)

    def _advance(self, target: int, publish: bool) -> None:
        m = self.machine
        target = self._reachable(target)
        if target <= m.cycle:
            if publish:
                # the engine's own wake-up may have computed the cycle due without
                # publishing it: the observer must still see it, not the one before
                m.publish()
            return
        every = self._every
        while m.cycle < target and not self._stop.is_set():
            if m.cycle >= self._next_overrun:
                slip = self._overrun()
                self.t0 += slip * self.period_ns
                target -= slip  # the cycle due now, on the slipped time line
                continue
            stop_at = min(target, self._next_overrun)
            if m.quiescent:
                if self._skip_at_rest(stop_at, stop_at == target, every):
                    break
            elif not self._compute_next(stop_at, target, publish, every):
                break
        if publish:
            m.publish()

    def _skip_at_rest(self, stop_at: int, last: bool, every: int) -> bool:
        """`advance` on a quiescent machine, towards `stop_at`: skip to the next cycle
        an observer wants (published) or to `stop_at`; one cycle, published, while
        someone samples every cycle. True when `advance` is done: `stop_at` is reached
        and it is the target (`last`), or the skip failed."""
        m = self.machine
        try:
            if not every:
                # skip to the next cycle an observer wants (if any before stop_at)
                nxt = self._next_demanded(m.cycle, True) if self._demands else None
                if nxt is None or nxt > stop_at:
                    m.skip(stop_at - m.cycle)
                    return last
                m.skip(nxt - m.cycle)
                if self._demanded(nxt, True):
                    m.publish()
                    self.demanded += 1
                return False
            m.skip(1)
            m.publish()
        except Exception:  # as `_guarded_cycle`: logged, counted, time goes on
            self.cycle_errors += 1
            log.exception("GEO cycle %d (skipped at rest) failed", m.cycle)
            return True
        return False

    def _compute_next(self, stop_at: int, target: int, publish: bool, every: int) -> bool:
        """`advance` on a machine that is not at rest: the next cycles up to `stop_at`,
        a steady stretch in one pass (docs/design.md §13.2) or else one cycle, which
        builds its snapshot when it is looked at (`publish` and the `target`, an
        observer's cycle, or every one while someone samples every cycle). False when
        the cycle failed: `advance` stops."""
        m = self.machine
        clock = time.perf_counter_ns
        demands = self._demands
        t0 = clock()
        before = m.cycle
        limit = stop_at
        if demands and not every:
            # a batch ends before the next cycle an observer wants published
            nxt = self._next_demanded(before, False)
            if nxt is not None and nxt <= stop_at:
                limit = nxt - 1
        if not every and limit - before >= 2 and self.before_cycle is None:
            # a steady stretch in one pass (docs/design.md §13.2), else single cycles
            done = self._batch(limit - before)
            if done:
                self.computed += done
                self.stats.record(0.0, (clock() - t0) / 1000 / done, m.kernel_ns / 1000)
                return True
        # only the last cycle of the batch is looked at (and every one while
        # someone samples every cycle, and those an observer wants): the others
        # need not build their snapshot
        return self._computed_observed(publish and m.cycle + 1 == target)

    def _computed_observed(self, publish: bool = False) -> bool:
        """`_computed_cycle`, published when `publish` or when an observer wants the cycle:
        someone samples every cycle, or a `CycleDemand` wants it (counted in
        `demanded`)."""
        every = self._every  # (once: another thread's demand may end meanwhile)
        wanted = not every and bool(self._demands)
        wanted = wanted and self._demanded(self.machine.cycle + 1, False)
        if not self._computed_cycle(bool(every) or wanted or publish):
            return False
        if wanted:
            self.demanded += 1
        return True

    def _batch(self, left: int) -> int:
        """Run a steady stretch of up to `left` (at most `BATCH_MAX`) cycles in one pass
        (`Machine.run_batch`); `advance` publishes the cycle it reaches. Returns the
        cycles run (0: fewer than two were steady)."""
        m = self.machine
        try:
            return m.run_batch(min(left, BATCH_MAX))
        except Exception:  # as `_guarded_cycle`: logged and counted, time goes on
            self.cycle_errors += 1
            log.exception("GEO cycles from %d on (one pass) failed", m.cycle)
            return 0

    def _reachable(self, target: int) -> int:
        """`target`, or less: `max_cycles` caps it, and behind by more than `max_lag`
        cycles that must be computed (the host cannot keep up) the time line moves on
        instead — one overrun, the cycles given up counted, t0 and the epoch shifted."""
        m = self.machine
        if self.max_cycles:
            target = min(target, self.max_cycles)
        lag = target - m.cycle
        if lag > self.max_lag and not m.quiescent and m.standing():
            # standing but not yet quiescent (its first cycles: a fleet starting a
            # hundred machines at once leaves some of them a second behind): the few
            # cycles that make it quiescent, then the rest is skipped — no overrun; each
            # published if an observer wants it, as every computed cycle is
            for _ in range(SETTLE_CYCLES):
                if m.quiescent or m.cycle >= target:
                    break
                if not self._computed_observed():
                    break
            lag = target - m.cycle
        if lag > self.max_lag and not m.quiescent:
            give_up = lag - 1
            self.t0 += give_up * self.period_ns
            m.slip(give_up)
            self.skipped += give_up
            target = m.cycle + 1
        return target

    @property
    def max_lag(self) -> int:
        """Cycles the exact engine computes in one catch-up before it calls it an overrun
        (a stall of the host, not a batch): at least a second of cycles. While the cycle
        still runs interpreted (its first seconds, `jit.loaded`) only `INTERPRETED_LAG_S`
        of cycles: an interpreted cycle (≈300 µs, several times that on a loaded host)
        can be slower than the period, and a catch-up of a second of them held the engine
        for longer than a request waits for it (`SYNC_WAIT`), so a write right after the
        start was refused 0x707 ("busy catching up"; CI, next to busy processes)."""
        if not jit.loaded():
            return max(self.max_catchup, round(INTERPRETED_LAG_S / self.machine.cycle_s))
        return max(self.max_catchup, 10 * self.batch, round(1.0 / self.machine.cycle_s))

    def _next_wake(self, now: int) -> int:
        """When the engine must look again (monotonic ns): an operation waits for the
        next cycle's deadline, a machine that moves (or an observer of every cycle)
        for the end of the next batch (a short one while requests come); a quiescent
        machine only for `idle_wake`."""
        m = self.machine
        if m.has_queued():
            return self.t0 + (m.cycle + 1) * self.period_ns
        if self._every or not m.quiescent:
            observed = now - self._observed_at < OBSERVED_S * 1e9
            return self.t0 + (m.cycle + (self.batch_observed if observed else self.batch)) * (
                self.period_ns
            )
        wake = self.idle_wake if jit.loaded() else min(self.idle_wake, IDLE_WAKE_INTERPRETED)
        idle = now + int(wake * 1e9)
        if self._demands:
            # at rest, an observer of chosen cycles: wake for the next one it wants, at
            # most every batch (the cycles of a batch are published together, in order)
            nxt = self._next_demanded(m.cycle, True)
            if nxt is not None:
                return min(idle, self.t0 + max(nxt, m.cycle + self.batch) * self.period_ns)
        return idle

    def _run_exact(self) -> None:
        clock = self._clock
        self._here = threading.current_thread() is not self._thread
        try:
            while not self._stop.is_set() and not self._done():
                wake = self.run_pass(blocking=True)
                delay = (wake - clock()) / 1e9
                if delay > 0:
                    self._wait(delay)
        finally:
            self._here = False

    def run_pass(self, blocking: bool) -> int:
        """One wake-up of the exact engine: catch up to the cycle due (a batch at a time
        while the machine moves); returns when it must look again (monotonic ns).

        A wake-up nobody asked for publishes nothing (whoever looks syncs; the stall
        watch reads the heartbeat), but in the cycle process: its server has no machine
        to sync, only the frames it is sent. Behind by more than a batch (the host was
        busy), the engine catches up a batch at a time and lets go of the lock in
        between, so a request never waits for more than one batch before it catches up
        to its own cycle. A cycle that fails (logged and counted: `_guarded_cycle`)
        leaves the machine where it was; the engine then looks again a batch later, not
        at once. Not `blocking` (a thread shared with other machines: `Engines`), a pass
        is one batch at most (the machines behind take turns: the next batch is planned
        for now, after those already due), and a machine whose lock a request holds is
        left to that request and looked at again a period later: no machine holds up
        the others."""
        clock = self._clock
        self.wakes += 1
        m = self.machine
        if not self._engine_lock.acquire(blocking=blocking):
            return clock() + self.period_ns
        try:
            target = self._reachable(self.due())
        finally:
            self._engine_lock.release()
        while True:
            if not self._engine_lock.acquire(blocking=blocking):
                return clock() + self.period_ns
            try:
                target = min(target, self.due())  # an overrun slipped the time line
                before = m.cycle
                step = target if m.quiescent else min(target, m.cycle + self.batch)
                self.advance(step, publish=self.waiter is not None and step == target)
                if m.cycle == before and m.cycle < target and not self._stop.is_set():
                    # nothing advanced (the cycle failed): again a batch later, not at
                    # once (each failure is logged and counted)
                    return max(self._next_wake(clock()), clock() + self.batch * self.period_ns)
                if m.cycle >= target or m.cycle == before or self._stop.is_set():
                    return self._next_wake(clock())
                if not blocking:
                    return clock()  # (more to catch up: after the others due)
            finally:
                self._engine_lock.release()

    def _wait(self, seconds: float) -> None:
        if self.waiter is not None:
            self.waiter(seconds)
        elif self._sleep is not time.sleep:  # a virtual clock (tests)
            self._sleep(seconds)
        else:
            self._wake.wait(seconds)
            self._wake.clear()

    # ------------------------------------------------------------------ loops

    def _run_free(self) -> None:
        rec, clock = self.stats.record, time.perf_counter_ns
        while not self._stop.is_set() and not self._done():
            if self.machine.cycle >= self._next_overrun:
                self._overrun()
            t0 = clock()
            self._guarded_cycle()
            rec(0.0, (clock() - t0) / 1000, self.machine.kernel_ns / 1000)

    def _done(self) -> bool:
        return bool(self.max_cycles) and self.machine.cycle >= self.max_cycles

    def _computed_cycle(self, publish: bool) -> bool:
        """Exact engine: one cycle computed, counted and timed; False when it failed
        before it counted (the caller stops: no busy loop)."""
        m = self.machine
        t0, before = time.perf_counter_ns(), m.cycle
        self._guarded_cycle(publish=publish)
        if m.cycle == before:
            return False
        self.computed += 1
        self.stats.record(0.0, (time.perf_counter_ns() - t0) / 1000, m.kernel_ns / 1000)
        return True

    def _guarded_cycle(self, publish: bool = True) -> None:
        """One cycle; an unexpected exception is logged and counted, the cycle goes on."""
        try:
            if self.before_cycle is not None:
                self.before_cycle()
            if publish:
                self.machine.run_cycle()
            else:
                self.machine.run_cycle(publish=False)
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
                self.machine.slip(0)  # counted; the stamps keep counting cycles
                self.skipped += late // period
                # (the stamps keep counting cycles: epoch + cycle·T, so a stamp always
                # names its cycle; after an overrun they trail wall time by the cycles
                # given up, which status reports as skipped_cycles)
                deadline = now
            if self.machine.cycle >= self._next_overrun:
                deadline = self._wait_overrun(deadline + self._overrun() * period)
                continue
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
        """Percentiles cost ~1 ms of GIL time: recompute at most every 250 cycles, and
        whenever the rings started again (the compiled cycle took over)."""
        generation, count = self._summary[0]
        stats = self.stats
        stale = generation != stats.generation or not 0 <= stats.count - count < 250
        if count < 0 or stale or self.mode == "stepped" or not jit.loaded():
            summary = stats.summary()  # (may start the rings again: read the keys after)
            self._summary = ((stats.generation, stats.count), summary)
        return self._summary[1]

    def status(self) -> dict[str, Any]:
        """Cycle count, cycle time, lateness percentiles, overruns (docs/design.md §7 `status`)."""
        m = self.machine
        return {
            "cycle": m.cycle,
            "cycle_time_us": round(m.cycle_s * 1e6),
            "mode": self.mode,
            "engine": self.engine if self.mode == "realtime" else self.mode,
            # the cycle's machine code is loaded (else it runs interpreted: geo_server/jit.py)
            "compiled": jit.loaded(),
            "computed_cycles": self.computed,
            "demanded_snapshots": self.demanded,
            "engine_wakes": self.wakes,
            **sync_summary(self.sync_stats),
            "overruns": m.overruns,
            "spin_margin_us": round(self.spin_ns / 1000),
            "cycle_errors": self.cycle_errors,
            "skipped_cycles": self.skipped,
            "axes": list(m.axes),
            **self._cached_summary(),
        }


class Engines:
    """One thread, `geo-cycles`, for the exact engines of many machines (a fleet): a
    fleet of 500 machines has one cycle thread, not 500 (docs/design.md §5.10).

    Each machine's engine is woken at the time its own pass asked for (`run_pass`), the
    earliest first; a machine whose plans change (`Scheduler._poke`: an operation
    queued, an observer added) is looked at at once. A pass computes one batch at most
    (a machine far behind takes turns with the others), never waits for a machine whose
    lock a request holds (that request is catching it up), and a machine whose cycle
    fails is looked at again a batch later, not at once: no machine holds up the
    others. A pass that raises takes only its own machine out (logged; its `running`
    turns False, as a dead thread's did); the others go on. Only the composition root
    makes one, and starts and stops it, once."""

    def __init__(self, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._members: set[Scheduler] = set()  # (guarded by `_lock`)
        self._poked: list[Scheduler] = []  # looked at next, at once (guarded by `_lock`)
        self._event = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def add(self, scheduler: Scheduler) -> None:
        with self._lock:
            self._members.add(scheduler)
            self._poked.append(scheduler)
        self._event.set()

    def poke(self, scheduler: Scheduler) -> None:
        """Look at `scheduler` at once (from any thread)."""
        with self._lock:
            self._poked.append(scheduler)
        self._event.set()

    def runs(self, scheduler: Scheduler) -> bool:
        """`scheduler` is served by a live thread (False once it failed or stopped)."""
        thread = self._thread
        return thread is not None and thread.is_alive() and scheduler in self._members

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="geo-cycles", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._event.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _leave(self, scheduler: Scheduler) -> None:
        with self._lock:
            self._members.discard(scheduler)

    def _run(self) -> None:
        clock = self._clock
        heap: list[tuple[int, int, Scheduler]] = []
        planned: dict[Scheduler, int] = {}  # each member's wake-up (older heap entries: stale)
        order = 0  # (ties on the heap go first come, first served)
        while not self._stop.is_set():
            with self._lock:
                poked, self._poked = self._poked, []
                self._event.clear()
                members = set(self._members)
            now = clock()
            for s in poked:
                if s in members and planned.get(s) != now:
                    planned[s] = now
                    order += 1
                    heapq.heappush(heap, (now, order, s))
            # the passes due by `now`, each once; a pass planned again for now (more to
            # catch up) comes in the next round, after the pokes that came meanwhile
            while heap and heap[0][0] <= now and not self._stop.is_set():
                wake, _, s = heapq.heappop(heap)
                if planned.get(s) != wake:
                    continue  # re-planned since (poked)
                if s not in members or s._stop.is_set() or s._done():
                    planned.pop(s, None)
                    self._leave(s)
                    continue
                try:
                    nxt = s.run_pass(blocking=False)
                except Exception:
                    log.exception("the GEO cycle of a machine failed; its engine stops")
                    planned.pop(s, None)
                    self._leave(s)
                    continue
                planned[s] = max(nxt, now + 1)  # (not again in this round)
                order += 1
                heapq.heappush(heap, (planned[s], order, s))
            delay = (heap[0][0] - clock()) / 1e9 if heap else IDLE_WAKE
            if delay > 0:
                self._event.wait(delay)
