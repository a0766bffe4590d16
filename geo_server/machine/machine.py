"""The simulated machine: axes, motion, NC player and the compensation kernel in one GEO cycle.

Every cycle runs, in this order (docs/design.md §5):
1. apply the queued writes and commands in arrival order;
2. advance the NC program and the motion;
3. compute the compensations (the kernel);
4. publish one consistent snapshot of every object;
5. hand the snapshot to the listeners (transports, notifications).

The machine is pure computation driven by `run_cycle()`; *when* cycles run is the
scheduler's business (`geo_server.machine.scheduler`). Other threads talk to it only
through `submit()` (a queue applied at the next cycle boundary) and the published
`snapshot` reference, so no lock is ever held across a cycle.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, fields, replace
from time import monotonic, perf_counter_ns
from typing import Any

import numpy as np

from geo_server import jit
from geo_server.dictionary import Dictionary, ObjectDef, load_dictionary
from geo_server.errors import AdsError, AdsErrorCode, CncErrorId
from geo_server.events import Event
from geo_server.jit import Packed
from geo_server.kernel import COMP_ORDER, Kernel, temperature
from geo_server.kernel.common import ALL_KINDS, COLUMN, listed_kinds, mask_of
from geo_server.listfile.values import Reporter
from geo_server.machine.cycle import (
    ACCELERATION,
    DISPLAY,
    FEED_UM,
    LOSE,
    NROWS,
    OUTPUT,
    TWIN_SHIFT,
    VELOCITY,
    VOLC_SHIFT,
    CycleFlag,
    CycleOut,
    cycles,
    derived,
)
from geo_server.machine.motion import Motion, MotionError
from geo_server.machine.nc import Player, Program, VolcompCommand, parse_program
from geo_server.machine.port import (
    Operation,
    Pending,
    Record,
    Reload,
    Reset,
    Saved,
    SensorFault,
    StartProgram,
    VolcUpdate,
    WriteObjects,
    listen,
    resolved,
)
from geo_server.model import SELECTED_OBJECTS, CompKind, Diagnostic, MachineConfig
from geo_server.seam import HELD_MAX
from geo_server.snapshot import ObjectLayout, Snapshot, filetime_now
from geo_server.twin.engine import TwinEngine
from geo_server.twin.model import TwinConfig
from geo_server.units import ACHS_TYP, UNITS_PER_MM, UNITS_PER_UM
from geo_server.volcomp.config import reload_compensation
from geo_server.volcomp.kernel import VOLC_ERROR, VolKernel

log = logging.getLogger(__name__)


def _fed(name: str) -> Any:
    """A field of `_MachineColumns`: the column of machine object `name`."""
    return field(metadata={"object": name})


@dataclass(frozen=True, slots=True)
class _MachineColumns:
    """Columns of the machine objects `Machine._build_snapshot` writes from the machine's
    own state, each field beside the object it feeds (the other machine objects are
    write-only: `_unfed` checks)."""

    cycle_count: int = _fed("SIM::cycle_count")
    cycle_time_us: int = _fed("SIM::cycle_time_us")
    overruns: int = _fed("SIM::overruns")
    last_error_id: int = _fed("SIM::last_error_id")
    program_running: int = _fed("SIM::program_running")
    program_line: int = _fed("SIM::program_line")
    ambient_temperature: int = _fed("TWIN::ambient_temperature")
    twin_time: int = _fed("TWIN::time")
    spindle_on: int = _fed("TWIN::spindle_on")
    volc_active: int = _fed("VOLC::active")
    volc_available: int = _fed("VOLC::available")
    volc_index: int = _fed("VOLC::index")
    volc_tool_length: int = _fed("VOLC::tool_length")
    volc_incorrect: int = _fed("VOLC::incorrect")

    @staticmethod
    def objects() -> tuple[str, ...]:
        """The machine objects fed, in field order."""
        return tuple(f.metadata["object"] for f in fields(_MachineColumns))

    @classmethod
    def of(cls, mcol: Callable[[str], int]) -> _MachineColumns:
        return cls(**{f.name: mcol(f.metadata["object"]) for f in fields(cls)})


#: the text objects the machine writes (`Machine._snapshot_of`)
_TEXTS = ("SIM::last_error", "SIM::axis_names", "VOLC::file")


#: (made once: an IntFlag made per call costs microseconds)
_NO_FLAGS = CycleFlag(0)


class Machine:
    """A whole simulated machine built from a validated `MachineConfig`."""

    def __init__(
        self,
        cfg: MachineConfig,
        cycle_s: float = 0.001,
        dictionary: Dictionary | None = None,
        homed: bool = False,
        time_scale: float | None = None,
    ) -> None:
        self.cfg = cfg
        self.cycle_s = float(cycle_s)
        self.time_scale = time_scale
        self.dictionary = dictionary or load_dictionary()
        self.layout = ObjectLayout(self.dictionary)
        self.axes: tuple[int, ...] = tuple(sorted(cfg.axes))
        self.names = {cfg.axes[a].params.name.upper(): i for i, a in enumerate(self.axes)}
        #: the TEMPC parameter objects of this machine's dictionary (000 §3.2.3)
        self.tempc = temperature.bindings(self.dictionary)
        self.kernel = Kernel(cfg, self.tempc)
        self.volc = self._new_volc(cfg)
        #: the machine as the NC player sees it (positions, moves, COMP, #VOLCOMP)
        self.nc_side = NcSide(self)
        #: cnc_interpr_vol_comp_index_w: the compensation the next file write updates
        self.volc_index = 0
        #: #VOLCOMP UPDATE: (ID, the worker reading its files)
        self._volc_loading: list[tuple[int, float, Future[Any]]] = []
        #: `V.G.VOLCOMP[i].FILE[j] = "…"` of NC programs: ID -> j -> name, for the next
        #: UPDATE (004 p.18); a reload of the lists forgets them, as a start-up would
        self._volc_files: dict[int, dict[int, str]] = {}
        self.twin = self._new_twin(cfg)
        #: called with (cycle, operation) for every operation applied at a cycle boundary
        #: (after `cycle`): what a recording replays (docs/recorder.md §4)
        self.input_taps: list[Callable[[int, Operation], None]] = []
        self.spindle_on = False  # TWIN::spindle_on: a heat source of the twin
        self.motion = Motion([cfg.axes[a].params for a in self.axes], self.cycle_s)
        if homed:
            for slot in range(len(self.axes)):
                self.motion.home(slot)
        self.cycle = 0
        #: cycles computed (not skipped): a snapshot published at rest is reused by the
        #: next publish at rest only if none was computed in between (`publish`)
        self._computed = 0
        self._rest_key: tuple[int, int] | None = None
        self.overruns = 0
        #: FILETIME (100 ns ticks since 1601) of cycle 0; cycle c ends at epoch + c·T.
        #: A real-time scheduler sets it when it starts; stepped, it is the creation time.
        self.epoch = filetime_now()
        self.period_ticks = round(self.cycle_s * 1e7)
        #: cycles in a row that began at rest (`_at_rest`): from 2 on, a cycle changes
        #: nothing but the counters and the twin's clock (`quiescent`)
        self._rest_streak = 0
        self._rest_after = False  # the last cycle ended at rest
        self.kernel_ns = 0  # time of the last cycle's compensation kernel (status)
        self.player: Player | None = None
        self.events: deque[Event] = deque(maxlen=100)
        self.last_error_id = 0
        self.last_error = ""  # SIM::last_error: the latest warning or error, as text
        self.listeners: list[Callable[[Snapshot], None]] = []
        #: snapshots published inside `held_back`, not handed to the listeners yet (None:
        #: outside it; the engine lock's holder's, as everything `publish` touches)
        self._held: list[Snapshot] | None = None
        self.event_listeners: list[Callable[[Event], None]] = []
        self._queue: deque[tuple[Operation, Pending]] = deque()
        self._queue_lock = threading.Lock()
        self._cycle_lock = threading.Lock()
        n = len(self.axes)
        self._reversal = np.full(n, -1, dtype=np.int64)
        # per-cycle derived snapshot values, one buffer (columns: `_MBUF`): a row per
        # column, so that each is a contiguous vector for the compiled code (`cycle`)
        self._mrows = np.zeros((NROWS, n))
        self._mbuf = self._mrows.T
        #: what the drives get: command + all compensations (SIM::output_position,
        #: computed once per cycle before the twin)
        self._output = self._mrows[OUTPUT]
        #: the drives' actual positions (dig_act_pos, 000 p.19; SIM::drive_actual_position):
        #: an enabled drive follows its command exactly, a disabled one stays where it is
        self._drive_act = np.zeros(n)
        #: ... and the reversals: where the compiled cycle writes (`cycle.cycles`)
        self._out: Packed = tuple(CycleOut(self._reversal, self._output, self._drive_act))
        self._lose = self._mrows[LOSE]
        self._lose[:] = [cfg.axes[a].params.lose for a in self.axes]
        self._modulo = np.array([cfg.axes[a].params.modulo for a in self.axes])
        self._period = np.array([cfg.axes[a].params.modulo_period for a in self.axes])
        #: SIM::axis_type: kenngr.achs_typ (1 linear, 2 rotary, 4 spindle)
        self._axis_type: np.ndarray = np.array(
            [float(ACHS_TYP[cfg.axes[a].params.kind]) for a in self.axes]
        )
        for d in cfg.diagnostics:
            self._record(d)
        self._layout_sources()
        np.add(self.motion.pos, self.kernel.total_offset, out=self._output)
        np.copyto(self._drive_act, self._output)
        #: the published snapshot while the machine shows its rest (`shows_rest`), else
        #: None: what a read at rest is answered from, checked with one look (`_show`)
        self.rest_snapshot: Snapshot | None = None
        self.snapshot: Snapshot = self._build_snapshot()
        self.snapshot_time = monotonic()
        #: when the cycle last advanced (computed, skipped or published: the stall watch)
        self.heartbeat = self.snapshot_time

    # ------------------------------------------------------------------ the cycle

    def run_cycle(self, publish: bool = True) -> Snapshot:
        """Run one GEO cycle (docs/design.md §5) and return the snapshot it published.

        With `publish=False` (the exact engine, for a cycle inside a batch that nobody
        observes) steps 4 and 5 are left to `publish`, unless the cycle applied
        operations: their acknowledgements wait for the snapshot that shows them."""
        applied: list[tuple[Pending, Any, BaseException | None]] = []
        try:
            with self._cycle_lock:
                self.rest_snapshot = None  # (a cycle computed: `shows_rest` is False)
                rest = self._at_rest()
                self._rest_streak = self._rest_streak + 1 if rest else 0
                self._rest_after = False
                applied = self._apply_queue()
                self._step_program()
                t0 = perf_counter_ns()
                _, vflags = self._compute(1, prepare=True)
                if vflags and not self.volc.settle(vflags):
                    self._volc_stop()
                self.kernel_ns = perf_counter_ns() - t0
                publish = publish or bool(applied)
                if publish:
                    mo = self.motion
                    self.twin.evaluate(self._output, mo.pos, mo.vel)
                self.cycle += 1
                self._computed += 1
                self.heartbeat = monotonic()
                if self._rest_streak >= 1:  # (only then can the next cycles be quiescent)
                    self._rest_after = self._at_rest()
                if not publish:
                    return self.snapshot
                snap = self._build_snapshot()
                self._show(snap)
                self.snapshot_time = monotonic()
        finally:
            # Acknowledge the operations only now: a read right after an acknowledged
            # write sees its effect (the snapshot of the cycle that applied it is
            # published). Even a failed cycle answers them, so no client waits for nothing.
            # The snapshots `held_back` before this cycle go out first: the cycle process
            # sends each acknowledgement with the next snapshot it hands out.
            if applied:
                self._hand_out_held()
            for pending, result, exc in applied:
                if not pending.set_running_or_notify_cancel():
                    continue  # cannot happen: a withdrawn operation is not in the queue
                if exc is None:
                    pending.set_result(result)
                else:
                    pending.set_exception(exc)
        if applied:
            self._hand_out(snap)
        else:
            self._handed_out(snap)
        return snap

    # ------------------------------------------------------------------ batches

    def run_batch(self, n: int) -> int:
        """Run up to `n` of the next cycles in one pass while nothing but the compiled
        cycle acts (docs/design.md §13.2): nothing queued, an axis moving, the program
        (if any) only waiting for that motion, no volumetric compensation acting. The
        pass ends after the first cycle with an event (an arrival, a sensor sample, a
        velocity that changes sign). Returns the cycles run: 0 when no pass is possible
        (nothing has changed then: run single cycles). The numbers are those of as many
        calls of `run_cycle(publish=False)`, by construction (`cycle.cycles`; tests/
        test_batch.py): the snapshot of the cycle reached is left to `publish`."""
        if n < 2 or self._queue or self.cycle == 0:
            return 0
        mo = self.motion
        with self._cycle_lock:
            if self._queue or not mo._moving.any():
                return 0
            self.rest_snapshot = None  # (cycles computed: `shows_rest` is False)
            player = self.player
            if player is not None and player.running:
                waits = player.motion_wait()
                if not waits or not mo._moving[list(waits)].any():
                    return 0
            t0 = perf_counter_ns()
            n, vflags = self._compute(n, prepare=False)
            if not n:
                return 0  # (an automatic activation or an axis in error state: Python)
            self.kernel_ns = (perf_counter_ns() - t0) // n
            if player is not None and player.running:
                player.skip(n)  # (it waits for the motion: nothing else changes for it)
            self.cycle += n - 1
            if vflags and not self.volc.settle(vflags):  # (reported in its own cycle)
                self._volc_stop()
            self.cycle += 1
            self._computed += n
            self.heartbeat = monotonic()
            self._rest_streak = 0  # an axis moved in every cycle
            self._rest_after = False
        return n

    def _compute(self, count: int, prepare: bool) -> tuple[int, int]:
        """Up to `count` cycles of the compiled part (`cycle.cycles`: motion, kernel,
        volumetric compensations, output, the twin's state), with what it leaves to
        Python in between: before the first cycle, the volumetric compensations'
        automatic activation and faults (`VolKernel.prepare`, when the compiled check
        asks for it — only with `prepare`, else nothing is computed), a queued move to
        plan (in the middle of its cycle), the twin's events after a cycle. Stops after
        a cycle with events; returns the cycles computed and the volumetric flags for
        `VolKernel.settle` (`volcomp.step.OFF` of the last cycle, `ENDED` of any,
        `FAULT` from `prepare`)."""
        mo, tw, k, volc = self.motion, self.twin, self.kernel, self.volc
        kernel, vol, out = k.state(), volc.state(), self._out
        done = 0
        vflags = _NO_FLAGS
        resume = False
        while True:
            ran, raw = cycles(
                count - done, resume, prepare, mo.state, kernel, vol, tw.state, self.spindle_on, out
            )
            done += ran
            if not raw:  # (most passes: no flag, and no IntFlag made — 2 µs a cycle)
                return done, int(vflags) >> VOLC_SHIFT
            flags = CycleFlag(raw)
            vflags |= flags & (CycleFlag.VOLC_OFF | CycleFlag.VOLC_ENDED)
            if CycleFlag.VOLC_PREPARE in flags:  # (before the first cycle's motion: none ran)
                if not prepare:
                    return 0, 0
                prepare = False
                if not volc.prepare(mo.homed, k.drive_enabled):
                    vflags |= CycleFlag.VOLC_FAULT
                continue
            if CycleFlag.PLAN in flags:  # the arrived axes' queued moves start (next cycle)
                mo.start_queued()
                resume = True
                continue
            if CycleFlag.TWIN_MOTION in flags:
                tw.events(int(flags & CycleFlag.TWIN_MOTION) >> TWIN_SHIFT, mo.vel)
            return done, int(vflags) >> VOLC_SHIFT

    def _volc_stop(self) -> None:
        """A volumetric compensation was switched off in error: the program stops and
        the axes with it (004 p.14: "the axis is stopped in a controlled manner")."""
        if self.player is not None and self.player.running:
            self.player.abort()
        self.motion.stop()

    # ------------------------------------------------------------------ virtual time

    def slip(self, periods: int, overrun: bool = True) -> None:
        """The engine's time line moved by `periods` cycles without them (an overrun, or
        part of one given back with a negative count): the stamps keep naming their
        cycle's wall time (epoch + cycle·T); `overrun` counts one (SIM::overruns)."""
        self.epoch += periods * self.period_ticks
        if overrun:
            self.overruns += 1

    def set_epoch(self, epoch: int) -> None:
        """Put cycle 0 at FILETIME `epoch` (a real-time engine starting its time line);
        the published snapshot gets its stamp on the new time line."""
        with self._cycle_lock:
            self.epoch = epoch
            snap = self.snapshot
            self._show(replace(snap, stamp=epoch + snap.cycle * self.period_ticks))

    def _at_rest(self) -> bool:
        """Nothing queued, no program, no axis moving, the kernel at rest, no motion heat
        pending in the twin (docs/design.md §13): a cycle that starts like this computes
        what the one before computed."""
        if not self.standing():
            return False
        return self.kernel.at_rest() and self.volc.at_rest and self.twin.at_rest()

    def standing(self) -> bool:
        """Nothing queued, no program running, every axis in position: whatever still
        changes (a sin² ramp — the temperature compensation of a freshly homed machine
        ramps in over its first 20 cycles — the friction delay line, the twin's motion
        heat) ends by itself, and then the machine is `quiescent`."""
        if self._queue:
            return False
        player = self.player
        if player is not None and player.running:
            return False
        return self.motion.all_in_position()

    @property
    def quiescent(self) -> bool:
        """True when the next cycles would publish the snapshot of this one but for the
        counters and the twin's clock and temperatures: two cycles in a row began at
        rest, the last one ended at rest, and nothing has been queued since (docs/
        design.md §13). Only operations change a machine between cycles, so the end of
        the last cycle is remembered (`_rest_after`) instead of looked at again."""
        return self._rest_streak >= 2 and self._rest_after and not self._queue

    def shows_rest(self) -> bool:
        """True when the published snapshot shows every object that cannot vary at rest
        (`varies_at_rest` in objects.toml) as it is in every cycle from now on until
        something is queued: the machine is `quiescent`, and no cycle has been computed since a
        snapshot was built at rest (docs/design.md §13, *Reads at rest*). Lock-free, for
        any thread: each attribute is one read, and whichever state a racing cycle
        leaves, a True here means the values are those of a cycle at rest with nothing
        queued (an operation makes it False from the moment it is queued)."""
        key = self._rest_key
        return key is not None and key[0] == self._computed and self.quiescent

    def _show(self, snap: Snapshot) -> None:
        """Publish `snap` (under the cycle lock), and as `rest_snapshot` while the machine
        `shows_rest` (docs/design.md §13, *Repeated reads*). Whatever can make
        `shows_rest` False clears `rest_snapshot`: a cycle computed, an operation applied
        or queued. `submit` clears it after queueing, so the queue is looked at again
        here after setting it: a racing `submit` leaves it None either way. No reader
        ever finds the old snapshot as `rest_snapshot` next to the new one."""
        self.rest_snapshot = None
        self.snapshot = snap
        if self.shows_rest():
            self.rest_snapshot = snap
            if self._queue:
                self.rest_snapshot = None

    def skip(self, n: int) -> None:
        """`n` cycles of a `quiescent` machine without computing them: the counter, the
        kernel's delay line position and the twin (its thermal and sensor events, in
        their cycles) advance exactly as `n` calls of `run_cycle` would advance them.
        No snapshot is built; `publish` builds the one of the cycle reached."""
        if n <= 0:
            return
        with self._cycle_lock:
            self.kernel.skip(n)
            self.twin.advance(n, self._output, self.motion.pos, self.spindle_on, False)
            self.cycle += n
            self.heartbeat = monotonic()

    def publish(self) -> Snapshot:
        """Build and hand out the snapshot of the cycle reached, when `skip` or an
        unpublished `run_cycle` has left the published one behind (else nothing to do):
        to the listeners now, or inside `held_back` at its end."""
        with self._cycle_lock:
            if self.snapshot.cycle == self.cycle:
                return self.snapshot
            key = (self._computed, self.twin.rest_events)
            if key == self._rest_key and self._src_owner == self._owner():
                # at rest since a snapshot published at rest, and no event of the twin
                # since: every axis value is what it was (docs/design.md §13); only the
                # machine objects (cycle, twin time, ambient…) and the stamp move on
                snap = self._snapshot_of(self.snapshot.values)
            else:
                mo = self.motion
                self.twin.evaluate(self._output, mo.pos, mo.vel)
                snap = self._build_snapshot()
                self._rest_key = key if self.quiescent else None
            self._show(snap)
            self.snapshot_time = monotonic()
        self._handed_out(snap)
        return snap

    @contextlib.contextmanager
    def held_back(self) -> Iterator[None]:
        """The snapshots `publish`ed inside go to the listeners at its end, in their order,
        each as it would have on its own (a cycle computed inside hands those before it
        out first). The exact engine publishes its catch-ups so (`Scheduler.advance`): a
        listener that hands its snapshots to a thread of its own (OPC UA's process, ADS
        notifications) wakes that thread once per catch-up, not at its first cycle —
        woken then, it took the interpreter lock at each of the next cycles' compiled
        calls (they let it go; docs/design.md §13, *Handing out a catch-up*). Nested,
        the outermost hands out."""
        if self._held is not None:
            yield
            return
        self._held = []
        try:
            yield
        finally:
            # (a listener may catch up again, on this thread: what it publishes meanwhile
            # is held and handed out here too, until none is left)
            try:
                while self._held:
                    self._hand_out_held()
            finally:
                self._held = None

    def _handed_out(self, snap: Snapshot) -> None:
        """`snap` to the listeners now, or held (`held_back`: at most `HELD_MAX`)."""
        held = self._held
        if held is None:
            self._hand_out(snap)
            return
        held.append(snap)
        if len(held) >= HELD_MAX:
            self._hand_out_held()

    def _hand_out_held(self) -> None:
        held = self._held
        if held:
            self._held = []
            for snap in held:
                self._hand_out(snap)

    def _hand_out(self, snap: Snapshot) -> None:
        for listener in tuple(self.listeners):  # (a copy: one may unsubscribe meanwhile)
            try:
                listener(snap)
            except Exception:  # one broken subscriber must not stop the engine
                log.exception("snapshot listener failed")

    def _step_program(self) -> None:
        """Advance the NC program; a command the machine cannot carry out ends the program
        with an error event instead of failing the cycle."""
        player = self.player
        if player is None or not player.running:
            return
        if self.cycle == 0:
            # Nothing is effective before the first kernel step: a program started
            # before the first cycle (`run --program`) begins in the second, so the
            # 70435 monitoring sees the compensations of the running machine.
            return
        try:
            player.step()
        except (MotionError, AdsError) as exc:
            player.abort()
            self.report(0, f"NC program stopped: {exc}", player.line)

    def step(self, n: int = 1) -> Snapshot:
        """Run `n` cycles now (stepped mode)."""
        snap = self.snapshot
        for _ in range(n):
            snap = self.run_cycle()
        return snap

    # ------------------------------------------------------------------ operations

    def submit(self, op: Operation) -> Pending:
        """Queue `op` for the next cycle boundary, in arrival order (docs/design.md §5 step 1)."""
        pending = Pending(self._withdraw)
        with self._queue_lock:
            self._queue.append((op, pending))
        self.rest_snapshot = None  # (after queueing: `_show`)
        return pending

    def has_queued(self) -> bool:
        """Operations wait for the next cycle boundary."""
        return bool(self._queue)

    def _withdraw(self, pending: Pending) -> bool:
        """Take a queued operation back; False once a cycle has taken it."""
        with self._queue_lock:
            for i, (_op, p) in enumerate(self._queue):
                if p is pending:
                    del self._queue[i]
                    return True
        return False

    def _apply_queue(self) -> list[tuple[Pending, Any, BaseException | None]]:
        """docs/design.md §5 step 1: carry out queued operations in arrival order."""
        with self._queue_lock:
            items = list(self._queue)
            self._queue.clear()
        out: list[tuple[Pending, Any, BaseException | None]] = []
        for op, pending in items:
            try:
                out.append((pending, self.apply(op), None))
            except Exception as exc:  # the caller gets the error, the cycle goes on
                out.append((pending, None, exc))
        return out

    def apply(self, op: Operation) -> Any:
        """Carry out one operation now (at a cycle boundary)."""
        self.rest_snapshot = None
        self._rest_after = False
        for tap in tuple(self.input_taps):  # a recorder's (geo_server/recorder): usually none
            try:
                tap(self.cycle, op)
            except Exception:  # a recording must never stop the cycle
                log.exception("input tap failed")
        match op:
            case WriteObjects(items):
                return tuple(self._apply_item(*item) for item in items)
            case StartProgram(program, mdi, _text):
                self.start(program, mdi)
                return self.cycle + 1  # the cycle being computed runs its first block
            case Reset():
                return self.reset()
            case Reload(cfg):
                return self.reload(cfg)
            case Saved(cfg):
                self.cfg = cfg
                return None
            case Record(diagnostic):
                self._record(diagnostic)
                return None
            case VolcUpdate(ident, comp):
                self.volc.update(ident, comp)
                self._volc_files.pop(ident, None)  # (the names are the loaded list's now)
                self.volc_index = ident
                return None
            case SensorFault(sensor, kind, sigma):
                self.twin.set_sensor_fault(sensor, kind, sigma)
                return None
        raise TypeError(f"not a machine operation: {op!r}")

    def _apply_item(self, obj: ObjectDef | str, axis: int, value: Any) -> BaseException | None:
        try:
            self.apply_write(obj, axis, value)
        except AdsError as exc:
            return exc
        return None

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        """Call `callback(snapshot)` after every cycle, on the cycle thread."""
        return listen(self.listeners, callback)

    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        """Call `callback(event)` for every new warning or error (on the reporting thread)."""
        return listen(self.event_listeners, callback)

    # ------------------------------------------------------------------ snapshot

    def _layout_sources(self) -> None:
        """Precompute where every snapshot column comes from (no name lookups per cycle).

        Each axis object is a column of a live 2-D "piece": a kernel `[n, 7]` array, a
        state vector, or the machine's own `[n, 13]` buffer of per-cycle derived values
        (`_MBUF`). A snapshot is then one `np.concatenate` of the pieces into a stacked
        buffer and one `take` of the columns in layout order. The pieces are updated in
        place by the kernel and the motion (their contract); they are looked up again
        if `kernel` or `motion` is ever replaced.
        """
        col = self.layout.col
        k = self.kernel
        self._src_owner = self._owner()
        n = len(self.axes)
        pieces: dict[str, np.ndarray] = {
            "actual": k.actual,
            "target": k.target,
            "selected": k.selected,
            "effective": k.effective,
            "machine": self._mbuf,
        }
        where: list[tuple[str, int] | None] = [None] * len(self.layout.axis_objects)
        for name, (attr, kind) in _FROM_COMP.items():
            where[col(name)] = ("machine" if attr == "delta" else attr, COLUMN[kind])
        tempc_rows = {name: _tempc_row(row) for row, name in enumerate(self.tempc.names) if name}
        for name, src in {**_FROM_STATE, **tempc_rows}.items():
            if isinstance(src, str):  # a column of the machine buffer
                where[col(name)] = ("machine", _MBUF[src])
            else:
                key = f"state:{name}"
                pieces[key] = src(self)[:, None]
                where[col(name)] = (key, 0)
        unfed = _unfed(self.layout, where)
        if unfed:
            raise ValueError(
                f"nothing feeds the readable object(s) {', '.join(unfed)}: objects.toml "
                "names them, the machine does not compute them (docs/design.md §1.3a)"
            )
        if any(w is None for w in where):  # not fed by the machine (write-only): 0
            pieces["zero"] = np.zeros((n, 1))
        offset, start = {}, 0
        for key, piece in pieces.items():
            offset[key] = start
            start += piece.shape[1]
        self._pieces = list(pieces.values())
        self._stack = np.zeros((n, start))
        self._columns = np.array(
            [offset[w[0]] + w[1] if w else offset["zero"] for w in where], dtype=np.int64
        )
        self._mc = _MachineColumns.of(self.layout.mcol)
        self._mach_template = [0.0] * len(self.layout.machine_objects)
        self._text_slot = self.layout.text_index["SIM::last_error"]
        self._volc_file_slot = self.layout.text_index["VOLC::file"]
        self._texts = [""] * len(self.layout.text_objects)
        self._texts[self.layout.text_index["SIM::axis_names"]] = " ".join(
            f"{a}={self.cfg.axes[a].params.name or a}" for a in self.axes
        )

    def _owner(self) -> tuple[object, ...]:
        """The parts whose arrays the snapshot's columns are taken from."""
        return (self.kernel, self.motion, self.twin, self.volc)

    def _build_snapshot(self) -> Snapshot:
        """docs/design.md §5 step 4: every object of every axis, from this cycle's state."""
        k, mo = self.kernel, self.motion
        if self._src_owner != self._owner():
            self._layout_sources()
        derived(k.F7, mo.F, mo.B, self._mrows)  # deltas, displayed position, units
        np.concatenate(self._pieces, axis=1, out=self._stack)
        return self._snapshot_of(self._stack.take(self._columns, axis=1))

    def _snapshot_of(self, v: np.ndarray) -> Snapshot:
        """The snapshot of the cycle reached with the axis values `v` and the machine
        objects and texts of the present state."""
        mach = self._mach_template.copy()
        mc = self._mc
        mach[mc.cycle_count] = self.cycle & 0xFFFF_FFFF
        mach[mc.cycle_time_us] = round(self.cycle_s * 1e6)
        mach[mc.overruns] = self.overruns
        mach[mc.last_error_id] = self.last_error_id
        player = self.player
        if player is not None:
            mach[mc.program_running] = float(player.running)
            mach[mc.program_line] = player.line
        mach[mc.ambient_temperature] = self.twin.ambient
        mach[mc.twin_time] = self.twin.time
        mach[mc.spindle_on] = float(self.spindle_on)
        volc = self.volc
        mach[mc.volc_active], mach[mc.volc_available] = volc.active_mask, volc.available_mask
        mach[mc.volc_index] = self.volc_index
        mach[mc.volc_tool_length] = volc.tool_length
        mach[mc.volc_incorrect] = volc.incorrect_mask
        self._texts[self._text_slot] = self.last_error
        self._texts[self._volc_file_slot] = volc.file_of(self.volc_index)
        return Snapshot(
            self.cycle,
            self.axes,
            v,
            np.array(mach, dtype=float),
            self.layout,
            tuple(self._texts),
            self.epoch + self.cycle * self.period_ticks,
        )

    # ------------------------------------------------------------------ events

    def _record(self, d: Diagnostic) -> Event:
        ev = Event(self.cycle, d)
        self.events.append(ev)
        if d.error_id:
            self.last_error_id = d.error_id
        if d.severity != "message":  # a #MSG is no error (SIM::last_error)
            self.last_error = d.describe()
        for listener in tuple(self.event_listeners):
            listener(ev)
        return ev

    def record(self, diagnostic: Diagnostic) -> Pending:
        """A warning or error the server found, into the error list now, from any thread.

        The published snapshot is re-issued with the new `SIM::last_error(_id)` (same
        cycle, same values otherwise), so a client that reads them right after the
        server's answer sees the reason — also in stepped mode, where no cycle may come.
        The cycle lock keeps this from replacing a newer snapshot."""
        with self._cycle_lock:
            self._record(diagnostic)
            snap = self.snapshot
            machine = snap.machine.copy()
            machine[self._mc.last_error_id] = self.last_error_id
            texts = list(snap.texts)
            texts[self._text_slot] = self.last_error
            self._show(replace(snap, machine=machine, texts=tuple(texts)))
        return resolved()

    def report(self, error_id: int, message: str, line: int = 0, axis: int = 0) -> None:
        """Record an error raised while running (NC program, monitoring)."""
        self._record(
            Diagnostic(
                "error",
                message,
                file="<nc>" if line else "",
                line=line,
                error_id=error_id,
                axis=axis,
            )
        )

    def message(self, text: str, line: int) -> None:
        """`#MSG ["text"]` (000 p.96): an event of severity "message" with the program
        line, in the error list and on every interface that hands out events."""
        self._record(Diagnostic("message", text, file="<nc>", line=line))

    # ------------------------------------------------------------------ object writes

    def slot(self, axis: int) -> int:
        return self.axes.index(axis)

    def apply_write(self, obj: ObjectDef | str, axis: int, value: Any) -> None:
        """Apply a validated object write (runs at a cycle boundary, docs/design.md §5 step
        1): `obj` as the service resolved it (a name: looked up here)."""
        if isinstance(obj, str):
            obj = self.dictionary.by_name(obj)
        slot = self.slot(axis) if obj.scope == "axis" else -1
        if obj.name in self.tempc.names:  # a TEMPC parameter of this dictionary
            self.kernel.write_tempc(slot, obj.key_field, float(value))
            return
        _WRITE_HANDLERS[obj.name](self, slot, value)

    def set_comp(self, slot: int, kinds: CompKind, on: bool) -> int:
        """COMP ON/OFF (manual §5.1). Returns 70495 for `COMP ON FRICT` without
        `lr_param.frict_comp` (000 p.73), else 0.

        COMP ON switches on only compensations the axis list enables (`listed_kinds`: what
        `*::activated` reads, "activated (selected) via" the axis parameter, 000 p.35;
        a list error clears the parameter, 000 §2.4): `COMP ON CROSS` on an axis
        without cross compensation leaves `CROSSC::activated` FALSE, and a temperature
        compensation its list's error switched off (990271) stays off, its `offset_0`
        not output. The manual names an error for friction only; the others change
        nothing."""
        params = self.cfg.axes[self.axes[slot]].params
        if on and kinds & CompKind.FRICT and not params.frict_comp:
            return CncErrorId.FRICT_NOT_SELECTED
        if on:
            kinds &= listed_kinds(params)
        for kind in COMP_ORDER:
            if kinds & kind:
                self.kernel.set_selected(slot, kind, on)
        return 0

    def program_end(self) -> None:
        """M30: manual-activation compensations are deselected (manual §5.1); a
        volumetric compensation linked to the channel that is still active is reduced
        without movement, with an error at the M30's line (004 p.24)."""
        self._deselect_all_manual()
        line = self.player.line if self.player is not None else 0
        for ident in self.volc.program_end():
            self.report(
                VOLC_ERROR,
                f"volumetric compensation {ident} is linked to the channel "
                "(associate_to_channel 1) and still active at program end: its values "
                "reduced without movement (004 p.24)",
                line,
            )

    def _deselect_all_manual(self) -> None:
        """Program end and reset: every axis' manual-activation compensations (§5.1)."""
        for slot in range(len(self.axes)):
            self._deselect_manual(slot)

    def release_axis(self, slot: int) -> None:
        """`#PUT AX`: the axis leaves the NC channel (000 §5.1 "release of the axis")."""
        self._deselect_manual(slot)

    def _deselect_manual(self, slot: int) -> None:
        """Deselect the axis' manual-activation compensations: at the end of the NC
        program, at CNC reset and on release of the axis (000 §3.2 p.17, §4.2–4.4,
        §4.6 P-COMP-00065, §5.1). The offset is executed at once."""
        manual = self._manual_kinds(slot)
        if manual:
            self.set_comp(slot, manual, False)
            self.kernel.release(slot, manual)

    def _manual_kinds(self, slot: int) -> CompKind:
        """The axis' compensations configured with manual activation."""
        ax = self.cfg.axes[self.axes[slot]]
        manual = CompKind(0)
        if ax.params.temp_comp_manual_activation:
            manual |= CompKind.TEMP
        comp = ax.comp
        if comp is not None:
            for kind, part in (
                (CompKind.CROSS, comp.cross),
                (CompKind.PLANE, comp.plane),
                (CompKind.LEAD, comp.lsec),
                (CompKind.CROSSTALK, comp.crosstalk),
            ):
                if part is not None and part.manual_activation:
                    manual |= kind
        return manual

    def reload(self, cfg: MachineConfig) -> None:
        """Swap in a validated configuration at this cycle boundary (docs/design.md §4).

        Active compensations ramp from the old to the new value with their n_cycles
        (the kernel treats the swap as a step event).
        """
        self.cfg = cfg
        self.kernel.reload(cfg)
        # the lists as the start-up list names them again (004 p.23: an update by CNC
        # object does not change the configuration); what was switched on stays on
        old = self.volc
        self.volc = self._new_volc(cfg)
        self.volc.carry_over(old)
        self._volc_loading.clear()  # an UPDATE still reading belongs to the old lists
        self._volc_files.clear()
        twin = self._new_twin(cfg)
        twin.take_state(self.twin)  # the machine does not cool down on a reload
        self.twin = twin
        self._lose[:] = [cfg.axes[a].params.lose for a in self.axes]
        for d in cfg.diagnostics:
            self._record(d)

    def _new_volc(self, cfg: MachineConfig) -> VolKernel:
        return VolKernel(
            cfg.volumetric,
            self.axes,
            [cfg.axes[a].params for a in self.axes],
            report=lambda error_id, message: self.report(error_id, message),
        )

    def _new_twin(self, cfg: MachineConfig) -> TwinEngine:
        """The machine behind the controller; without a twin file a perfect machine at
        the reference temperature (true position = output position)."""
        names = [cfg.axes[a].params.name or str(a) for a in self.axes]
        periods = [
            cfg.axes[a].params.modulo_period if cfg.axes[a].params.modulo else 0.0
            for a in self.axes
        ]
        return TwinEngine(
            cfg.twin or TwinConfig(), names, self.cycle_s, self.time_scale, modulo=periods
        )

    def start_program(self, text: str, mdi: bool = False) -> Pending:
        """Parse an NC program (raises `NcError`) and run it from the next cycle on."""
        return self.submit(StartProgram(parse_program(text, self.names, mdi=mdi), mdi, text))

    def reset(self) -> None:
        """CNC reset: stop the program and every axis (controlled stop), deselect the
        manual-activation compensations (manual §5.1)."""
        if self.player is not None and self.player.running:
            self.player.abort()
        self.motion.stop()
        self._deselect_all_manual()
        self.volc.reset()  # 004 p.24: every volumetric compensation off, no movement
        self._volc_loading.clear()  # an UPDATE still reading is given up

    def start(self, prog: Program, mdi: bool = False) -> None:
        """Run a parsed program (or MDI lines) from the next cycle on."""
        if self.player is not None and self.player.running:
            raise AdsError(
                AdsErrorCode.DEVICE_BUSY,
                f"an NC program is running (line {self.player.line}); wait for its end",
                "nc",
            )
        for w in prog.warnings:
            self._record(w)
        self.player = Player(prog, self.nc_side, self.cycle_s, mdi=mdi)

    def set_drive_enable(self, slot: int, on: bool) -> None:
        """`SIM::drive_enable`: without it the axis' cross and plane compensation are not
        effective (000 §5.3 p.97 item 4) and the drive holds its actual position."""
        self.kernel.set_drive_enabled(slot, on)


