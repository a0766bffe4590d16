"""ADS notifications on the event loop (docs/design.md §9, §13): registering and
deleting them (the `notifications.NotificationTable` holds them, sans-I/O), the hand-off
of the cycles' snapshots from the cycle thread to the loop, and the sampling passes,
shared fairly between the machines behind one port in rounds of `sample_budget`.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from typing import Protocol, cast

from geo_server.errors import AdsError
from geo_server.seam import HELD_MAX
from geo_server.service import varies_at_rest
from geo_server.snapshot import Snapshot
from geo_server.transports.ads import codec, handles, symbols
from geo_server.transports.ads.codec import AddNotificationRequest, AmsHeader, Stamp
from geo_server.transports.ads.connection import Connection
from geo_server.transports.ads.device import Device
from geo_server.transports.ads.notifications import Batch, SamplingPass
from geo_server.transports.ads.options import HANDOFF_MAX, NOTIFICATIONS_STATUS

#: Registrations sampled between two looks at the clock (keeps the budget check cheap).
_SAMPLE_STEP = 32
#: A machine's share of one sampling round is at least this long (seconds), however many
#: machines have samples waiting: a pass makes progress in every round.
_MIN_SHARE = 0.0002
#: How long (seconds) the cycles stay demanded after the last registration went: the
#: cycle process answers a new demand with its next frame, and the registration that
#: makes it waits for that (`ProcessScheduler.demand_every_cycle`); a client adding and
#: deleting (or failing to add) one registration after another waits once, not each time.
DEMAND_LINGER_S = 1.0


def add_notification(
    dev: Device, conn: Connection, h: AmsHeader, req: AddNotificationRequest, port: int
) -> bytes:
    """AddDeviceNotification at the task (or system) port `port`."""
    hold = 0.0
    if dev.service.info.running:
        hold = time.monotonic() + dev.options.first_sample_hold
    if req.index_group == symbols.SYM_VALBYHND:
        ig, io = handles.address(dev, conn, port, req.index_group, req.index_offset)
        req = replace(req, index_group=ig, index_offset=io)
    sampler = dev.sampler
    # the cycles the registrations want from now on, before the first one's cycle
    sampler.demand(True)
    try:
        reg = dev.notifications.add(
            conn,
            h.source,
            h.target,
            req,
            dev.service.current(stale_ok=True),
            hold_until=hold,
            prepare=lambda ig, io, length, snap: _getter(dev, port, ig, io, length, snap),
            steady=lambda ig, io: _steady(dev, port, ig, io),
        )
    finally:
        sampler.demand(len(dev.notifications) > 0)
        sampler.update_status()
    return codec.add_notification_response(0, reg.handle)


def delete_notification(
    dev: Device, conn: Connection, handle: int, *, update_status: bool = True
) -> None:
    """DeleteDeviceNotification (0x714 for a handle not `conn`'s)."""
    dev.notifications.delete(conn, handle)
    dev.sampler.demand(len(dev.notifications) > 0)
    if update_status:
        dev.sampler.update_status()


def _getter(
    dev: Device, port: int, ig: int, io: int, length: int, snap: Snapshot
) -> Callable[[Snapshot], bytes]:
    """Check a notification's address by reading it (0x702…0x705 as a Read answers)
    and resolve it once: sampling then only encodes the value of each snapshot (an
    attribute is a constant)."""
    constant = handles.service_read(dev, port, ig, length)
    if constant is not None and ig in handles.NOTIFIABLE_SERVICES:
        return lambda _snap: constant
    data = dev.service.read(ig, io, length, snap, port=port)
    obj, axis, attr = dev.service.resolve(ig, io, port=port)
    if attr is not None:
        return lambda _snap: data
    return lambda later: later.encode(obj, axis)


def _steady(dev: Device, port: int, ig: int, io: int) -> bool:
    """The value a notification watches cannot change while the machine is at rest
    (a constant service, an attribute, or an object `varies_at_rest` is False for)."""
    if ig in handles.NOTIFIABLE_SERVICES:
        return True
    try:
        obj, _axis, attr = dev.service.resolve(ig, io, port=port)
    except AdsError:
        return False
    return attr is not None or not varies_at_rest(obj)


class _Sink(Protocol):
    """What sampling needs of a registration's owner (`protocol.AdsConnection`)."""

    @property
    def backlog(self) -> int: ...

    def send(self, frame: bytes) -> None: ...


#: the passes whose median cost is what a pass costs (`Sampler._oldest_fresh`)
_COSTS_KEPT = 15


class Sampler:
    """One machine's notification sampling; the head's (the server that listens) also
    runs the rounds over every machine behind the port. It is the engine's
    `CycleDemand` while registrations exist."""

    def __init__(self, dev: Device) -> None:
        self.dev = dev
        #: what `status()` shows of the notifications (kept current, read by status)
        self._status: dict[str, int] = {}
        #: head: the machines with snapshots to sample, served in turn (`_sample_round`)
        self._ready: deque[Sampler] = deque()
        self._round_pending = False
        self._notify_invoke = 0
        # Cycle thread -> loop hand-off of the cycles' snapshots, each with the monotonic
        # time it was handed over (see `on_cycle_thread`, `_oldest_fresh`).
        self._handed: deque[tuple[Snapshot, float]] = deque(maxlen=HANDOFF_MAX)
        self._handoff_pending = False
        # The sampling pass under way (with its FILETIME), the time spent on it so far,
        # and what a whole pass costs (seconds of the loop thread's own CPU time, the
        # median of the last `_COSTS_KEPT`: one pass that met a garbage collection does
        # not make the sampler shed cycles; `_oldest_fresh`).
        self._pass: tuple[SamplingPass, int] | None = None
        self._pass_spent = 0.0
        self._pass_costs: deque[float] = deque(maxlen=_COSTS_KEPT)
        self._pass_cost = 0.0
        # While registrations exist the cycle publishes every cycle's snapshot.
        self._every_cycle: Callable[[], None] | None = None
        # the demand's end, `DEMAND_LINGER_S` after the last registration went
        self._linger: asyncio.TimerHandle | None = None

    def stop(self) -> None:
        self._pass = None
        self._handed.clear()
        self._ready.clear()
        self._release(ended=True)

    def demand(self, on: bool) -> None:
        """Ask the engine for the snapshots the registrations want while any exist (the
        exact engine publishes only the cycles someone looks at, docs/design.md §13):
        this sampler is the `CycleDemand` (`wants`). The demand ends `DEMAND_LINGER_S`
        after the last registration went (a new one meanwhile keeps it)."""
        if on:
            if self._linger is not None:
                self._linger.cancel()
                self._linger = None
            if self._every_cycle is None:
                self._every_cycle = self.dev.service.demand_cycles(self)
            return
        if self._every_cycle is None or self._linger is not None:
            return
        loop = self.dev.loop
        if loop is None or loop.is_closed():
            self._release()
        else:
            self._linger = loop.call_later(DEMAND_LINGER_S, self._release)

    def _release(self, ended: bool = False) -> None:
        """End the demand: it lingered long enough with no registration, or the server
        stops (`ended`)."""
        if self._linger is not None:
            self._linger.cancel()
            self._linger = None
        if self._every_cycle is not None and (ended or not len(self.dev.notifications)):
            self._every_cycle()
            self._every_cycle = None

    def wants(self, cycle: int, quiescent: bool) -> bool:
        """`CycleDemand` (engine thread): the registrations want `cycle` published,
        unless `sample_backlog` snapshots already wait for the loop — then the engine
        goes on without it (counted; those samples come from a later cycle)."""
        if not self.dev.notifications.wants(cycle, quiescent):
            return False
        if len(self._handed) >= self._backlog:
            self.dev.stats.samples_refused += 1
            return False
        return True

    @property
    def _backlog(self) -> int:
        """This machine's share of the port's `sample_backlog`, below `HANDOFF_MAX` by
        `HELD_MAX`: the snapshots a catch-up holds back arrive after `wants` counted
        `_handed`, and the deque must not drop them uncounted."""
        head = self.dev.head
        share = max(16, head.options.sample_backlog // len(head.devices))
        return min(share, HANDOFF_MAX - HELD_MAX)

    def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
        """`CycleDemand` (engine thread): the next cycle the registrations want."""
        return self.dev.notifications.next_wanted(cycle, quiescent)

    def update_status(self) -> None:
        """What `status()["ads_notifications"]` shows (a dict the status reads)."""
        st = self._status
        st["registrations"] = len(self.dev.notifications)
        st["samples_late"] = self.dev.notifications.late
        st["samples_refused"] = self.dev.stats.samples_refused
        st["cycles_shed"] = self.dev.stats.cycles_shed
        st["pass_cost_ns"] = round(self._pass_cost * 1e9)
        st["waiting_snapshots"] = len(self._handed)
        self.dev.service.status_extra[NOTIFICATIONS_STATUS] = st

    def on_cycle_thread(self, snap: Snapshot) -> None:
        """GEO cycle thread: hand the cycle's snapshot to the loop, when someone listens.

        Every snapshot is handed over, in cycle order (the exact engine publishes a
        batch of cycles at once, each with its own time stamp, and the samples due in
        each must be taken from it), but at most one hand-off callback is queued at a
        time: one `call_soon_threadsafe` per cycle (each also waking the loop through its
        self-pipe) piles up callbacks whenever the loop is busy. `_on_cycle` works
        through all snapshots handed over, in the head's rounds (`_sample_round`:
        machines in turn). When the loop falls `HANDOFF_MAX` cycles
        behind the oldest ones go, and with running cycles those older than
        `sample_lag` are skipped (`_oldest_fresh`): sampling counts intervals in cycles
        (`NotificationTable.begin`), so a snapshot the loop never saw delays a sample,
        it does not lose one.
        """
        if not len(self.dev.notifications):
            return
        loop = self.dev.loop
        if loop is None or loop.is_closed():
            return
        # Append first, then test the flag (`_on_cycle` clears it, then reads): a
        # snapshot appended after `_on_cycle` looked finds the flag cleared and queues a
        # new hand-off, so no snapshot is left unsampled. deque.append and popleft are
        # atomic; no lock on the cycle thread.
        self._handed.append((snap, time.monotonic()))
        if self._handoff_pending:
            return
        self._handoff_pending = True
        try:
            loop.call_soon_threadsafe(self._on_cycle)
        except RuntimeError:  # the loop closed in between: nobody to notify any more
            self._handoff_pending = False

    def _on_cycle(self) -> None:
        """Event loop: this machine has snapshots to sample; it joins the head's round."""
        self._handoff_pending = False
        head = self.dev.head.sampler
        if self not in head._ready:
            head._ready.append(self)
        head._again()

    def _sample_round(self) -> None:
        """Event loop (head): sample for at most `sample_budget` seconds, the machines
        with snapshots waiting in turn (docs/design.md §13.1).

        Each machine of the round gets an equal share of the budget (at least
        `_MIN_SHARE`) before the next one's turn; one with work left goes to the back of
        the queue. What the budget leaves waits for a later loop iteration
        (`call_soon`): the loop first answers the requests of every transport that
        arrived meanwhile. So one machine's many registrations delay its own samples,
        not the other machines' — nor anyone's requests by more than one budget.
        """
        self._round_pending = False
        ready = self._ready
        now = time.perf_counter()
        deadline = now + self.dev.options.sample_budget
        for turn in range(len(ready)):
            if not ready or (turn and now >= deadline):  # (the first turn always runs)
                break
            sampler = ready.popleft()
            share = max(_MIN_SHARE, (deadline - now) / (len(ready) + 1))
            if sampler._sample(min(deadline, now + share)):
                ready.append(sampler)
            now = time.perf_counter()
        self._again()

    def _sample(self, deadline: float) -> bool:
        """Work on this machine's sampling passes until `deadline`; True when work is
        left (a pass under way or snapshots waiting).

        A pass covers the registrations due at one snapshot; it is begun from the oldest
        snapshot handed over when none is under way. A pass cut short by the deadline
        (thousands of due registrations) goes on in a later turn, still sampling its
        own snapshot and carrying its timestamp — values the client sees are those of
        the cycle they were due at, only later. Passes follow each other in cycle order.
        """
        stats = self.dev.stats
        while True:
            if self._pass is None:
                snap = self._oldest_fresh()
                if snap is None:
                    break  # every snapshot handed over is sampled
                self._pass = (self.dev.notifications.begin(snap, time.monotonic()), snap.stamp)
                stats.sampling_passes += 1
            samples, filetime = self._pass
            began = time.thread_time()  # (the loop's own time: not the host's other work)
            while not samples.done:
                samples.step(_SAMPLE_STEP)
                if time.perf_counter() >= deadline:
                    break
            for batch in samples.take():
                self._send_batch(batch, filetime)
            self._pass_spent += time.thread_time() - began
            if samples.done:
                self._pass = None
                self._pass_costs.append(self._pass_spent)
                self._pass_spent = 0.0
                self._pass_cost = sorted(self._pass_costs)[len(self._pass_costs) // 2]
            else:
                stats.sampling_slices += 1
            if time.perf_counter() >= deadline:
                break
        self.update_status()
        return self._pass is not None or bool(self._handed)

    def _oldest_fresh(self) -> Snapshot | None:
        """The next snapshot to begin a pass at: the oldest one handed over — unless
        working through every snapshot waiting would take longer than `sample_lag` (at
        what a pass has cost lately). Then, with running cycles, those handed over longer
        than `sample_lag` ago are skipped, down to what can be sampled within it: a loop
        that cannot sample every cycle (thousands of registrations on a busy host) would
        otherwise fall further behind with every pass, up to `sample_backlog` cycles, and
        a registration made meanwhile would get its first sample seconds late. Skipped
        cycles are counted (`cycles_shed`); what was due in them is sampled from the
        next pass (late, `NotificationTable.late`). A loop that was only held for a
        while (a busy host, a long request) with passes that cost little catches up
        every cycle, late: a cyclic stream then has no gap."""
        handed = self._handed
        if not handed:
            return None
        lag = self.dev.options.sample_lag
        keep = max(1, int(lag / self._pass_cost)) if self._pass_cost > 0 else len(handed)
        if self.dev.service.info.running and len(handed) > keep:
            oldest = time.monotonic() - lag
            shed = 0
            while len(handed) > keep and handed[0][1] < oldest:
                handed.popleft()
                shed += 1
            self.dev.stats.cycles_shed += shed
        return handed.popleft()[0]

    def _again(self) -> None:
        """Head: another sampling round in a later loop iteration (other requests
        first), while machines wait."""
        if self._ready and not self._round_pending:
            loop = self.dev.loop
            if loop is not None and not loop.is_closed():
                self._round_pending = True
                loop.call_soon(self._sample_round)

    def _send_batch(self, batch: Batch, filetime: int) -> None:
        conn = cast(_Sink, batch.owner)  # the owner of a registration: its connection
        dev = self.dev
        if conn.backlog > dev.options.notification_backlog:
            dev.stats.notifications_dropped += len(batch.samples)
            return
        self._notify_invoke = (self._notify_invoke + 1) & 0xFFFF_FFFF
        payload = codec.device_notification([Stamp(filetime, tuple(batch.samples))])
        conn.send(
            codec.notification_frame(batch.server, batch.client, payload, self._notify_invoke)
        )
        dev.stats.notifications_sent += len(batch.samples)
