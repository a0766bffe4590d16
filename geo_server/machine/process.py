"""The GEO cycle in its own process (`geo-server run --cycle-in process`, docs/design.md §5).

In one process the cycle thread and the transports share one interpreter lock, and under
load on all transports the cycle starts late (README, *Benchmarks*). Here the cycle runs
in a child process with the unchanged `Machine` and `Scheduler`; the server process keeps
a `RemoteMachine` with the same face the `ObjectService` uses (`snapshot`, `axes`,
`names`, `cfg`, `events`, `listeners`, `event_listeners`, `call`).

Child → server, once per cycle: the snapshot values, the acknowledgements of the queued
operations that cycle applied, its events and (every `STATUS_EVERY` cycles) the
scheduler status — one frame, so an acknowledged write is always visible in the snapshot
the server holds when the caller hears of it. Server → child: queued operations by name
(`Machine.CALLS`) and `stop`. The child writes without ever blocking (`ipc.OutBuffer`: a
snapshot nobody has read yet is superseded by the next, acknowledgements and events are
kept) and drains its commands right before each cycle. It ends when the server process
goes away (end of file on the channel), so no orphan keeps spinning.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import multiprocessing
import os
import queue
import select
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, TypeVar

from geo_server import jit
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.machine.ipc import FrameDecoder, OutBuffer, SlotTable, encode_frame
from geo_server.machine.machine import Machine
from geo_server.machine.nc import parse_program
from geo_server.machine.port import (
    Operation,
    Pending,
    Record,
    Reload,
    Saved,
    StartProgram,
    listen,
)
from geo_server.machine.scheduler import (
    ENGINES,
    IDLE_WAKE_PROCESS,
    SYNC_WAIT,
    CycleStats,
    Scheduler,
    switch_interval,
    sync_summary,
)
from geo_server.model import Diagnostic, MachineConfig
from geo_server.snapshot import Snapshot

log = logging.getLogger(__name__)
_T = TypeVar("_T")

STATUS_EVERY = 100  # cycles between two status reports from the child
#: Bytes of operations the server may have sent that the cycle process has not read yet;
#: beyond this the cycle process is not reading (stopped, hung) and new operations are
#: refused at once (0x707) instead of piling up.
SEND_BACKLOG = 8 * 1024 * 1024
#: Seconds `ProcessScheduler.start` waits for the child's first cycle.
FIRST_FRAME_TIMEOUT = 30.0
#: Exact engine: the longest a request waits for the cycle process to catch up — the
#: thread engine's `scheduler.SYNC_WAIT` (a loaded 2-core CI runner once kept the cycle
#: process from the CPU for more than 50 ms, and a read was answered 0x707) — and how
#: long without any frame (it sends one at least every `scheduler.IDLE_WAKE_PROCESS`) makes it
#: count as not responding (then requests are not held up: the stall watch answers).
SYNC_DEAD = 0.3


def _outcome(fut: Future[Any]) -> tuple[bool, Any]:
    """A finished future as something that pickles: (True, result) or (False, error)."""
    exc = fut.exception()
    if exc is None:
        return True, fut.result()
    if isinstance(exc, AdsError):
        return False, ("ads", exc.code, exc.message, exc.name)
    return False, ("exc", f"{type(exc).__name__}: {exc}")


class _ChildChannel:
    """The cycle process's end of the channel (`_child_main`): it drains the server's
    commands into the machine and writes one frame per published cycle (see the module
    docstring), without ever blocking."""

    __slots__ = (
        "acks",
        "dec",
        "events",
        "every_seq",
        "exact",
        "fd",
        "held",
        "machine",
        "out",
        "sched",
        "sent",
        "slots",
        "status_sent",
        "wake_fd",
    )

    def __init__(self, fd: int, sched: Scheduler, slots: SlotTable, wake_conn: Any) -> None:
        self.fd = fd
        self.sched = sched
        self.machine = sched.machine
        self.slots = slots
        self.exact = sched.exact
        self.out, self.dec = OutBuffer(), FrameDecoder()
        self.acks: list[tuple[int, bool, Any]] = []
        self.events: list[Event] = []
        self.wake_fd = wake_conn.fileno() if wake_conn is not None else -1
        if self.wake_fd >= 0:
            os.set_blocking(self.wake_fd, False)
        self.held: Snapshot | None = None  # exact engine: the newest snapshot not framed yet
        self.sent = -1  # cycle of the last snapshot framed
        self.status_sent = 0  # cycle of the last status
        #: the server's last every-cycle demand message applied (`ProcessScheduler`)
        self.every_seq = 0

    def on_done(self, seq: int, fut: Future[Any]) -> None:
        ok, payload = _outcome(fut)
        self.acks.append((seq, ok, payload))

    def drain(self) -> None:
        """Take every command the server has sent (never waits)."""
        while True:
            try:
                data = os.read(self.fd, 1 << 16)
            except BlockingIOError:
                return
            if not data:  # the server process is gone
                self.sched.request_stop()
                return
            for msg in self.dec.feed(data):
                self._command(msg)

    def _command(self, msg: tuple[Any, ...]) -> None:
        sched = self.sched
        if msg[0] == "op":
            _, seq, slot, op, arrival = msg
            if self.slots.take(slot):  # else withdrawn: the server answered already
                if self.exact:  # the cycles before its arrival run without it
                    sched.advance(min(arrival, sched.due()))
                pending = self.machine.submit(op)
                pending.add_done_callback(functools.partial(self.on_done, seq))
        elif msg[0] == "every":
            _, count, self.every_seq = msg
            sched.hold_every(count)
        elif msg[0] == "stop":
            sched.request_stop()

    def frame(self, snap: Snapshot, status: dict[str, Any] | None) -> tuple[Any, ...]:
        return (
            "cycle",
            snap.wire(),
            self.acks[:],
            self.events[:],
            status,
            self.sched.t0,
            self.every_seq,
        )

    def on_cycle(self, snap: Snapshot) -> None:
        sched = self.sched
        # every STATUS_EVERY cycles (the exact engine skips over cycles: at the first
        # snapshot of each new hundred)
        status = None
        if snap.cycle // STATUS_EVERY != self.status_sent // STATUS_EVERY:
            status = sched.status()
            self.status_sent = snap.cycle
        quiet = not self.acks and not self.events and status is None
        if self.exact and quiet and not sched.every_held:
            # framed once the batch is done (`wait`), unless a newer one comes first
            self.held = snap
            return
        self.held = None
        self.out.add(self.frame(snap, status), droppable=quiet and not sched.every_held)
        self.sent = snap.cycle
        self.acks.clear()
        self.events.clear()
        self.flush()

    def flush(self) -> None:
        try:
            self.out.flush(lambda b: os.write(self.fd, b))
        except OSError:  # the server process is gone
            self.sched.request_stop()

    def wait(self, seconds: float) -> None:
        """Exact engine: frame the batch's last snapshot, then sleep until the deadline,
        a command or a wake-up, and take the commands."""
        held, fd, wake_fd = self.held, self.fd, self.wake_fd
        if held is not None and held.cycle > self.sent:
            self.out.add(self.frame(held, None), droppable=True)
            self.sent = held.cycle
        self.held = None
        self.flush()
        fds = [fd] if wake_fd < 0 else [fd, wake_fd]
        try:
            ready, _, _ = select.select(fds, [], [], seconds)
        except InterruptedError:
            ready = []
        if wake_fd in ready:
            with contextlib.suppress(BlockingIOError, OSError):
                while os.read(wake_fd, 4096):
                    pass
        if fd in ready:
            self.drain()

    def close(self) -> None:
        """The last cycle once more (never dropped) with the final status, then
        everything still buffered, written blocking: the server reads until end of
        file."""
        self.out.add(self.frame(self.machine.snapshot, self.sched.status()))
        os.set_blocking(self.fd, True)
        with contextlib.suppress(OSError):
            self.out.flush(lambda b: os.write(self.fd, b))


@dataclass(frozen=True)
class ChildSpec:
    """The machine and engine the GEO-cycle process runs (pickled to it at its start)."""

    cfg: MachineConfig
    cycle_s: float
    homed: bool
    time_scale: float | None
    mode: str
    max_cycles: int
    engine: str
    #: the shared slots of its published values (`SlotTable`)
    slots: SlotTable
    #: picklable (benchmarks): may adjust the scheduler before the first cycle and return
    #: a function to run after the last
    setup: Callable[[Scheduler], Callable[[], None] | None] | None = None


def _child_main(conn: Any, wake_conn: Any, spec: ChildSpec) -> None:
    """Entry point of the GEO-cycle process: the machine of `spec`, commanded over
    `conn`. With the exact engine the process sleeps on its two pipes: commands, and
    wake-ups from a server that needs the cycle due now (`wake_conn`,
    `ProcessScheduler.sync`)."""
    # Ctrl-C in a terminal reaches the whole process group: the server stops the cycle
    # (its `stop` message), the child must not die first of KeyboardInterrupt.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    fd = conn.fileno()
    os.set_blocking(fd, False)
    _raise_priority()
    # compiled from the first cycle: this process does nothing else, and its server waits
    # for its first frame (`FIRST_FRAME_TIMEOUT`)
    jit.load()
    sys.setswitchinterval(switch_interval(1))  # (this process's composition root)
    machine = Machine(spec.cfg, cycle_s=spec.cycle_s, homed=spec.homed, time_scale=spec.time_scale)
    sched = Scheduler(machine, mode=spec.mode, max_cycles=spec.max_cycles, engine=spec.engine)
    sched.idle_wake = IDLE_WAKE_PROCESS  # a frame well within SYNC_DEAD of the last
    channel = _ChildChannel(fd, sched, spec.slots, wake_conn)
    machine.subscribe(channel.on_cycle)
    machine.subscribe_events(channel.events.append)
    if channel.exact:
        sched.waiter = channel.wait
    else:
        sched.before_cycle = channel.drain
    finish = spec.setup(sched) if spec.setup is not None else None
    sched.run_here()
    if finish is not None:
        finish()
    channel.close()


#: The cycle process exchanges frames over an OS pipe with plain file descriptors
#: (`os.read`/`os.write`, non-blocking): POSIX systems (Linux, macOS). On Windows a
#: multiprocessing pipe is a named-pipe handle, so the cycle runs in a thread there.
SUPPORTED = os.name == "posix"


def _raise_priority() -> None:
    """Ask the OS to prefer the cycle over the transports and clients (nice −10).

    With fewer cores than busy threads the OS, not the interpreter lock, decides when the
    cycle runs. Raising priority needs CAP_SYS_NICE (root) on Linux, root on macOS;
    without it, or where `os.nice` does not exist, the cycle runs at normal priority and
    this says so once."""
    nice = getattr(os, "nice", None)
    if nice is None:
        log.info("GEO-cycle process keeps normal priority (no os.nice here)")
        return
    try:
        nice(-10)
    except OSError as exc:
        log.info("GEO-cycle process keeps normal priority (%s)", exc)


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Ignore SIGINT while the child is created: an ignored signal stays ignored across
    exec, so a Ctrl-C during the child's imports cannot kill it with a traceback."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


class RemoteMachine:
    """The server process's view of a machine whose cycle runs in a child process
    (implements `MachinePort`)."""

    def __init__(
        self,
        cfg: MachineConfig,
        cycle_s: float = 0.001,
        homed: bool = False,
        time_scale: float | None = None,
    ) -> None:
        # A local machine that never steps gives layout, names, the first snapshot and
        # the load diagnostics exactly as the child will have them.
        local = Machine(cfg, cycle_s=cycle_s, homed=homed, time_scale=time_scale)
        self.time_scale = time_scale
        self.cfg = cfg
        self.cycle_s = local.cycle_s
        self.homed = homed
        self.dictionary = local.dictionary
        self.layout = local.layout
        self.axes = local.axes
        self.names = local.names
        self.snapshot: Snapshot = local.snapshot
        self.snapshot_time = time.monotonic()
        self.heartbeat = self.snapshot_time  # a frame is the cycle process's sign of life
        #: never: only a frame of the cycle due tells the machine's state (`shows_rest`)
        self.rest_snapshot: Snapshot | None = None
        self.events: deque[Event] = deque(local.events, maxlen=100)
        self._listeners: list[Callable[[Snapshot], None]] = []
        self._event_listeners: list[Callable[[Event], None]] = []
        self.status: dict[str, Any] = Scheduler(local, mode="stepped").status()
        ctx = multiprocessing.get_context("spawn")
        self.slots = SlotTable(ctx)
        self._pending: dict[int, tuple[Pending, int, Operation]] = {}
        self._seq = 0
        self._lock = threading.Lock()
        self.conn, self.child_conn = ctx.Pipe(duplex=True)
        self._fd = self.conn.fileno()
        # exact engine: a one-way pipe whose bytes only wake the cycle process up
        self.wake_conn, self._wake_w = ctx.Pipe(duplex=False)
        self._wake_fd = self._wake_w.fileno()
        os.set_blocking(self._wake_fd, False)
        #: the cycle process's time line: cycle c ends at monotonic ns t0 + c·T
        self.t0 = 0
        #: notified whenever a frame arrives (`ProcessScheduler.sync` waits on it)
        self.arrived = threading.Condition()
        #: the last every-cycle demand message the cycle process had applied when it sent
        #: the newest frame (`ProcessScheduler.demand_every_cycle`)
        self.every_seq = 0
        self._outbox: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._backlog = 0  # bytes queued for the child and not written yet
        self._sender = threading.Thread(target=self._send_loop, name="geo-cycle-send", daemon=True)
        self._sender.start()
        self.closed = False
        self.first_frame = threading.Event()

    @property
    def cycle(self) -> int:
        return self.snapshot.cycle

    # ------------------------------------------------------------------ MachinePort

    def submit(self, op: Operation, arrival: int = 0) -> Pending:
        """Queue `op` in the cycle process; the future resolves after the cycle that
        carried it out has been received (its snapshot is then `self.snapshot`).
        `arrival`: the cycle due when it arrived (exact engine: applied in the next)."""
        with self._lock:
            if self.closed:
                raise AdsError(AdsErrorCode.DEVICE_NOTREADY, "the GEO cycle process ended")
            if self._backlog > SEND_BACKLOG:
                raise AdsError(
                    AdsErrorCode.DEVICE_NOTREADY,
                    "the GEO cycle process is not reading its commands (stopped or hung)",
                )
            slot = self.slots.allocate()
            if slot is None:
                raise AdsError(
                    AdsErrorCode.DEVICE_BUSY,
                    f"{self.slots.capacity} operations are already waiting for the GEO cycle",
                )
            self._seq += 1
            seq = self._seq
            pending = Pending(lambda _p: self.slots.withdraw(slot))
            self._pending[seq] = (pending, slot, op)
            frame = encode_frame(("op", seq, slot, op, arrival))
            self._backlog += len(frame)
            self._outbox.put(frame)
        return pending

    def record(self, diagnostic: Diagnostic) -> Pending:
        """Into the child's error list at its next cycle boundary (it owns the list)."""
        return self.submit(Record(diagnostic))

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        return listen(self._listeners, callback)

    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        return listen(self._event_listeners, callback)

    def start_program(self, text: str, mdi: bool = False) -> Pending:
        """Parse here (raises `NcError` at once) and run it in the cycle process."""
        return self.submit(StartProgram(parse_program(text, self.names, mdi=mdi), mdi, text))

    def stop(self) -> None:
        """Ask the cycle process to end after its current cycle."""
        self.control(("stop",))
        self.wake()

    def control(self, message: tuple[Any, ...]) -> None:
        """Send a message that is not an operation (stop, every-cycle demand)."""
        with self._lock:
            if not self.closed:
                self._outbox.put(encode_frame(message))

    def wake(self) -> None:
        """Wake the sleeping cycle process up: it catches up to now and publishes."""
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_fd, b"\0")

    # ------------------------------------------------------------------ to the child

    def _send_loop(self) -> None:
        """Write queued frames to the child (blocking here, never on a caller's thread)."""
        while True:
            frame = self._outbox.get()
            if frame is None:
                return
            data = memoryview(frame)
            try:
                while data:
                    data = data[os.write(self._fd, data) :]
            except OSError:  # the child is gone; pending operations fail in `pump`
                return
            finally:
                with self._lock:
                    self._backlog -= len(frame)

    # ------------------------------------------------------------------ from the child

    def pump(self) -> None:
        """Read the child's frames until it ends (runs on its own thread)."""
        dec = FrameDecoder()
        try:
            while True:
                try:
                    data = os.read(self._fd, 1 << 16)
                except OSError:
                    break
                if not data:
                    break
                for msg in dec.feed(data):
                    self._dispatch(msg)
        finally:
            self.first_frame.set()
            with self._lock:
                self.closed = True
                pending, self._pending = self._pending, {}
            self._outbox.put(None)
            with self.arrived:
                self.arrived.notify_all()
            for fut, _slot, _op in pending.values():
                if fut.set_running_or_notify_cancel():
                    fut.set_exception(
                        AdsError(AdsErrorCode.DEVICE_NOTREADY, "the GEO cycle process ended")
                    )

    def _dispatch(self, msg: tuple[Any, ...]) -> None:
        _, wire, acks, events, status, t0, every_seq = msg
        self.t0 = t0
        # Events first, as in the cycle itself (an event is recorded while its cycle runs,
        # before that cycle's snapshot is published): whoever sees the snapshot of a program
        # that stopped has already been told why (the `run --program` report relies on it).
        for ev in events:
            self.events.append(ev)
            for listener in list(self._event_listeners):
                _guarded(listener, ev)
        self.snapshot = Snapshot.from_wire(wire, self.layout)
        self.snapshot_time = self.heartbeat = time.monotonic()
        self.every_seq = every_seq  # (after the snapshot: whoever sees it holds that one)
        self.first_frame.set()
        with self.arrived:
            self.arrived.notify_all()
        if status is not None:
            self.status = status
        for seq, ok, payload in acks:
            with self._lock:
                entry = self._pending.pop(seq, None)
            if entry is None:
                continue
            fut, slot, op = entry
            self.slots.release(slot)
            if ok and isinstance(op, Reload | Saved):  # (the child swapped it in too)
                self.cfg = op.cfg
            if not fut.set_running_or_notify_cancel():
                continue
            if ok:
                fut.set_result(payload)
            elif payload[0] == "ads":
                fut.set_exception(AdsError(*payload[1:]))
            else:
                fut.set_exception(RuntimeError(payload[1]))
        for on_cycle in list(self._listeners):
            _guarded(on_cycle, self.snapshot)