B, T, X, P, L, K = (
    CompKind.BACKLASH,
    CompKind.TEMP,
    CompKind.CROSS,
    CompKind.PLANE,
    CompKind.LEAD,
    CompKind.CROSSTALK,
)
#: Axis objects fed by a kernel [n, 7] array: object -> (array, compensation) (docs/design.md §2).
_FROM_COMP: dict[str, tuple[str, CompKind]] = {
    "BC::actual backlash": ("actual", B),
    "BC::sum backlash": ("target", B),
    "BC::delta backlash": ("delta", B),
    "TEMPC::f_is_active": ("effective", T),
    "TEMPC::actual_offset": ("actual", T),
    "CROSSC::f_is_active": ("effective", X),
    "CROSSC::actual_offset": ("actual", X),
    "CROSSC::delta_offset": ("delta", X),
    "CC2::correction": ("actual", P),
    "LSEC::active": ("effective", L),
    "LSEC::epsilon": ("delta", L),
    "LSEC::sum epsilon": ("actual", L),
    "CROSSTALK::actual_offset": ("actual", K),
    "CROSSTALK::delta_offset": ("delta", K),
    "CROSSTALK::end_offset": ("target", K),
    **{name: ("selected", kind) for kind, name in SELECTED_OBJECTS.items()},
}
#: Columns of the machine's per-cycle buffer `Machine._mbuf`: the published deltas of
#: the 7 compensations (from column "delta" on, kernel column order), then vectors
#: computed by `Machine._build_snapshot` and the configured backlash.
_MBUF: dict[str, int] = {
    "delta": 0,
    "display": DISPLAY,  # motion.display_pos()
    "velocity": VELOCITY,  # motion.vel / UNITS_PER_UM
    "acceleration": ACCELERATION,  # motion.acc / UNITS_PER_MM
    "feed": FEED_UM,  # motion.feed / UNITS_PER_UM
    "output": OUTPUT,  # motion.pos + kernel.total_offset
    "lose": LOSE,
}
#: Axis objects fed by per-axis state vectors (emulator group, TEMPC parameters): the
#: live vector (updated in place) a column is read from, or the name of a column of
#: the machine buffer (`_MBUF`).
_FROM_STATE: dict[str, str | Callable[[Machine], np.ndarray]] = {
    "BC::conf. backlash": "lose",
    "SIM::command_position": "display",
    "SIM::set_position": "display",
    "SIM::target_position": lambda m: m.motion.target,
    "SIM::velocity": "velocity",
    "SIM::acceleration": "acceleration",
    "SIM::homed": lambda m: m.motion.homed,
    "SIM::output_position": "output",
    "SIM::drive_actual_position": lambda m: m._drive_act,
    "SIM::drive_enable": lambda m: m.kernel.drive_enabled,
    "SIM::total_offset": lambda m: m.kernel.total_offset,
    "SIM::feed": "feed",
    "FRICT::additive_current": lambda m: m.kernel.friction_current,
    "SIM::axis_type": lambda m: m._axis_type,
    "TWIN::sensor_temperature": lambda m: m.twin.sensor_temperature,
    "TWIN::true_position": lambda m: m.twin.true_position,
    "TWIN::residual": lambda m: m.twin.residual,
    "TWIN::friction_current": lambda m: m.twin.friction_current,
    "VOLC::correction": lambda m: m.volc.offset,
    "VOLC::held": lambda m: m.volc.held,
}


