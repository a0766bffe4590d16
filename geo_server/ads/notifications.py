"""ADS device notifications: registrations and per-cycle sampling, without I/O.

A client registers with AddDeviceNotification (IG, IO, length, transmission mode, max
delay and cycle time in 100 ns ticks — AdsLib `AdsNotificationAttrib`); the server then
sends DeviceNotification frames (command 8, no response) carrying stamps of samples
(Beckhoff "ADS Device Notification"). Here:

- samples are taken at **GEO cycle boundaries** from the published snapshot (SPEC §5
  step 5), so every value a client sees is one the service reports at that cycle;
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
  what `sample` already groups);
- every sample is exactly the registered length (zero-padded when the object is
  shorter): AdsLib drops the whole stamp when a sample size differs from the registered
  one (`AmsConnection.cpp ReceiveNotification`).

`NotificationTable` is driven by the server: `add`/`delete`/`drop_owner` from requests
and disconnects, `sample(snapshot)` on the event loop with the newest snapshot (normally
once per cycle; fewer when the loop falls behind, see `AdsServer._on_cycle_thread`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field

from geo_server.ads.codec import AddNotificationRequest, AmsAddr, ReturnCode, Sample, TransMode
from geo_server.dictionary import AdsError
from geo_server.machine.snapshot import Snapshot

#: Modes served; the client-side ones are served like their server-side twins.
CYCLIC_MODES = frozenset({TransMode.CLIENTCYCLE, TransMode.SERVERCYCLE, TransMode.SERVERCYCLE2})
ON_CHANGE_MODES = frozenset({TransMode.CLIENTONCHA, TransMode.SERVERONCHA, TransMode.SERVERONCHA2})
#: Beckhoff recommends at most 550 notifications per device; refuse beyond this per client.
MAX_PER_OWNER = 1024
#: Largest registered length (0x717 INVALIDWATCHSIZE beyond).
MAX_WATCH_SIZE = 64 * 1024

Reader = Callable[[int, int, int, Snapshot], bytes]


@dataclass
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

    @property
    def on_change(self) -> bool:
        return self.trans_mode in ON_CHANGE_MODES


@dataclass
class Batch:
    """Samples of one cycle for one (connection, client, server) route: one frame."""

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


class NotificationTable:
    """All registrations of one server, keyed by handle (unique per server)."""

    def __init__(self, read: Reader, cycle_s: float, max_per_owner: int = MAX_PER_OWNER) -> None:
        self._read = read
        self.cycle_s = cycle_s
        self.max_per_owner = max_per_owner
        self._regs: dict[int, Registration] = {}
        self._handles = itertools.count(1)

    def __len__(self) -> int:
        return len(self._regs)

    def __contains__(self, handle: object) -> bool:
        return handle in self._regs

    def get(self, handle: int) -> Registration | None:
        return self._regs.get(handle)

    def owned_by(self, owner: Hashable) -> list[Registration]:
        return [r for r in self._regs.values() if r.owner == owner]

    def _value(self, ig: int, io: int, length: int, snap: Snapshot) -> bytes:
        return self._read(ig, io, length, snap).ljust(length, b"\0")

    def add(
        self,
        owner: Hashable,
        client: AmsAddr,
        server: AmsAddr,
        req: AddNotificationRequest,
        snapshot: Snapshot,
        hold_until: float = 0.0,
    ) -> Registration:
        """Register (the address is checked by reading it from `snapshot`).

        AdsError: 0x713 unsupported mode, 0x705 zero length, 0x717 too long, 0x716 too
        many handles, and whatever reading the address raises (0x702/0x703/0x705).
        """
        if req.trans_mode not in CYCLIC_MODES and req.trans_mode not in ON_CHANGE_MODES:
            raise AdsError(
                ReturnCode.DEVICE_TRANSMODENOTSUPP,
                f"transmission mode {req.trans_mode} is not supported (cyclic 1/3/5, "
                "on-change 2/4/6)",
            )
        if req.length == 0:
            raise AdsError(ReturnCode.DEVICE_INVALIDSIZE, "notification length 0")
        if req.length > MAX_WATCH_SIZE:
            raise AdsError(
                ReturnCode.DEVICE_INVALIDWATCHSIZE,
                f"notification length {req.length} > {MAX_WATCH_SIZE}",
            )
        if sum(1 for r in self._regs.values() if r.owner == owner) >= self.max_per_owner:
            raise AdsError(
                ReturnCode.DEVICE_NOMOREHDLS,
                f"more than {self.max_per_owner} notifications on one connection",
            )
        self._value(req.index_group, req.index_offset, req.length, snapshot)
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
        )
        self._regs[reg.handle] = reg
        return reg

    def delete(self, owner: Hashable, handle: int) -> None:
        """0x714 NOTIFYHNDINVALID when the handle is unknown or another connection's."""
        reg = self._regs.get(handle)
        if reg is None or reg.owner != owner:
            raise AdsError(
                ReturnCode.DEVICE_NOTIFYHNDINVALID, f"notification handle {handle} is unknown"
            )
        del self._regs[handle]

    def drop_owner(self, owner: Hashable) -> int:
        """Forget every registration of a connection (it disconnected)."""
        gone = [h for h, r in self._regs.items() if r.owner == owner]
        for h in gone:
            del self._regs[h]
        return len(gone)

    def sample(self, snapshot: Snapshot, now: float = 0.0) -> list[Batch]:
        """Samples due at this cycle, grouped into one batch per route."""
        batches: dict[tuple[Hashable, AmsAddr, AmsAddr], Batch] = {}
        cycle = snapshot.cycle
        for reg in list(self._regs.values()):
            # The first sample is due at the first cycle after the registration, every
            # later one (or on-change check) a whole interval after the previous one.
            # `>=` rather than `==` or a phase modulo: the loop may hand us a later
            # snapshot than the due cycle, and a sample is then late, never lost.
            wait = reg.interval if reg.last is not None else 1
            if cycle - reg.last_cycle < wait or now < reg.hold_until:
                continue
            reg.last_cycle = cycle
            try:
                data = self._value(reg.index_group, reg.index_offset, reg.length, snapshot)
            except AdsError:
                continue  # the object vanished (cannot happen today: reload keeps axes)
            if reg.on_change and data == reg.last:
                continue
            reg.last = data
            key = (reg.owner, reg.client, reg.server)
            batch = batches.get(key)
            if batch is None:
                batch = batches[key] = Batch(reg.owner, reg.client, reg.server)
            batch.samples.append(Sample(reg.handle, data))
        return list(batches.values())
