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
share lets it in (`gates`), as an ADS or Modbus connection of that machine would. Requests
that touch no machine's variable (a Browse, the server's own nodes) draw on no share;
they are bounded per request (`operations.py`).

While a share is used up — OPC UA's own or a machine's — whose request runs when it is
back is decided fairly (`FairShare`, start-time fair queuing over connections): each
connection's requests are tagged with the processor time its earlier ones took of that
share, and the request with the smallest tag runs next, one at a time. A connection that
asks seldom (a SCADA client's read, asyncua's keep-alive probe) is served as soon as the
share is back, ahead of a flood's queued requests. Before, every held connection slept on
its own until the share was back, and all woke together: a request waited for everyone's,
and a legitimate client beside a flood of four connections waited up to 2.4 s for one
Read (OPC UA's share), or, reading the flooded machine of a fleet of 30, 6 s (its
machine's); asyncua's client gives a connection up when its keep-alive probe waits a
second.

The machines touched are kept in a context variable: each connection's requests run in
that connection's own task, so two connections' requests never mix their marks.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from contextvars import ContextVar
from dataclasses import dataclass, field

from geo_server.transports.share import LoopShare

_touched: ContextVar[set[str] | None] = ContextVar("geo_server_opcua_touched", default=None)


@dataclass(eq=False)
class Ticket:
    """One request let in by a `FairShare`: its connection, its start tag (the
    connection's processor time of that share, in the queue's virtual time), the share
    and, when it was queued, what tells the queue it began (`RequestMeter.begin`) and
    ended (`RequestMeter.end`)."""

    key: object
    start: float
    gate: FairShare | None = None
    began: asyncio.Future[None] | None = None
    ended: asyncio.Future[None] | None = None


@dataclass(order=True)
class _Waiting:
    start: float
    seq: int
    admitted: asyncio.Future[Ticket] = field(compare=False)
    key: object = field(compare=False)
    since: float = field(compare=False)


class FairShare:
    """A `LoopShare` whose held requests go in start-time fair order (the module's
    docstring): while the share is used up, connections queue with their start tags (the
    processor time their earlier requests took of it, in the queue's virtual time), and
    the one with the smallest goes next, one at a time, once the share has time again."""

    def __init__(self, share: LoopShare) -> None:
        self.share = share
        #: the requests held for the share, smallest start tag first (`admit`)
        self._queue: list[_Waiting] = []
        self._seq = itertools.count()
        #: each connection's finish tag: its last request's start tag and processor time
        #: (weak: a connection's tag goes with it, also one written by a request that
        #: ended after its connection was lost)
        self._tags: weakref.WeakKeyDictionary[object, float] = weakref.WeakKeyDictionary()
        #: the virtual time: the start tag of the request let in last
        self._now = 0.0
        self._dispatcher: asyncio.Task[None] | None = None
        self._wait = 0.0  # what `admit_now` found last (the dispatcher's first sleep)

    def admit_now(self, key: object) -> Ticket | None:
        """Connection `key` (weakly referenced) may run its next request at once (the
        share has time and nobody waits), or None: then `admit`."""
        if self._queue or self._dispatcher is not None:
            return None
        self._wait = self.share.wait(count=False)
        if self._wait > 0.0:
            return None
        start = self._now = max(self._now, self._tags.get(key, 0.0))
        return Ticket(key, start, self)

    async def admit(self, key: object) -> Ticket:
        """Wait until connection `key`'s next request may run, in the fair order;
        counted as a hold of the share, with the time it waited."""
        start = max(self._now, self._tags.get(key, 0.0))
        admitted: asyncio.Future[Ticket] = asyncio.get_running_loop().create_future()
        since = self.share.clock()
        heapq.heappush(self._queue, _Waiting(start, next(self._seq), admitted, key, since))
        self.share.hold()
        if self._dispatcher is None:  # (after an `admit_now` that found the share used up:
            wait, self._wait = self._wait, 0.0  # its wait; else the dispatcher looks now)
            self._dispatcher = asyncio.ensure_future(self._dispatch(wait))
        try:
            return await admitted
        except asyncio.CancelledError:  # (let in as its connection went: the next may go)
            if admitted.done() and not admitted.cancelled():
                _ended(admitted.result())
            raise

    async def _dispatch(self, wait: float) -> None:
        """Let the held requests in, smallest start tag first, each once the share has
        time again and the one before it has ended — or has run for a burst's time: a
        request that waits for the main loop (a Call, a Write) does not hold the others.
        Its burst counts from when it began: a machine's ticket may wait at OPC UA's
        share first, and letting the next in meanwhile let the whole queue through
        before any of them was charged."""
        try:
            while self._queue:
                if wait > 0.0:
                    await asyncio.sleep(wait)
                wait = self.share.wait(count=False)  # (each request counted once: `admit`)
                if wait > 0.0:
                    continue
                waiting = heapq.heappop(self._queue)
                if waiting.admitted.done():  # (its connection went while it waited)
                    continue
                loop = asyncio.get_running_loop()
                began: asyncio.Future[None] = loop.create_future()
                ended: asyncio.Future[None] = loop.create_future()
                self._now = max(self._now, waiting.start)
                self.share.held(self.share.clock() - waiting.since)
                ticket = Ticket(waiting.key, waiting.start, self, began, ended)
                waiting.admitted.set_result(ticket)
                await asyncio.wait((began, ended), return_when=asyncio.FIRST_COMPLETED)
                await asyncio.wait((ended,), timeout=self.share.burst)
        finally:
            self._dispatcher = None

    def paid(self, key: object, took: float, start: float | None = None) -> None:
        """Connection `key`'s request took `took` seconds of the share's processor time
        (`start`: its ticket's start tag; None: it was not let in here)."""
        if start is None:
            start = max(self._now, self._tags.get(key, 0.0))
        self._tags[key] = start + took

    @property
    def waiting(self) -> int:
        """Requests held now, one at most per connection."""
        return sum(1 for w in self._queue if not w.admitted.done())

    def close(self) -> None:
        """The server stops: nobody is let in any more."""
        for waiting in self._queue:
            waiting.admitted.cancel()
        self._queue.clear()
        if self._dispatcher is not None:
            self._dispatcher.cancel()
            self._dispatcher = None  # (one cancelled before its first step never ends)


class RequestMeter:
    """OPC UA's share of the loop (`overall`: every request draws on it), the shares of
    a fleet's machines by name (`machines`: a request draws on those it touched), the
    requests' charges, and the fair order of the requests held for any of them."""

    def __init__(self, overall: LoopShare, machines: Mapping[str, LoopShare]) -> None:
        #: OPC UA's share, with its fair order
        self.fair = FairShare(overall)
        #: a fleet's machines' shares, each with its own fair order
        self.machines = {m: FairShare(share) for m, share in machines.items()}
        self._turn_taken = False

    @property
    def overall(self) -> LoopShare:
        """OPC UA's share (every request draws on it)."""
        return self.fair.share

    def gates(self, machines: Sequence[str]) -> list[FairShare]:
        """What a connection whose last request touched `machines` waits for before its
        next: those machines' shares (a fleet's), then OPC UA's own."""
        return [self.machines[m] for m in machines if m in self.machines] + [self.fair]

    async def let_in(
        self, key: object, machines: Sequence[str], on_hold: Callable[[], None]
    ) -> list[Ticket]:
        """The tickets of connection `key`'s next request, its last one having touched
        `machines`: each of `gates` lets it in at once, or in fair order while its share
        is used up (`on_hold` is called before each such wait). OPC UA's ticket last."""
        tickets: list[Ticket] = []
        try:
            for gate in self.gates(machines):
                ticket = gate.admit_now(key)
                if ticket is None:
                    on_hold()
                    ticket = await gate.admit(key)
                tickets.append(ticket)
        except BaseException:  # (its connection went while it waited: the next may go)
            self.release(tickets)
            raise
        return tickets

    @property
    def waiting(self) -> int:
        """Requests held now for OPC UA's share or a machine's, one at most per
        connection in each."""
        return self.fair.waiting + sum(g.waiting for g in self.machines.values())

    def close(self) -> None:
        """The server stops: nobody is let in any more."""
        self.fair.close()
        for gate in self.machines.values():
            gate.close()

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

    @staticmethod
    def begin(tickets: Sequence[Ticket] = ()) -> float:
        """The request of `tickets` starts (in its connection's task): its marks and CPU
        time from now; the queues that let it in count its burst from now."""
        for ticket in tickets:
            if ticket.began is not None and not ticket.began.done():
                ticket.began.set_result(None)
        _touched.set(set())
        return time.thread_time()

    @staticmethod
    def release(tickets: Sequence[Ticket]) -> None:
        """Tickets let in for a request that will not run: the next held may go."""
        for ticket in tickets:
            _ended(ticket)

    def end(self, tickets: Sequence[Ticket], began: float | None) -> list[str]:
        """The request let in with `tickets` (`let_in`'s, OPC UA's last) ended (`began`:
        None when it never started): its CPU time charged to OPC UA's share and its
        connection's tag there, and, split evenly, to the shares and tags of the
        machines it touched. The next held requests may go. Returns those machines:
        what the connection's next request waits for (`gates`)."""
        took = 0.0 if began is None else time.thread_time() - began
        touched = _touched.get() or set()
        _touched.set(None)
        # at most a burst to OPC UA's share, and to a machine's what makes it wait as
        # long after one request: a fraction of a second at the default share (asyncua's
        # client gives a connection up when its keep-alive Read waits 1 s)
        overall = self.overall
        overall.charge(min(took, overall.burst))
        starts = {t.gate: t.start for t in tickets}
        key = tickets[-1].key
        self.fair.paid(key, took, starts.get(self.fair))
        self.release(tickets)
        machines = [m for m in sorted(touched) if m in self.machines]
        for m in machines:
            gate, part = self.machines[m], took / len(machines)
            # (at most what waits as long after it as OPC UA's burst does on its share)
            gate.share.charge(min(part, gate.share.rate * overall.burst / overall.rate))
            gate.paid(key, part, starts.get(gate))
        return machines


def _ended(ticket: Ticket) -> None:
    if ticket.ended is not None and not ticket.ended.done():
        ticket.ended.set_result(None)


__all__ = ["FairShare", "RequestMeter", "Ticket"]
