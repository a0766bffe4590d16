"""`NotificationTable` without I/O: when samples are due (docs/design.md §9, cycle time in 100 ns).

The server hands the table the newest snapshot, normally every cycle but fewer when the
event loop falls behind; these tests feed it chosen cycle numbers directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from geo_server.errors import AdsError
from geo_server.transports.ads.codec import AddNotificationRequest, AmsAddr, TransMode
from geo_server.transports.ads.notifications import NotificationTable, cycles_for

CLIENT = AmsAddr("10.1.2.3.1.1", 32905)
SERVER = AmsAddr("127.0.0.1.1.1", 551)
MS = 10_000  # 100 ns ticks per millisecond


@dataclass
class Snap:
    """All the table looks at: the cycle number (the reader below makes the bytes)."""

    cycle: int


def table(values: dict[int, bytes] | None = None) -> NotificationTable:
    # the sampled bytes: the cycle number, or a fixed value per cycle for on-change
    def read(_ig: int, _io: int, _n: int, snap: Snap) -> bytes:
        if values is not None:
            return values.get(snap.cycle, b"\0")
        return snap.cycle.to_bytes(4, "little")

    return NotificationTable(read, cycle_s=0.001)


def register(t: NotificationTable, cycle: int, mode: TransMode, cycle_time_ms: float) -> None:
    req = AddNotificationRequest(0x12F300, 1, 4, mode, 0, round(cycle_time_ms * MS))
    t.add("conn", CLIENT, SERVER, req, Snap(cycle))


def sent(t: NotificationTable, cycles: list[int]) -> list[int]:
    """The cycles among `cycles` (the snapshots the loop saw) at which a sample went out."""
    return [c for c in cycles if t.sample(Snap(c))]


@pytest.mark.parametrize(
    ("ticks", "cycles"),
    [(0, 1), (1, 1), (5_000, 1), (10_000, 1), (20_000, 2), (25_000, 3), (30_000, 3)],
)
def test_cycle_time_in_ticks_to_cycles(ticks: int, cycles: int) -> None:
    # 2.5 ms is 2.4999999999999996 cycles in floating point: half-way rounds up here
    assert cycles_for(ticks, 0.001) == cycles


def test_cyclic_interval_counts_from_the_previous_sample() -> None:
    t = table()
    register(t, 100, TransMode.SERVERCYCLE, 3)
    assert sent(t, list(range(100, 120))) == [101, 104, 107, 110, 113, 116, 119]


def test_interval_of_one_cycle_sends_every_cycle() -> None:
    t = table()
    register(t, 7, TransMode.CLIENTCYCLE, 0)
    assert sent(t, list(range(7, 12))) == [8, 9, 10, 11]


def test_a_cycle_the_loop_skipped_delays_the_sample_never_drops_it() -> None:
    """The loop saw no snapshot of cycles 102…104 (busy): the sample due at 104 goes out
    at 105, the next one 3 cycles after that. A phase rule (`(cycle - base) % 3 == 0`)
    would send nothing at 105 and wait for 106."""
    t = table()
    register(t, 100, TransMode.SERVERCYCLE, 3)
    assert sent(t, [101, 105, 106, 107, 108, 109]) == [101, 105, 108]


def test_on_change_checks_every_interval() -> None:
    """On-change: checked at 201, 203, 205, … (interval 2); sent when the bytes differ."""
    values = {c: (b"B" if c >= 204 else b"A") for c in range(200, 212)}
    t = table(values)
    register(t, 200, TransMode.SERVERONCHA, 2)
    # 201 first sample (A); 203 still A; 205 B (changed at 204, seen at the check)
    assert sent(t, list(range(200, 212))) == [201, 205]


def test_same_snapshot_twice_samples_once() -> None:
    t = table()
    register(t, 10, TransMode.SERVERCYCLE, 1)
    assert sent(t, [11, 11, 12, 12]) == [11, 12]


def test_notifications_per_connection_are_capped_with_0x716() -> None:

    t = NotificationTable(lambda *_a: b"\0\0\0\0", cycle_s=0.001, max_per_owner=3)
    req = AddNotificationRequest(0x12F300, 1, 4, TransMode.SERVERONCHA, 0, MS)
    for _ in range(3):
        t.add("conn", CLIENT, SERVER, req, Snap(1))
    with pytest.raises(AdsError) as e:
        t.add("conn", CLIENT, SERVER, req, Snap(1))
    assert e.value.code == 0x716  # ADSERR_DEVICE_NOMOREHDLS
    t.add("other", CLIENT, SERVER, req, Snap(1))  # the cap is per connection
    assert len(t) == 4
    t.drop_owner("conn")  # a disconnect frees its handles
    assert len(t) == 1
    t.add("conn", CLIENT, SERVER, req, Snap(1))