def _guarded(fn: Callable[[_T], None], arg: _T) -> None:
    try:
        fn(arg)
    except Exception:  # one broken subscriber must not stop the others
        log.exception("snapshot/event listener failed")


class ProcessScheduler:
    """`Scheduler`'s face (`start`, `stop`, `running`, `status`) for a `RemoteMachine`."""

    def __init__(
        self,
        machine: RemoteMachine,
        mode: str = "realtime",
        max_cycles: int = 0,
        child_setup: Callable[[Scheduler], Callable[[], None] | None] | None = None,
        engine: str = "exact",
    ) -> None:
        if mode not in ("realtime", "free"):
            raise ValueError("the cycle process runs in real time or free-running")
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {ENGINES}, not {engine!r}")
        self.machine = machine
        self.mode = mode
        self.engine = engine
        self._every = 0
        self._every_seq = 0  # the last every-cycle demand message sent (`demand_every_cycle`)
        self._every_on = 0  # the last one of them that began a demand
        self._every_lock = threading.Lock()
        self.sync_stats = CycleStats(2000)  # what waiting for the cycle process added (µs)
        self.max_cycles = max_cycles
        self.child_setup = child_setup
        self._proc: Any = None
        self._pump: threading.Thread | None = None

    def start(self) -> None:
        if self._proc is not None:
            return
        m = self.machine
        ctx = multiprocessing.get_context("spawn")
        self._proc = ctx.Process(
            target=_child_main,
            args=(
                m.child_conn,
                m.wake_conn,
                ChildSpec(
                    m.cfg,
                    m.cycle_s,
                    m.homed,
                    m.time_scale,
                    self.mode,
                    self.max_cycles,
                    self.engine,
                    m.slots,
                    self.child_setup,
                ),
            ),
            name="geo-cycle",
            daemon=True,
        )
        with _sigint_ignored():  # inherited through exec: ignored from its first line on
            self._proc.start()
        m.child_conn.close()  # the child holds it now; EOF reaches us when it ends
        m.wake_conn.close()
        self._pump = threading.Thread(target=m.pump, name="geo-cycle-pump", daemon=True)
        self._pump.start()
        # Serve from the child's snapshots only: until its first frame arrives (process
        # start and imports take a second or more) the machine has not run a cycle.
        m.first_frame.wait(FIRST_FRAME_TIMEOUT)

    def stop(self, timeout: float = 5.0) -> None:
        if self._proc is None:
            return
        self.machine.stop()
        self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout)
        if self._pump is not None:
            self._pump.join(timeout)

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def step(self, n: int = 1) -> None:
        raise RuntimeError("step() needs the stepped mode (the cycle runs in its own process)")

    @property
    def exact(self) -> bool:
        return self.mode == "realtime" and self.engine == "exact"

    def due(self) -> int:
        """The cycle an observer must see now (the cycle process's time line)."""
        m = self.machine
        return (time.monotonic_ns() - m.t0) // round(m.cycle_s * 1e9)

    def sync(self, wait: float = SYNC_WAIT, record: bool = True) -> bool:
        """Exact engine: wake the cycle process and wait (at most `wait` seconds) for the
        snapshot of the cycle due now. A cycle process that has sent nothing for
        `SYNC_DEAD` seconds (stopped, hung) is not waited for: the stall watch answers
        instead."""
        if not self.exact or not self.running:
            return True
        m = self.machine
        t0 = time.perf_counter_ns()
        target = self.due()
        if m.snapshot.cycle >= target:
            return True
        if time.monotonic() - m.snapshot_time > SYNC_DEAD:
            return False
        m.wake()
        with m.arrived:
            done = m.arrived.wait_for(lambda: m.snapshot.cycle >= target or m.closed, wait)
        if record:
            self.sync_stats.record(0.0, (time.perf_counter_ns() - t0) / 1000)
        return bool(done) and not m.closed

    def shows_due(self) -> bool:
        """`Scheduler.shows_due`: the snapshot the cycle process sent is the one due."""
        return not self.exact or not self.running or self.machine.snapshot.cycle >= self.due()

    def submit(self, op: Operation) -> Pending:
        """Queue `op` for the cycle after the one due now (exact engine: the cycle
        process runs the cycles up to its arrival without it)."""
        return self.machine.submit(op, self.due() if self.exact else 0)

    def demand_every_cycle(self) -> Callable[[], None]:
        """`Scheduler.demand_every_cycle`, told to the cycle process — and in force when
        this returns: the snapshot the server holds then, and every later one, was
        published while the cycle process knew of it (`_in_force`)."""
        m = self.machine
        with self._every_lock:
            self._every += 1
            if self._every == 1:
                self._every_seq += 1
                self._every_on = self._every_seq
                m.control(("every", 1, self._every_on))
            seq = self._every_on  # (a second demand waits for the first one's message too)
        self._in_force(seq)
        released = False

        def release() -> None:
            nonlocal released
            with self._every_lock:
                if released:
                    return
                released = True
                self._every -= 1
                if self._every == 0:
                    self._every_seq += 1
                    m.control(("every", 0, self._every_seq))

        return release

    def _in_force(self, seq: int) -> None:
        """Wait (at most `SYNC_WAIT`) for a frame sent after the cycle process applied the
        every-cycle demand `seq`. Until then it published only the cycles someone looked
        at: an ADS registration sampled from such a snapshot found its next cycles
        missing (a cyclic stream every 3 cycles with 44, 50, 55 on a busy host, the
        demand's message a few milliseconds late). It answers with its next cycle's
        frame (`Scheduler.hold_every`). A cycle process that is silent (`SYNC_DEAD`) is
        not waited for."""
        m = self.machine
        if not self.running or time.monotonic() - m.snapshot_time > SYNC_DEAD:
            return
        with m.arrived:  # (the message itself wakes a sleeping cycle process)
            m.arrived.wait_for(lambda: m.every_seq >= seq or m.closed, SYNC_WAIT)

    def status(self) -> dict[str, Any]:
        st = dict(self.machine.status)
        st["cycle"] = self.machine.cycle
        st["mode"] = self.mode
        st["engine"] = self.engine if self.mode == "realtime" else self.mode
        st.update(sync_summary(self.sync_stats))
        st["cycle_in"] = "process"
        st["cycle_pid"] = self.pid
        return st