def _unfed(layout: ObjectLayout, where: Sequence[tuple[str, int] | None]) -> list[str]:
    """The readable objects no source feeds: an axis object without its column
    (`where`), a machine object without its `_MachineColumns` field, a text the
    machine does not write. Each would read 0 (or "") without a word."""
    fed = {*_MachineColumns.objects(), *_TEXTS}
    axis = zip(layout.axis_objects, where, strict=True)
    machine = (*layout.machine_objects, *layout.text_objects)
    return [
        *(o.name for o, w in axis if w is None and o.readable),
        *(o.name for o in machine if o.name not in fed and o.readable),
    ]


def _tempc_row(row: int) -> Callable[[Machine], np.ndarray]:
    """The live TEMPC parameter of row `row` (`temperature.Bindings` order): a row of the
    kernel's parameter block, bound per machine from its own dictionary."""
    return lambda m: m.kernel.tempc_params[row]


def _move(m: Machine, slot: int, target: float) -> None:
    moves = target != m.motion.pos[slot]
    try:
        m.motion.move_to(slot, target)
    except MotionError as exc:
        raise AdsError(AdsErrorCode.DEVICE_BUSY, f"axis {m.axes[slot]}: {exc}") from None
    if moves:
        m.kernel.release(slot)  # a motion of the axis executes a held COMP offset


