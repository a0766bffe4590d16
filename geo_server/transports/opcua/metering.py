"""OPC UA's requests charged to loop shares (docs/design.md §9.1 and §13.1 *Isolation*,
`geo_server.transports.share`).

All OPC UA work draws on one share (`OpcUaOptions.loop_share`) of the processor time of
its thread (`opcua`, a loop of its own: docs/design.md §9.1): asyncua's work is pure
Python, and a client flooding OPC UA would otherwise take the cores and the interpreter
lock from ADS, Modbus, the web HMI and the cycle. A connection waits, its reading paused,
while that share is used up.

In a fleet, one OPC UA server answers every machine of a fleet, and a request names its machines
only in its nodes, so what a request costs is known after it ran: the interface marks the
machines whose variables a request read, wrote, monitored or called (`touch`), and the
thread's CPU time of the request is split among their shares (`end`: each machine's share
of OPC UA's thread, at its fleet share's rate). A connection
whose last request drew on a share that is used up waits, its reading paused, until the
share is back (`wait`), as an ADS or Modbus connection of that machine would. Requests
that touch no machine's variable (a Browse, the server's own nodes) draw on no share;
they are bounded per request (`operations.py`).

The machines touched are kept in a context variable: each connection's requests run in
that connection's own task, so two connections' requests never mix their marks.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Mapping, Sequence
from contextvars import ContextVar

from geo_server.transports.share import LoopShare

_touched: ContextVar[set[str] | None] = ContextVar("geo_server_opcua_touched", default=None)


class RequestMeter:
    """OPC UA's share of the loop (`overall`: every request draws on it), the shares of
    a fleet's machines by name (`machines`: a request draws on those it touched), and
    the requests' charges."""

    def __init__(self, overall: LoopShare, machines: Mapping[str, LoopShare]) -> None:
        self.overall = overall
        self.machines = dict(machines)
        self._turn_taken = False

    async def take_turn(self) -> None:
        """Wait for this turn of the event loop to have no OPC UA request yet, and take
        it: one request starts per turn. Several connections with a request ready
        would otherwise all run in one turn, before the loop looks at its sockets
        again, and an ADS or Modbus request would wait for all of them."""
        while self._turn_taken:
            await asyncio.sleep(0)
        self._turn_taken = True
        asyncio.get_running_loop().call_soon(self._next_turn)

    def _next_turn(self) -> None:
        self._turn_taken = False

    @staticmethod
    def touch(machine: str) -> None:
        """The request being served (in this task) used `machine`'s variables."""
        touched = _touched.get()
        if touched is not None:
            touched.add(machine)

    def wait(self, last: Sequence[LoopShare]) -> float:
        """0.0, or how long (seconds) a connection whose last request drew on the
        machines' shares `last` must wait for OPC UA's share and those to be back."""
        return max((share.wait() for share in (self.overall, *last)), default=0.0)

    @staticmethod
    def begin() -> float:
        """A request starts (in its connection's task): its marks and CPU time from now."""
        _touched.set(set())
        return time.thread_time()

    def end(self, began: float) -> list[LoopShare]:
        """The request ended: its CPU time charged to OPC UA's share and, split evenly,
        to the shares of the machines it touched; those machines' shares."""
        took = time.thread_time() - began
        touched = _touched.get() or set()
        _touched.set(None)
        # at most a burst: the wait after one request stays a fraction of a second
        # (asyncua's client gives a connection up when its keep-alive Read waits 1 s)
        self.overall.charge(min(took, self.overall.burst))
        shares = [self.machines[m] for m in sorted(touched) if m in self.machines]
        for share in shares:
            share.charge(took / len(shares))
        return shares


__all__ = ["RequestMeter"]
