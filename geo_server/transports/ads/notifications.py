"""ADS device notifications: registrations and per-cycle sampling, without I/O.

A client registers with AddDeviceNotification (IG, IO, length, transmission mode, max
delay and cycle time in 100 ns ticks — AdsLib `AdsNotificationAttrib`); the server then
sends DeviceNotification frames (command 8, no response) carrying stamps of samples
(Beckhoff "ADS Device Notification"). Here:

- samples are taken at **GEO cycle boundaries** from the published snapshot (the last
  step of a cycle, after the snapshot is complete), so every value a client sees is one
  the service reports at that cycle;
- the cycle time is rounded to a whole number of GEO cycles (at least 1), the
  interval: cyclic modes (CLIENTCYCLE, SERVERCYCLE, SERVERCYCLE2) send every interval,
  on-change modes (CLIENTONCHA, SERVERONCHA, SERVERONCHA2) check every interval and send
  when the bytes differ from the last ones sent. "Every interval" counts from the last
  sample (or check): the next one is due when `cycle - last_cycle >= interval`, so the
  gap is the interval from the first sample on, and a cycle the server never got to
  sample (the event loop only looks at the newest snapshot when it falls behind) delays
  the next sample instead of silently skipping a whole interval;
- like TwinCAT (which samples in its task cycle), the first sample goes out
  unconditionally at the first cycle boundary after the registration — never with the
  response itself: AdsLib creates its notification dispatcher only after the calling
  thread has processed the AddDeviceNotification response (`AmsRouter::AddNotification`),
  and drops samples that arrive earlier ("No dispatcher found for notification"). When
  cycles run by themselves the server also holds the first sample for a few milliseconds
  of wall time (`hold_until`) for the same reason;
- samples are sent as soon as they are taken, which honours any max delay (the max delay
  is an upper bound for batching; there is nothing to batch within one GEO cycle beyond
  what a sampling pass already groups);
- every sample is exactly the registered length (zero-padded when the object is
  shorter): AdsLib drops the whole stamp when a sample size differs from the registered
  one (`AmsConnection.cpp ReceiveNotification`).

Cost. Every operation costs what it touches, never what the whole table holds, so that
thousands of registrations cannot stall the event loop that also answers Modbus, Zenoh
and ADS requests:

- registrations are indexed by handle and by owner (connection): `add` and `delete` are
  O(1), `drop_owner` is O(registrations of that owner);
- registrations wait in **buckets keyed by the cycle at which they are next due**; a
  sampling pass takes only the buckets up to its cycle, so a cycle costs the due
  registrations (on-change ones compare their bytes only then), not all of them;
- within a pass every (index group, index offset, length) is read once from the
  snapshot, however many registrations watch it;
- a pass is **resumable** (`SamplingPass.step(limit)`): the server works through it in
  slices of bounded duration and answers other requests in between. A slice that runs
  later still samples the snapshot the pass began with, so every sample keeps the
  values (and the server the timestamp) of the cycle it was due at;
- the number of registrations is capped per owner, per table (machine) and, through a
  shared `NotificationPool`, for every table of a fleet together (0x716 NOMOREHDLS
  beyond any), which bounds the work of one pass and the memory of the tables;
- the cycles sampled follow the registrations, not the cycle rate (docs/design.md §13):
  a registration is due on a grid, the cycles where `(cycle - phase) % interval == 0`
  through its last sample, and the table tells the exact engine which cycles
  it wants published (`wants`, `next_wanted`: the `CycleDemand` of `machine/port.py`).
  An on-change registration of a value that cannot change while the machine is at rest
  (`steady`, `ObjectDef.varies_at_rest`) wants no cycle of a quiescent stretch: its
  value is the one it had when the stretch began, so the first cycle after the stretch
  is checked instead — a machine at rest is not made to build a snapshot per cycle for
  it. A sample taken later than its grid cycle for another reason (the loop or the
  engine could not keep up) is counted in `late`.

`NotificationTable` is driven by the server: `add`/`delete`/`drop_owner` from requests
and disconnects, `begin(snapshot)` (or `sample(snapshot)`, a whole pass at once) on the
event loop with the newest snapshot — normally once per cycle, fewer when the loop falls
behind (see `AdsServer._on_cycle_thread`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.snapshot import Snapshot
from geo_server.transports.ads.codec import (
    AddNotificationRequest,
    AmsAddr,
    Sample,
    TransMode,
)

#: Modes served; the client-side ones are served like their server-side twins.
CYCLIC_MODES = frozenset({TransMode.CLIENTCYCLE, TransMode.SERVERCYCLE, TransMode.SERVERCYCLE2})
ON_CHANGE_MODES = frozenset({TransMode.CLIENTONCHA, TransMode.SERVERONCHA, TransMode.SERVERONCHA2})
#: Registrations all connections together may hold (0x716 NOMOREHDLS beyond): Beckhoff's
#: recommended maximum for one ADS device, which is also what sampling on one event loop
#: sustains at a 1 ms GEO cycle (the measurements are in `AdsOptions`).
MAX_TOTAL = 550
#: Registrations one connection may hold (0x716 beyond): half the total, so that one
#: client cannot take every handle and at least two clients get their maximum. (The
#: default machine has 136 readable values: one client can watch each twice over.)
MAX_PER_OWNER = MAX_TOTAL // 2
#: Largest registered length (0x717 INVALIDWATCHSIZE beyond).
MAX_WATCH_SIZE = 64 * 1024
#: Registrations every machine of a fleet together may hold (0x716 beyond): twice one
#: machine's `MAX_TOTAL`. A fleet of 100 with this many on-change registrations at
#: interval 1 still answers every machine within milliseconds (bench/fleet_isolation.py,
#: docs/benchmarks.md).
MAX_FLEET = 2 * MAX_TOTAL

Reader = Callable[[int, int, int, Snapshot], bytes]
#: Given (IG, IO, length, snapshot): check the address by reading it (raising AdsError like
#: a read would) and return a getter of its bytes in any later snapshot. Lets a server do
#: the address resolution once per registration instead of once per sample.
Preparer = Callable[[int, int, int, Snapshot], Callable[[Snapshot], bytes]]
#: Given (IG, IO): True when the value there cannot change while the machine is
#: quiescent (`ObjectDef.varies_at_rest` is False for it, or it is a constant).
Steady = Callable[[int, int], bool]


class NotificationPool:
    """The registrations several tables hold together (a fleet's machines): at most
    `limit` (0x716 beyond)."""

    def __init__(self, limit: int = MAX_FLEET) -> None:
        self.limit = limit
        self.count = 0


@dataclass(eq=False, slots=True)
class Registration:
    """One notification handle."""

    handle: int
    owner: Hashable  # the connection that registered it
    client: AmsAddr  # where samples go (the requester's NetId and AMS port)
    server: AmsAddr  # the address the client targeted (source of the notifications)
    index_group: int
    index_offset: int
    length: int
    trans_mode: int
    max_delay: int
    cycle_time: int
    interval: int  # GEO cycles between samples / checks
    last_cycle: int  # cycle of the last sample or check (at first: of the registration)
    last: bytes | None = None  # None until the first sample was sent
    hold_until: float = 0.0  # no sample before this `now` (monotonic seconds)
    #: its value cannot change while the machine is quiescent (`Steady`)
    steady: bool = False
    #: grid of its samples after the first: cycles c with (c - phase) % interval == 0
    phase: int | None = field(default=None, init=False)
    due_at: int = field(default=0, init=False)  # the cycle it was scheduled for
    on_change: bool = field(init=False)
    #: The bucket (cycle) the registration waits in; None while a pass holds it.
    slot: int | None = field(default=None, init=False)
    alive: bool = field(default=True, init=False)  # False once deleted
    key: tuple[int, int, int] = field(init=False)  # what is read: (IG, IO, length)
    getter: Callable[[Snapshot], bytes] = field(init=False)  # its bytes in a snapshot
    #: Samples for equal routes go into one frame; flat, so that hashing it is cheap.
    route: tuple[Hashable, str, int, str, int] = field(init=False)

    def __post_init__(self) -> None:
        self.on_change = self.trans_mode in ON_CHANGE_MODES
        self.key = (self.index_group, self.index_offset, self.length)
        self.route = (
            self.owner,
            self.client.netid,
            self.client.port,
            self.server.netid,
            self.server.port,
        )

    @property
    def due(self) -> int:
        """The cycle at which the next sample (or on-change check) is due."""
        return self.last_cycle + (self.interval if self.last is not None else 1)


@dataclass
class Batch:
    """Samples of one pass for one (connection, client, server) route: one frame."""

    owner: Hashable
    client: AmsAddr
    server: AmsAddr
    samples: list[Sample] = field(default_factory=list)


def cycles_for(cycle_time_ticks: int, cycle_s: float) -> int:
    """A cycle time in 100 ns ticks as a whole number of GEO cycles (nearest, halves
    up), at least 1.

    Integer nanoseconds: in floating point 2.5 ms / 1 ms is 2.4999999999999996, which
    would round a half-way cycle time down.
    """
    period_ns = round(cycle_s * 1e9)
    if period_ns <= 0:
        return 1
    return max(1, (cycle_time_ticks * 100 + period_ns // 2) // period_ns)


_FAILED = b""  # cache marker: reading the address raised (a sample is never empty)


class SamplingPass:
    """The registrations due at one snapshot, worked through in resumable steps.

    Made by `NotificationTable.begin`. `step(limit)` samples up to `limit` of them (all
    when None) and returns how many it looked at; `take()` hands out the batches
    collected so far (one per route, so a slice of many steps still sends one frame per
    connection). A registration deleted before its turn is skipped.
    """

    def __init__(
        self, table: NotificationTable, snapshot: Snapshot, now: float, due: list[Registration]
    ) -> None:
        self.table = table
        self.snapshot = snapshot
        self.cycle = snapshot.cycle
        self.now = now
        self._due = due
        self._pos = 0
        self._cache: dict[tuple[int, int, int], bytes] = {}
        self._batches: dict[tuple[Hashable, str, int, str, int], Batch] = {}

    @property
    def done(self) -> bool:
        return self._pos >= len(self._due)

    @property
    def remaining(self) -> int:
        return len(self._due) - self._pos

    def step(self, limit: int | None = None) -> int:
        start = self._pos
        end = len(self._due) if limit is None else min(len(self._due), start + limit)
        self._pos = end
        cycle, now, cache, batches = self.cycle, self.now, self._cache, self._batches
        table = self.table
        schedule = table._schedule
        buckets = table._buckets
        swept = table._swept if table._swept is not None else cycle
        # the bucket used last (the same for every registration of the same interval)
        last_nxt = -1
        bucket: dict[int, Registration] = {}
        for reg in self._due[start:end]:
            if not reg.alive:
                continue
            if now < reg.hold_until:
                schedule(reg, cycle + 1)  # checked again at the next pass
                continue
            reg.last_cycle = cycle
            if cycle > reg.due_at and reg.phase is not None and not (reg.on_change and reg.steady):
                table.late += 1
            key = reg.key
            data = cache.get(key)
            if data is None:
                try:
                    data = reg.getter(self.snapshot).ljust(reg.length, b"\0")
                except Exception:  # the object vanished (cannot happen today: reload keeps
                    data = _FAILED  # axes); whatever the reader raised, the pass goes on
                cache[key] = data
            if not data:  # _FAILED
                schedule(reg, reg.due)
                continue
            # Next sample or check one interval on (inlined `_schedule`: a pass runs at
            # the newest swept cycle, so that bucket has not been taken yet); a sample
            # off the registration's grid (its first, or a late one) moves the grid.
            interval = reg.interval
            if reg.phase is None or (cycle - reg.phase) % interval:
                table._on_grid(reg, cycle)
            nxt = cycle + interval
            reg.due_at = nxt
            if nxt <= swept:  # a newer pass began meanwhile
                schedule(reg, nxt)
            else:
                if nxt != last_nxt:
                    last_nxt = nxt
                    found = buckets.get(nxt)
                    if found is None:
                        found = buckets[nxt] = {}
                    bucket = found
                bucket[reg.handle] = reg
                reg.slot = nxt
            if reg.on_change and data == reg.last:
                continue
            reg.last = data
            route = reg.route
            batch = batches.get(route)
            if batch is None:
                batch = batches[route] = Batch(reg.owner, reg.client, reg.server)
            batch.samples.append(Sample(reg.handle, data))
        return end - start

    def take(self) -> list[Batch]:
        """The batches collected since the last `take` (and forget them)."""
        out = list(self._batches.values())
        self._batches = {}
        return out


class NotificationTable:
    """All registrations of one server, keyed by handle (unique per server).

    `max_per_owner` and `max_total` cap the registrations of one owner and of all of
    them (AdsError 0x716 NOMOREHDLS beyond either).
    """

    def __init__(
        self,
        read: Reader,
        cycle_s: float,
        max_per_owner: int = MAX_PER_OWNER,
        max_total: int = MAX_TOTAL,
        prepare: Preparer | None = None,
        pool: NotificationPool | None = None,
        steady: Steady | None = None,
    ) -> None:
        self._read = read
        self._prepare = prepare
        self._steady = steady
        #: shared with the other machines of a fleet (its own when alone)
        self.pool = pool if pool is not None else NotificationPool(max_total)
        self.cycle_s = cycle_s
        self.max_per_owner = max_per_owner
        self.max_total = max_total
        self._regs: dict[int, Registration] = {}
        self._by_owner: dict[Hashable, dict[int, Registration]] = {}
        #: cycle -> the registrations due then (insertion ordered, O(1) removal)
        self._buckets: dict[int, dict[int, Registration]] = {}
        #: the newest cycle a pass began at: every bucket up to it has been taken
        self._swept: int | None = None
        self._active: SamplingPass | None = None  # the pass begun last
        self._handles = itertools.count(1)
        #: samples taken later than their grid cycle (not counting on-change checks of
        #: steady values, which a quiescent stretch defers by design)
        self.late = 0
        # The cycles wanted (`wants`): registrations before their first sample want
        # every cycle; the others their grid, (interval, phase) -> registrations, kept
        # for every registration and for those that need quiescent cycles too. The
        # engine reads the tuples (replaced, never mutated) from its own thread.
        self._first = 0
        self._grid: dict[tuple[int, int], int] = {}
        self._grid_rest: dict[tuple[int, int], int] = {}
        self.grid: tuple[tuple[int, int], ...] = ()
        self.grid_rest: tuple[tuple[int, int], ...] = ()

    def __len__(self) -> int:
        return len(self._regs)

    def __contains__(self, handle: object) -> bool:
        return handle in self._regs

    def get(self, handle: int) -> Registration | None:
        return self._regs.get(handle)

    def count_of(self, owner: Hashable) -> int:
        return len(self._by_owner.get(owner, ()))

    @property
    def waiting(self) -> int:
        """Cycles with registrations waiting in them (for tests and statistics)."""
        return len(self._buckets)

    def _getter(
        self, ig: int, io: int, length: int, snap: Snapshot, prepare: Preparer | None = None
    ) -> Callable[[Snapshot], bytes]:
        """Check the address by reading it from `snap`; a getter for later snapshots."""
        prepare = prepare or self._prepare
        if prepare is not None:
            return prepare(ig, io, length, snap)
        read = self._read
        read(ig, io, length, snap)
        return lambda later: read(ig, io, length, later)

    # ------------------------------------------------------------------ registrations

    def add(
        self,
        owner: Hashable,
        client: AmsAddr,
        server: AmsAddr,
        req: AddNotificationRequest,
        snapshot: Snapshot,
        hold_until: float = 0.0,
        prepare: Preparer | None = None,
        steady: Steady | None = None,
    ) -> Registration:
        """Register (the address is checked by reading it from `snapshot`). `prepare`
        and `steady` stand in for the table's own for this registration (the ADS server
        passes the request's AMS port along in them).

        AdsError: 0x713 unsupported mode, 0x705 zero length, 0x717 too long, 0x716 too
        many handles (of this owner or in total), and whatever reading the address
        raises (0x702/0x703/0x705).
        """
        if req.trans_mode not in CYCLIC_MODES and req.trans_mode not in ON_CHANGE_MODES:
            raise AdsError(
                AdsErrorCode.DEVICE_TRANSMODENOTSUPP,
                f"transmission mode {req.trans_mode} is not supported (cyclic 1/3/5, "
                "on-change 2/4/6)",
            )
        if req.length == 0:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDSIZE, "notification length 0")
        if req.length > MAX_WATCH_SIZE:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDWATCHSIZE,
                f"notification length {req.length} > {MAX_WATCH_SIZE}",
            )
        own = self._by_owner.get(owner)
        if own is not None and len(own) >= self.max_per_owner:
            raise AdsError(
                AdsErrorCode.DEVICE_NOMOREHDLS,
                f"more than {self.max_per_owner} notifications on one connection",
            )
        if len(self._regs) >= self.max_total:
            raise AdsError(
                AdsErrorCode.DEVICE_NOMOREHDLS,
                f"more than {self.max_total} notifications on this machine",
            )
        if self.pool.count >= self.pool.limit:
            raise AdsError(
                AdsErrorCode.DEVICE_NOMOREHDLS,
                f"more than {self.pool.limit} notifications on the machines of this server",
            )
        getter = self._getter(req.index_group, req.index_offset, req.length, snapshot, prepare)
        steady = steady or self._steady
        reg = Registration(
            handle=next(self._handles),
            owner=owner,
            client=client,
            server=server,
            index_group=req.index_group,
            index_offset=req.index_offset,
            length=req.length,
            trans_mode=req.trans_mode,
            max_delay=req.max_delay,
            cycle_time=req.cycle_time,
            interval=cycles_for(req.cycle_time, self.cycle_s),
            last_cycle=snapshot.cycle,
            hold_until=hold_until,
            steady=steady is not None and steady(req.index_group, req.index_offset),
        )
        reg.getter = getter
        self._regs[reg.handle] = reg
        self.pool.count += 1
        self._first += 1
        if own is None:
            own = self._by_owner[owner] = {}
        own[reg.handle] = reg
        self._schedule(reg, reg.due)
        return reg

    def delete(self, owner: Hashable, handle: int) -> None:
        """0x714 NOTIFYHNDINVALID when the handle is unknown or another connection's."""
        reg = self._regs.get(handle)
        if reg is None or reg.owner != owner:
            raise AdsError(
                AdsErrorCode.DEVICE_NOTIFYHNDINVALID, f"notification handle {handle} is unknown"
            )
        own = self._by_owner[owner]
        del own[handle]
        if not own:
            del self._by_owner[owner]
        self._forget(reg)

    def drop_owner(self, owner: Hashable) -> int:
        """Forget every registration of a connection (it disconnected)."""
        own = self._by_owner.pop(owner, None)
        if not own:
            return 0
        for reg in own.values():
            self._forget(reg)
        return len(own)

    def _forget(self, reg: Registration) -> None:
        del self._regs[reg.handle]
        reg.alive = False
        self.pool.count -= 1
        if reg.phase is None:
            self._first -= 1
        else:
            key = (reg.interval, reg.phase)
            self._count(self._grid, key, -1)
            if not (reg.on_change and reg.steady):
                self._count(self._grid_rest, key, -1)
        if reg.slot is not None:
            bucket = self._buckets.get(reg.slot)
            if bucket is not None:
                bucket.pop(reg.handle, None)
                if not bucket:
                    del self._buckets[reg.slot]
            reg.slot = None

    # ------------------------------------------------------------------ cycles wanted

    def _on_grid(self, reg: Registration, cycle: int) -> None:
        """`reg` is sampled at `cycle`, off its grid (its first sample, or a late one):
        from now on it is due on the grid through `cycle` (the interval counts from the
        last sample)."""
        old = reg.phase
        reg.phase = cycle % reg.interval
        key = (reg.interval, reg.phase)
        rest = not (reg.on_change and reg.steady)
        # the new grid point first, then the old one goes: the engine never sees neither
        self._count(self._grid, key, +1)
        if rest:
            self._count(self._grid_rest, key, +1)
        if old is None:
            self._first -= 1
        else:
            self._count(self._grid, (reg.interval, old), -1)
            if rest:
                self._count(self._grid_rest, (reg.interval, old), -1)

    def _count(self, grid: dict[tuple[int, int], int], key: tuple[int, int], delta: int) -> None:
        n = grid.get(key, 0) + delta
        if n > 0:
            grid[key] = n
            if n == delta:  # a new point of the grid
                self._publish_grid()
        else:
            grid.pop(key, None)
            self._publish_grid()

    def _publish_grid(self) -> None:
        self.grid = tuple(self._grid)
        self.grid_rest = tuple(self._grid_rest)

    def wants(self, cycle: int, quiescent: bool) -> bool:
        """Whether a registration needs the snapshot of `cycle` (`quiescent`: the
        machine is at rest, so on-change checks of steady values wait)."""
        if self._first > 0:
            return True
        for interval, phase in self.grid_rest if quiescent else self.grid:
            if (cycle - phase) % interval == 0:
                return True
        return False

    def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
        """The first cycle after `cycle` that `wants` names (None: none)."""
        if self._first > 0:
            return cycle + 1
        best: int | None = None
        for interval, phase in self.grid_rest if quiescent else self.grid:
            c = cycle + interval - (cycle - phase) % interval
            if best is None or c < best:
                best = c
        return best

    def _schedule(self, reg: Registration, cycle: int) -> None:
        """Put `reg` in the bucket of `cycle` — or of the next cycle no pass has begun at
        yet, when `cycle` has been swept already (it is then due at the next pass: late,
        never lost)."""
        if self._swept is not None and cycle <= self._swept:
            cycle = self._swept + 1
        bucket = self._buckets.get(cycle)
        if bucket is None:
            bucket = self._buckets[cycle] = {}
        bucket[reg.handle] = reg
        reg.slot = cycle
        reg.due_at = cycle

    # ------------------------------------------------------------------ sampling

    def begin(self, snapshot: Snapshot, now: float = 0.0) -> SamplingPass:
        """A pass over the registrations due at `snapshot` (their bucket's cycle is at or
        before `snapshot.cycle`; a snapshot not newer than the last pass has nothing due).
        Registrations an unfinished earlier pass has not reached yet move to this one.

        Costs the number of due registrations, plus the number of cycles skipped since
        the last pass or of waiting buckets, whichever is smaller.
        """
        cycle = snapshot.cycle
        due: list[Registration] = []
        previous = self._active
        if previous is not None and not previous.done:
            # An unfinished pass is superseded: what it had not sampled yet is due now.
            due.extend(previous._due[previous._pos :])
            previous._pos = len(previous._due)
        swept = self._swept
        if swept is None or cycle > swept:
            buckets = self._buckets
            if swept is not None and cycle - swept <= len(buckets):
                cycles = range(swept + 1, cycle + 1)
            else:
                cycles = sorted(c for c in buckets if c <= cycle)  # type: ignore[assignment]
            for c in cycles:
                bucket = buckets.pop(c, None)
                if bucket:
                    due.extend(bucket.values())
            for reg in due:
                reg.slot = None
            self._swept = cycle
        self._active = SamplingPass(self, snapshot, now, due)
        return self._active

    def sample(self, snapshot: Snapshot, now: float = 0.0) -> list[Batch]:
        """Samples due at this cycle, grouped into one batch per route (a whole pass)."""
        p = self.begin(snapshot, now)
        p.step()
        return p.take()
