"""OPC UA's requests charged to the loop shares of a fleet's machines (docs/design.md
§13.1 *Isolation*, `geo_server.transports.share`).

One OPC UA server answers every machine of a fleet, and a request names its machines
only in its nodes, so what a request costs is known after it ran: the interface marks the
machines whose variables a request read, wrote, monitored or called (`touch`), and the
loop thread's CPU time of the request is split among their shares (`end`). A connection
whose last request drew on a share that is used up waits, its reading paused, until the
share is back (`wait`), as an ADS or Modbus connection of that machine would. Requests
that touch no machine's variable (a Browse, the server's own nodes) draw on no share;
they are bounded per request (`operations.py`).

The machines touched are kept in a context variable: each connection's requests run in
that connection's own task, so two connections' requests never mix their marks.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from contextvars import ContextVar

from geo_server.transports.share import LoopShare

_touched: ContextVar[set[str] | None] = ContextVar("geo_server_opcua_touched", default=None)


class RequestMeter:
    """The shares of a fleet's machines, by machine name, and the requests' charges."""

    def __init__(self, shares: Mapping[str, LoopShare]) -> None:
        self.shares = dict(shares)

    @staticmethod
    def touch(machine: str) -> None:
        """The request being served (in this task) used `machine`'s variables."""
        touched = _touched.get()
        if touched is not None:
            touched.add(machine)

    def wait(self, last: Sequence[LoopShare]) -> float:
        """0.0, or how long (seconds) a connection whose last request drew on `last`
        must wait for those shares to be back."""
        return max((share.wait() for share in last), default=0.0)

    @staticmethod
    def begin() -> float:
        """A request starts (in its connection's task): its marks and CPU time from now."""
        _touched.set(set())
        return time.thread_time()

    def end(self, began: float) -> list[LoopShare]:
        """The request ended: its CPU time charged to the shares of the machines it
        touched (split evenly); those shares."""
        touched = _touched.get() or set()
        _touched.set(None)
        shares = [self.shares[m] for m in sorted(touched) if m in self.shares]
        if shares:
            each = (time.thread_time() - began) / len(shares)
            for share in shares:
                share.charge(each)
        return shares


__all__ = ["RequestMeter"]