def _set_tempc_activated(m: Machine, slot: int, on: bool) -> None:
    """A selection by object acts at once, also on an offset a NO_MOVE held back.

    The object activates the compensation also without `temp_comp 1` (000 p.17), but
    not one its list's error switched off (000 §2.4: the compensation is deactivated;
    990271): TRUE is refused with 0x70B and the diagnostic, as `COMP ON TEMP` leaves it
    off (`set_comp`)."""
    if on:
        axis = m.axes[slot]
        for d in m.cfg.deactivated:
            if d.axis == axis and d.deactivated == CompKind.TEMP:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDPARM,
                    f"axis {axis}: temperature compensation is deactivated by a list "
                    f"error, not switched on: {d.describe()}",
                )
    m.kernel.set_selected(slot, CompKind.TEMP, on)
    m.kernel.release(slot, CompKind.TEMP)


def _volc_switch(m: Machine, ident: int, on: bool) -> None:
    """cnc_vol_comp_enable/disable_index_w (004 p.22): like #VOLCOMP ON/OFF [ID..]. An
    ID that is not configured or not available answers 0x706 (invalid data)."""
    try:
        m.volc.switch(ident, on, homed=m.motion.homed, drive=m.kernel.drive_enabled)
    except (KeyError, ValueError) as exc:
        message = str(exc.args[0]) if exc.args else str(exc)
        m.report(VOLC_ERROR, message)
        raise AdsError(AdsErrorCode.DEVICE_INVALIDDATA, message) from None


