"""A machine's share of the event loop in a fleet (docs/design.md §13.1 *Isolation*).

One event loop answers every machine of a fleet. The loop time a machine's clients take
— the loop thread's CPU time for an ADS or Modbus request, from its framing until its
answer is written, the catch-up of the machine's cycles it causes included — is charged
to the machine's `LoopShare`: a bucket of loop time that fills at `rate` seconds per
second, up to `burst` seconds. While a machine's bucket is empty its requests wait (the
connection's reading paused, or the answering task asleep) until it has filled again,
so a client that floods one machine is answered at that machine's pace and otherwise
sits idle: the loop stays free to answer the other machines at once, and the CPU the
flood no longer takes is theirs too. The machine's requests are answered in order, only
later; nothing is refused or lost.

CPU time, not wall time: wall time includes the waits for the interpreter lock that the
engine threads cause, and would charge them to whichever machine is being served. On a
busy host a request costs more CPU time (a Modbus read of a machine at rest: 0.25 ms on
a quiet 2-core VM, 0.75 ms at a load average of 15), so its clients are held back
sooner there.

A single machine has no share (None): nobody else is on its loop to protect.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

#: A machine's status entry of its share (`LoopShare.status`), written by the interfaces
#: that charge it (ADS, Modbus) and read by the fleet's status
STATUS_KEY = "loop_share"
#: The loop time (seconds per second) one machine's requests may take in a fleet of ten
#: machines or more (`fleet_rate`): a tenth, ten times a machine's even share in a fleet
#: of 100, several hundred ADS Reads a second. A flood on one machine of a fleet of 100
#: (bench/fleet_isolation.py) raised the other machines' p99 by 1.4-1.7x at a tenth, by
#: 2x at 0.15 and 0.25 (docs/benchmarks.md, *Fleet isolation with a share of the loop per
#: machine*; docs/design.md §13.1).
FLEET_RATE = 0.1
#: The most loop time a machine that was quiet may take at once (seconds): a burst of
#: requests (an HMI's screenful of sum reads) is not held back.
FLEET_BURST = 0.002


def fleet_rate(machines: int) -> float:
    """A machine's share of the loop in a fleet of `machines`: its even share, and at
    least `FLEET_RATE` (a small fleet has few other machines, and engines, to delay)."""
    return max(FLEET_RATE, 1.0 / max(1, machines))


class LoopShare:
    """One machine's bucket of event-loop time (see the module's docstring).

    `status` is the dict a machine's status shows as `loop_share` (`ObjectService.
    status_extra`): `rate`, `loop_s` (loop time its requests were charged: what they
    took, OPC UA's at most a burst each), `holds` (how often its requests had to wait
    for their share) and `held_s` (for how long, together).
    """

    __slots__ = ("_at", "_credit", "burst", "clock", "rate", "status")

    def __init__(
        self,
        rate: float = FLEET_RATE,
        burst: float = FLEET_BURST,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 0.0 < rate <= 1.0 or burst <= 0.0:
            raise ValueError(f"a loop share needs 0 < rate <= 1 and burst > 0, not {rate}, {burst}")
        self.rate, self.burst, self.clock = rate, burst, clock
        self._credit = burst
        self._at = clock()
        self.status: dict[str, Any] = {"rate": rate, "loop_s": 0.0, "holds": 0, "held_s": 0.0}

    def charge(self, seconds: float) -> None:
        """The machine's requests took `seconds` of the loop."""
        self._credit -= seconds
        self.status["loop_s"] += seconds

    def wait(self, *, count: bool = True) -> float:
        """0.0: the machine may be served now; else how long (seconds) its requests must
        wait for its share to be back (each such answer counts a hold, unless `count` is
        False: the caller counts its holds itself, `hold`)."""
        now = self.clock()
        credit = min(self.burst, self._credit + (now - self._at) * self.rate)
        self._credit, self._at = credit, now
        if credit > 0.0:
            return 0.0
        seconds = -credit / self.rate + 1e-4  # (just past: the next look finds it back)
        if count:
            self.hold(seconds)
        return seconds

    def hold(self, seconds: float = 0.0) -> None:
        """A request waits for the share (`seconds`: for how long, when known; a caller
        that learns it later adds it with `held`)."""
        st = self.status
        st["holds"] += 1
        st["held_s"] += seconds

    def held(self, seconds: float) -> None:
        """A request counted by `hold` waited `seconds` in all."""
        self.status["held_s"] += seconds

    @property
    def holds(self) -> int:
        """How often the machine's requests had to wait for their share."""
        return int(self.status["holds"])


__all__ = ["FLEET_BURST", "FLEET_RATE", "LoopShare", "fleet_rate"]
