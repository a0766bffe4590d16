"""`NotificationTable` at scale, without I/O: caps, per-owner costs, due buckets, sliced
passes.

Costs are asserted as counts of work done (registrations a pass looks at, owner
comparisons, waiting buckets), never as times.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from geo_server.errors import AdsError
from geo_server.transports.ads.codec import AddNotificationRequest, AmsAddr, TransMode
from geo_server.transports.ads.notifications import MAX_PER_OWNER, MAX_TOTAL, NotificationTable
from geo_server.transports.ads.server import AdsOptions

CLIENT = AmsAddr("10.1.2.3.1.1", 32905)
SERVER = AmsAddr("127.0.0.1.1.1", 551)
MS = 10_000  # 100 ns ticks per millisecond


@dataclass
class Snap:
    cycle: int


class Owner:
    """A connection stand-in that counts how often it is compared with another."""

    comparisons = 0

    def __init__(self, name: str) -> None:
        self.name = name

    def __eq__(self, other: object) -> bool:
        Owner.comparisons += 1
        return self is other

    def __hash__(self) -> int:
        return id(self)


def reader(calls: list | None = None):
    """Bytes of (IG, IO) at a cycle: the cycle number and the offset, 8 bytes."""

    def read(_ig: int, io: int, _n: int, snap: Snap) -> bytes:
        if calls is not None:
            calls.append((io, snap.cycle))
        return snap.cycle.to_bytes(4, "little") + io.to_bytes(4, "little")

    return read


def req(
    io: int = 1, mode: TransMode = TransMode.SERVERCYCLE, cycle_ms: float = 1
) -> AddNotificationRequest:
    return AddNotificationRequest(0x12F300, io, 8, mode, 0, round(cycle_ms * MS))


def test_default_caps_are_the_documented_ones() -> None:
    opts = AdsOptions()
    assert opts.max_notifications_total == MAX_TOTAL == 550  # Beckhoff's figure per device
    assert opts.max_notifications == MAX_PER_OWNER == MAX_TOTAL // 2


def test_total_cap_is_0x716_across_connections() -> None:
    t = NotificationTable(reader(), 0.001, max_per_owner=3, max_total=5)
    a, b, c = Owner("a"), Owner("b"), Owner("c")
    handles = [t.add(a, CLIENT, SERVER, req(), Snap(1)).handle for _ in range(3)]
    t.add(b, CLIENT, SERVER, req(), Snap(1))
    t.add(b, CLIENT, SERVER, req(), Snap(1))
    for owner in (b, c):  # b is under its own cap, c has none yet: the total is full
        with pytest.raises(AdsError) as e:
            t.add(owner, CLIENT, SERVER, req(), Snap(1))
        assert e.value.code == 0x716  # ADSERR_DEVICE_NOMOREHDLS
    t.delete(a, handles[0])
    t.add(c, CLIENT, SERVER, req(), Snap(1))  # a freed handle is available to anyone
    assert len(t) == 5
    assert t.drop_owner(a) == 2
    assert len(t) == 3


def test_registering_deleting_and_dropping_never_scan_other_owners() -> None:
    """3 × 150 registrations, deletions and a disconnect: no operation compares the
    owner with the owners of other registrations (a scan of the table would do so
    for every registration: ~10^5 comparisons here)."""
    owners = [Owner(str(i)) for i in range(3)]
    t = NotificationTable(reader(), 0.001, max_per_owner=150)
    Owner.comparisons = 0
    regs = [t.add(o, CLIENT, SERVER, req(i), Snap(1)) for i in range(150) for o in owners]
    assert t.count_of(owners[0]) == 150
    for r in regs[:90]:
        t.delete(r.owner, r.handle)  # one comparison each: is it the caller's handle?
    assert t.drop_owner(owners[1]) == 150 - 30
    assert Owner.comparisons <= 90
    assert len(t) == 450 - 90 - 120
    assert t.count_of(owners[1]) == 0


def test_a_pass_looks_only_at_the_registrations_due() -> None:
    """1000 registrations every 100 cycles and 5 every cycle: between the slow ones'
    samples a pass looks at the 5 only, and reads only their addresses."""
    calls: list = []
    t = NotificationTable(reader(calls), 0.001, max_per_owner=2000, max_total=2000)
    slow = [
        t.add("slow", CLIENT, SERVER, req(1000 + i, cycle_ms=100), Snap(10)) for i in range(1000)
    ]
    fast = [t.add("fast", CLIENT, SERVER, req(i), Snap(10)) for i in range(5)]
    first = t.begin(Snap(11))
    assert first.remaining == 1005  # every first sample is due at the next cycle
    first.step()
    calls.clear()
    for cycle in range(12, 111):
        p = t.begin(Snap(cycle))
        assert p.remaining == 5, cycle
        p.step()
    assert {io for io, _c in calls} == {r.index_offset for r in fast}
    p = t.begin(Snap(111))  # 100 cycles after the first samples
    assert p.remaining == 1005
    p.step()
    batches = p.take()
    assert sorted(s.handle for b in batches for s in b.samples) == sorted(
        r.handle for r in slow + fast
    )


def test_on_change_compares_only_when_due() -> None:
    calls: list = []
    t = NotificationTable(reader(calls), 0.001)
    t.add("c", CLIENT, SERVER, req(7, TransMode.SERVERONCHA, cycle_ms=10), Snap(0))
    sent = [c for c in range(1, 40) if t.sample(Snap(c))]
    assert [c for _io, c in calls[1:]] == [1, 11, 21, 31]  # (the first read: at add)
    assert sent == [1, 11, 21, 31]  # the reader's bytes change every cycle


def test_a_sliced_pass_keeps_its_snapshot_and_skips_deleted_handles() -> None:
    """A pass worked through in steps samples the snapshot it began with, however late
    the steps run; a handle deleted before its turn is skipped, one added meanwhile
    waits for the next pass."""
    t = NotificationTable(reader(), 0.001)
    regs = [t.add("c", CLIENT, SERVER, req(i), Snap(100)) for i in range(10)]
    p = t.begin(Snap(101))
    assert p.step(3) == 3
    t.delete("c", regs[5].handle)
    late = t.add("c", CLIENT, SERVER, req(99), Snap(105))  # the service is at 105 by now
    while not p.done:
        p.step(2)
    samples = [s for b in p.take() for s in b.samples]
    assert [s.handle for s in samples] == [r.handle for r in regs if r is not regs[5]]
    assert {s.data[:4] for s in samples} == {(101).to_bytes(4, "little")}
    nxt = t.begin(Snap(106))  # the regular ones: 1 cycle after 101; the late one: first
    nxt.step()
    assert sorted(s.handle for b in nxt.take() for s in b.samples) == sorted(
        [r.handle for r in regs if r is not regs[5]] + [late.handle]
    )


def test_a_huge_jump_samples_each_due_registration_once() -> None:
    """The loop saw no snapshot for a billion cycles (a stepped test, a stalled loop):
    the pass costs the waiting buckets, not the cycles skipped, and samples are late,
    never lost; intervals count from there."""
    t = NotificationTable(reader(), 0.001)
    t.add("c", CLIENT, SERVER, req(1, cycle_ms=3), Snap(100))
    t.add("c", CLIENT, SERVER, req(2, cycle_ms=7), Snap(100))
    assert len(t.sample(Snap(101))[0].samples) == 2
    far = 10**9
    assert len(t.sample(Snap(far))[0].samples) == 2
    got = {c: len(b[0].samples) for c in range(far + 1, far + 8) if (b := t.sample(Snap(c)))}
    assert got == {far + 3: 1, far + 6: 1, far + 7: 1}


def test_held_first_sample_waits_for_its_time() -> None:
    t = NotificationTable(reader(), 0.001)
    t.add("c", CLIENT, SERVER, req(), Snap(10), hold_until=5.0)
    assert t.sample(Snap(11), now=4.0) == []
    assert t.sample(Snap(12), now=4.9) == []
    assert len(t.sample(Snap(13), now=5.0)[0].samples) == 1


def test_churn_leaves_no_waiting_buckets_behind() -> None:
    """Registering and deleting over and over (long cycle times, so nothing falls due)
    leaves nothing behind: the table's memory follows its registrations."""
    t = NotificationTable(reader(), 0.001, max_per_owner=500, max_total=500)
    owner = Owner("churn")
    for i in range(5000):
        r = t.add(owner, CLIENT, SERVER, req(i, cycle_ms=1000 + i), Snap(i))
        t.delete(owner, r.handle)
    assert len(t) == 0 and t.waiting == 0 and t.count_of(owner) == 0
    for i in range(500):
        t.add(owner, CLIENT, SERVER, req(i, cycle_ms=1000 + i), Snap(5000))
    assert t.waiting == 1  # every first sample is due at the next cycle
    t.sample(Snap(5001))
    assert t.waiting == 500  # then each one a different cycle time later
    t.drop_owner(owner)
    assert len(t) == 0 and t.waiting == 0


def test_an_abandoned_pass_loses_nothing() -> None:
    """A pass begun while another is unfinished takes over what that one had not reached
    (sampled at the newer snapshot: late, never lost)."""
    t = NotificationTable(reader(), 0.001)
    regs = [t.add("c", CLIENT, SERVER, req(i), Snap(100)) for i in range(10)]
    first = t.begin(Snap(101))
    first.step(4)
    second = t.begin(Snap(103))
    # the 6 the first pass never reached, and the 4 it sampled (due again at 102)
    assert first.done and second.remaining == 10
    second.step()
    early = [s.handle for b in first.take() for s in b.samples]
    late = [s for b in second.take() for s in b.samples]
    assert early == [r.handle for r in regs[:4]]
    assert sorted(s.handle for s in late) == sorted(r.handle for r in regs)
    assert {s.data[:4] for s in late} == {(103).to_bytes(4, "little")}
    nxt = t.begin(Snap(104))  # and everyone is due again one interval on
    assert nxt.remaining == 10