def _set_homed(m: Machine, slot: int, value: Any) -> None:
    if value:
        m.motion.home(slot)
    else:
        m.motion.homed[slot] = False


_WRITE_HANDLERS: dict[str, Callable[[Machine, int, Any], None]] = {
    "TEMPC::activated": lambda m, s, v: _set_tempc_activated(m, s, bool(v)),
    "SIM::target_position": lambda m, s, v: _move(m, s, float(v)),
    "SIM::homed": _set_homed,
    "SIM::drive_enable": lambda m, s, v: m.set_drive_enable(s, bool(v)),
    "SIM::feed": lambda m, s, v: m.motion.feed.__setitem__(
        s, min(float(v) * UNITS_PER_UM, m.cfg.axes[m.axes[s]].params.v_max)
    ),
    "SIM::set_position": lambda m, s, v: m.motion.set_position(s, float(v)),
    "TWIN::spindle_on": lambda m, s, v: setattr(m, "spindle_on", bool(v)),
    "TWIN::ambient_temperature": lambda m, s, v: m.twin.hold_ambient(float(v)),
    "TWIN::soak": lambda m, s, v: m.twin.soak(),
    "VOLC::tool_length": lambda m, s, v: setattr(m.volc, "tool_length", float(v)),
    "cnc_interpr_vol_comp_index_w": lambda m, s, v: setattr(m, "volc_index", int(v)),
    "cnc_vol_comp_enable_index_w": lambda m, s, v: _volc_switch(m, int(v), True),
    "cnc_vol_comp_disable_index_w": lambda m, s, v: _volc_switch(m, int(v), False),
}


def _warm_up() -> None:
    """`jit.load`'s warm-up (geo_server/jit.py): the default machine moving cycle by cycle
    and in a pass, then standing until quiescent, skipping at rest and publishing — so the
    machine code of each path is loaded before a real machine needs it."""
    from geo_server.listfile.loader import load_machine
    from geo_server.paths import default_startup_list

    m = Machine(load_machine(default_startup_list()), homed=True)
    m.start_program("N10 G91 G01 X1 Y-1 F3000\nM30\n")
    m.step(3)
    m.run_batch(8)
    for _ in range(400):
        if m.quiescent:
            break
        m.run_cycle(publish=False)
    m.skip(300)
    m.publish()


# ---------------------------------------------------------------------- the NC side


#: seconds a #VOLCOMP UPDATE may take to read its files before it is given up
VOLC_LOAD_TIMEOUT = 30.0
#: the longest name `V.G.VOLCOMP[i].FILE[j] = "…"` takes (a STRING of 255, as the CNC's)
MAX_VOLC_FILE_NAME = 255


def _in_worker(fn: Callable[[], Any]) -> Future[Any]:
    """Run `fn` in a daemon thread of its own (reading files off the cycle: one that
    never delivers, a FIFO or a dead share, holds up neither other machines nor the
    interpreter's exit)."""
    fut: Future[Any] = Future()

    def run() -> None:
        try:
            fut.set_result(fn())
        except BaseException as exc:  # handed to the cycle, which reports it
            fut.set_exception(exc)

    threading.Thread(target=run, name="volcomp-load", daemon=True).start()
    return fut


class NcSide:
    """The machine as the NC player sees it (`nc.MachinePort`, `Machine.nc_side`):
    positions, moves, homing, COMP and #VOLCOMP switches, the compensation states the
    V.A variables read (000 §5). One role, one class: `Machine` is what the object
    service and the scheduler drive; this is what an NC program drives, over the same
    machine, on the cycle's thread (the player runs in the cycle)."""

    def __init__(self, machine: Machine) -> None:
        self._m = machine

    def position(self, slot: int) -> float:
        return float(self._m.motion.pos[slot])

    def modulo_period(self, slot: int) -> float:
        return float(self._m._period[slot]) if self._m._modulo[slot] else 0.0

    def move_linear(
        self,
        targets: dict[int, float],
        feed: float | None,
        rapid: bool,
        next_dirs: dict[int, int],
    ) -> None:
        moving = [slot for slot, target in targets.items() if target != self._m.motion.pos[slot]]
        self._m.motion.move_linear(targets, feed, rapid)
        for slot in moving:
            self._m.kernel.release(slot)  # the axis' next motion (COMP … NO_MOVE)
        for slot, direction in next_dirs.items():
            self._m.motion.announce_next(slot, direction)

    def home(self, slots: Sequence[int]) -> None:
        for slot in slots:
            self._m.motion.home(slot)

    def in_position(self, slots: Iterable[int]) -> bool:
        return self._m.motion.all_in_position(slots)

    def stop_axes(self, slots: Iterable[int]) -> None:
        for s in slots:
            self._m.motion.stop(s)

    def comp(self, slot: int, on: bool, kinds: CompKind, no_move: bool) -> int:
        return self._switch(slot, kinds, on, no_move)

    def comp_off_all(self, slot: int, no_move: bool) -> int:
        return self._switch(slot, ALL_KINDS, False, no_move)

    def _switch(self, slot: int, kinds: CompKind, on: bool, no_move: bool) -> int:
        """COMP ON/OFF (000 §5.1 p.94). Without NO_MOVE the offset is executed now (the
        program waits for it), together with any offset an earlier NO_MOVE held back; with
        NO_MOVE it is held until the axis' next motion."""
        before = self._m.kernel.selected[slot].copy()
        err = self._m.set_comp(slot, kinds, on)
        if err:
            return err
        # only a switch that changes the selection has an offset to hold; an axis in
        # motion executes it with that motion
        changed = mask_of(
            k for k in COMP_ORDER if before[COLUMN[k]] != self._m.kernel.selected[slot, COLUMN[k]]
        )
        if no_move and self._m.motion.all_in_position([slot]):
            self._m.kernel.hold(slot, changed)
        else:
            self._m.kernel.release(slot)
        return 0

    def volcomp(self, cmd: VolcompCommand) -> tuple[int, str]:
        """`#VOLCOMP …` (004 p.21-23): switch, or start reading the files of an UPDATE
        in a worker thread (the cycle never waits for a disk); ALL switches every
        available compensation."""
        volc = self._m.volc
        ids = cmd.ids
        if ids is None:
            ids = tuple(
                i for i, st in volc.states.items() if st.evaluator is not None or not cmd.on
            )
        try:
            for ident in ids:
                if cmd.update:
                    self._volc_update(ident)
                else:
                    volc.switch(
                        ident,
                        cmd.on,
                        cmd.no_move,
                        cmd.cfact,
                        self._m.motion.homed,
                        self._m.kernel.drive_enabled,
                    )
        except (KeyError, ValueError) as exc:
            return VOLC_ERROR, str(exc.args[0]) if exc.args else str(exc)
        return 0, ""

    def _volc_update(self, ident: int) -> None:
        """Read compensation `ident` again from its VOLC list (004 p.23)."""
        comp = self._m.volc.get(ident).comp
        cfg = self._m.cfg

        written = dict(self._m._volc_files.get(ident, {}))

        def load() -> tuple[Any, list[Diagnostic]]:
            diags: list[Diagnostic] = []
            path = comp.path or comp.file_name
            new = reload_compensation(cfg, ident, path, Reporter(diags), written)
            return new, diags

        self._m._volc_loading.append((ident, monotonic(), _in_worker(load)))

    def volcomp_active(self, ident: int) -> bool:
        st = self._m.volc.states.get(ident)
        return st is not None and st.active

    def volcomp_file(self, ident: int, index: int) -> str:
        written = self._m._volc_files.get(ident, {})
        if index in written:
            return written[index]
        st = self._m.volc.states.get(ident)
        cfg = st.comp.config if st is not None else None
        if cfg is None:
            return ""
        by_slot = dict(zip(cfg.file_slots, (name for name, _, _ in cfg.files), strict=True))
        return by_slot.get(index, "")

    def set_volcomp_file(self, ident: int, index: int, name: str) -> tuple[int, str]:
        if ident not in self._m.volc.states:
            return VOLC_ERROR, (
                f"V.G.VOLCOMP[{ident}].FILE[{index}]: no volumetric compensation {ident} "
                f"(vol_comp[{ident}] in the start-up list, 004 p.12)"
            )
        if not name.strip() or len(name) > MAX_VOLC_FILE_NAME:
            return VOLC_ERROR, (
                f"V.G.VOLCOMP[{ident}].FILE[{index}]: a file name of 1 … "
                f"{MAX_VOLC_FILE_NAME} characters"
            )
        self._m._volc_files.setdefault(ident, {})[index] = name.strip()
        return 0, ""

    def volcomp_settled(self) -> bool:
        """The #VOLCOMP ramps are over and the updates read and applied. An update
        whose files did not load keeps the compensation as it was (like the CNC object,
        docs/volumetric.md §7) and ends the program with its error; one still reading
        after `VOLC_LOAD_TIMEOUT` s (a file that never delivers) is given up."""
        while self._m._volc_loading:
            ident, since, fut = self._m._volc_loading[0]
            if not fut.done():
                if monotonic() - since < VOLC_LOAD_TIMEOUT:
                    break
                self._m._volc_loading.pop(0)
                raise AdsError(
                    AdsErrorCode.DEVICE_TIMEOUT,
                    f"#VOLCOMP [ID{ident} UPDATE]: its files were not read within "
                    f"{VOLC_LOAD_TIMEOUT:.0f} s",
                )
            self._m._volc_loading.pop(0)
            new, diags = fut.result()
            for d in diags:
                self._m._record(d)
            if new is None or not new.available:
                why = new.problem if new is not None else "not configured"
                raise AdsError(
                    AdsErrorCode.DEVICE_SYNTAX,
                    f"#VOLCOMP [ID{ident} UPDATE] failed, compensation unchanged: {why}",
                )
            self._m.volc.update(ident, new)
            self._m._volc_files.pop(ident, None)  # (the loaded list carries the names given)
        return not self._m._volc_loading and self._m.volc.at_rest

    def comp_settled(self, slots: Iterable[int]) -> bool:
        """000 §5.1: the offset of a COMP switch is travelled before the program goes
        on, i.e. the program waits until the axis' sin² ramps have ended (NO_MOVE
        blocks do not wait: their offset is held until the axis' next motion)."""
        return not any(self._m.kernel.ramping(s) for s in slots)

    def effective(self, slot: int) -> CompKind:
        """Effective now: the present selection (a COMP of this cycle included) with the
        preconditions of the last cycle (000 §5.3; docs/design.md §6.8)."""
        k = self._m.kernel
        return mask_of(
            kind
            for i, kind in enumerate(COMP_ORDER)
            if k.selected[slot, i] and k.preconditions[slot, i]
        )

    def required(self, slot: int) -> CompKind:
        """`prog_movement_requires_compensations` ∩ compensations selected in the axis
        list: errors only for compensations also enabled there (000 §5.3, p.97)."""
        p = self._m.cfg.axes[self._m.axes[slot]].params
        monitored = ~(CompKind.FRICT | CompKind.CROSSTALK)  # no bit in 000 p.98
        return p.prog_movement_requires_compensations & listed_kinds(p) & monitored

    def initialised(self, slot: int) -> CompKind:
        """`V.A.<name>_COMP_INIT` (000 §5.2 p.95): enabled in the axis list and validly
        configured (a valid table whose masters are axes of the machine), whether or not
        it is selected (manual activation) or effective yet."""
        p = self._m.cfg.axes[self._m.axes[slot]].params
        on = self._m.kernel.configured[slot]
        configured = mask_of(k for i, k in enumerate(COMP_ORDER) if on[i])
        return listed_kinds(p) & configured

    def current(self, slot: int, kind: CompKind) -> float:
        """`V.A.<name>_COMP_CURR` (000 §5.2 p.96): the output in mm (° on rotary axes);
        friction, which has no position offset here, gives its additive current."""
        value = float(self._m.kernel.actual[slot, COLUMN[kind]])
        return value if kind == CompKind.FRICT else value / UNITS_PER_MM

    def program_end(self) -> None:
        """M30 (`Machine.program_end`: it shares the deselection with a reset)."""
        self._m.program_end()

    def release_axis(self, slot: int) -> None:
        """`#PUT AX` (`Machine.release_axis`)."""
        self._m.release_axis(slot)

    def report(self, error_id: int, message: str, line: int) -> None:
        """An error of the program, at its line, in the machine's errors list."""
        self._m.report(error_id, message, line)

    def message(self, text: str, line: int) -> None:
        """`#MSG` (`Machine.message`)."""
        self._m.message(text, line)


# last: registered after `load`, the warm-up runs at once and needs every name above
jit.on_load(_warm_up)
