"""The asyncio side of one ADS connection (docs/design.md §9): `AdsConnection` is the
sans-I/O `connection.Connection` plus a transport — reading paused and resumed for
back-pressure, a timer for a frame that never completes, answers that come later run
as tasks (at most `max_pending`). Each event the framer yields goes to the server.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Coroutine, Sequence
from typing import Any, cast

from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsPacket, BadPacket, Command, Dropped, StreamError
from geo_server.transports.ads.connection import Connection
from geo_server.transports.ads.device import Port
from geo_server.transports.share import LoopShare

log = logging.getLogger("geo_server.transports.ads.server")


def log_rarely(count: int, msg: str, *args: object) -> None:
    """A warning for the 1st, 2nd, 4th, 8th… occurrence, debug otherwise: a flood of
    hostile connections must not turn into a flood of log lines."""
    log.log(logging.WARNING if count & (count - 1) == 0 else logging.DEBUG, msg, *args)


class AdsConnection(Connection, asyncio.Protocol):
    """One TCP client: framing in, responses and notifications out.

    A frame that stays unfinished for `incomplete_frame_timeout` seconds after its first
    byte (the framer's `incomplete_since`, on the loop's clock) closes the connection:
    one timer per connection, armed when an unfinished frame begins and cancelled when
    it completes.
    """

    def __init__(self, server: Port) -> None:
        super().__init__(server.options.max_frame)
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.peer: Any = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._admitted = False
        self._frame_timer: asyncio.TimerHandle | None = None
        self._frame_timer_since: float | None = None
        # reading paused: the client does not read its answers / too many outstanding
        self._paused_writing = False
        self._paused_work = False
        #: events read but not served yet: their machine had served its turn
        self._queued: deque[codec.FrameEvent] = deque()
        #: answers of the frames being served, written together (`_handle`); None:
        #: not serving frames, `send` writes at once
        self._corked: list[bytes] | None = None

    # (Equality and hash are object identity, the C defaults: a connection is a key of
    # the notification table and of every sampled route, looked up per sample.)

    # asyncio callbacks

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.peer = transport.get_extra_info("peername")
        self._admitted = self.server.connected(self)
        if not self._admitted:
            refused = self.server.stats.refused_connections
            log_rarely(
                refused,
                "ADS refusing %s: %d connections open (%d refused so far)",
                self.peer,
                self.server.connection_count,
                refused,
            )
            self.framer.close()
            transport.abort()  # nothing was sent to it; free the socket at once

    def connection_lost(self, exc: Exception | None) -> None:
        if self._admitted:
            self.server.disconnected(self)
        for t in list(self._tasks):
            t.cancel()
        self._cancel_frame_timer()
        self.framer.close()  # release an unfinished frame's buffer now
        self.repeats.clear()
        self.transport = None

    def data_received(self, data: bytes) -> None:
        if (
            self.repeats
            and not self._queued
            and self.framer.idle
            and self.server.repeat(self, data)
        ):
            return  # a Read sent before, answered from what was kept (`repeats`)
        loop = self.server.loop
        now = loop.time() if loop is not None else 0.0
        start = time.thread_time() if self.server.shared else None
        events = self.receive(data, now)
        if self._queued:  # (reading is paused; what was read already waits its turn)
            self._queued.extend(events)
        else:
            self._handle(events, start)
        self._arm_frame_timer()

    def _handle(self, events: Sequence[codec.FrameEvent], start: float | None = None) -> None:
        """Serve `events` in order, their answers written in one go (one system call for
        a client that pipelines, not one per answer: the send was a third of a flooded
        machine's cost, docs/benchmarks.md). A request for a machine that has served
        its `requests_per_step` in this loop step waits, with the rest, for the next
        step (reading paused meanwhile): a client pipelining requests to one machine
        takes that machine's turn, not the other machines'. In a fleet, the loop
        thread's CPU time from `start` (before the bytes were framed, else now) until
        the answers are written is charged to the loop shares of the machines served,
        and a request for a machine whose share is used up waits, with the rest, until
        it is back (docs/design.md §13.1)."""
        self._corked = []
        shares: list[LoopShare] = []
        if start is None and self.server.shared:
            start = time.thread_time()
        try:
            self._serve_events(events, shares)
        finally:
            self._uncork()
            if shares and start is not None:
                self._charge(shares, time.thread_time() - start)

    @staticmethod
    def _charge(shares: list[LoopShare], seconds: float) -> None:
        """Split the loop time a batch took among the shares of the requests served
        (one machine's, as a rule)."""
        each = seconds / len(shares)
        first = shares[0]
        if all(s is first for s in shares):
            first.charge(each * len(shares))
            return
        for s in shares:
            s.charge(each)

    def _uncork(self) -> None:
        corked, self._corked = self._corked, None
        if corked:
            self.send(corked[0] if len(corked) == 1 else b"".join(corked))

    def _serve_events(self, events: Sequence[codec.FrameEvent], shares: list[LoopShare]) -> None:
        for i, ev in enumerate(events):
            if isinstance(ev, AmsPacket):
                wait = self.server.take_turn(ev, shares)
                if wait is not None:
                    self._wait_turn(events[i:], wait)
                    return
                self.server.handle_packet(self, ev)
            elif isinstance(ev, codec.RouterCommand):
                self.server.handle_router(self, ev)
            elif isinstance(ev, BadPacket):
                self.server.stats.dropped_frames += 1
                log.debug("ADS bad packet from %s: %s", self.peer, ev.reason)
                if not ev.header.is_response and ev.header.command != Command.DEVICE_NOTIFICATION:
                    self.send(self.refusal(ev.header, ev.error_code))
            elif isinstance(ev, Dropped):
                self.server.stats.dropped_frames += 1
                log.debug("ADS frame dropped from %s: %s", self.peer, ev.reason)
            elif isinstance(ev, StreamError):
                self.server.stats.closed_for_framing += 1
                log.warning("ADS closing %s: %s", self.peer, ev.reason)
                self._cancel_frame_timer()
                self._uncork()  # the answers before the bad frame go out first
                if self.transport is not None:
                    self.transport.close()  # flushes the answers already queued
                return

    def _wait_turn(self, events: Sequence[codec.FrameEvent], wait: float) -> None:
        """`events` wait, reading paused, for the next loop step (`wait` 0) or `wait`
        seconds (`_serve_events`)."""
        self._queued.extend(events)
        if self.transport is not None and not self.transport.is_closing():
            self.transport.pause_reading()
        loop = self.server.loop
        if loop is None:
            return
        if wait > 0.0:
            loop.call_later(wait, self._drain)
        else:
            loop.call_soon(self._drain)

    def _drain(self) -> None:
        """A later loop step: serve the requests that waited for their machine's turn."""
        if self.transport is None:
            self._queued.clear()
            return
        events, self._queued = list(self._queued), deque()
        self._handle(events)
        if not self._queued:
            self._resume_reading()

    def _arm_frame_timer(self) -> None:
        """Keep the timer in step with the unfinished frame (if any) after a feed."""
        since = self.framer.incomplete_since
        timeout = self.server.options.incomplete_frame_timeout
        if since is None or timeout <= 0:
            self._cancel_frame_timer()
            return
        if self._frame_timer is not None and self._frame_timer_since == since:
            return  # the same frame is still arriving: its deadline stands
        self._cancel_frame_timer()
        loop = self.server.loop
        if loop is None:
            return
        self._frame_timer = loop.call_at(since + timeout, self._frame_timed_out)
        self._frame_timer_since = since

    def _cancel_frame_timer(self) -> None:
        if self._frame_timer is not None:
            self._frame_timer.cancel()
        self._frame_timer = None
        self._frame_timer_since = None

    def _frame_timed_out(self) -> None:
        self._frame_timer = None
        if self.transport is None or self.framer.incomplete_since is None:
            return
        self.server.stats.closed_incomplete += 1
        log_rarely(
            self.server.stats.closed_incomplete,
            "ADS closing %s: a frame stayed unfinished for %g s (%d bytes buffered)",
            self.peer,
            self.server.options.incomplete_frame_timeout,
            self.framer.buffered,
        )
        self.framer.close()
        # abort, not close: a client that stalls mid-frame may not read either, and a
        # graceful close would wait for its unread answers.
        self.transport.abort()

    def pause_writing(self) -> None:
        # The client does not read its answers: stop reading its requests meanwhile.
        self._paused_writing = True
        if self.transport is not None:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        self._paused_writing = False
        self._resume_reading()

    def _resume_reading(self) -> None:
        if self._paused_writing or self._paused_work or self._queued:
            return
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

    # used by the server

    @property
    def backlog(self) -> int:
        return self.transport.get_write_buffer_size() if self.transport is not None else 0

    def send(self, frame: bytes) -> None:
        if self._corked is not None:  # serving a batch of frames: written at its end
            self._corked.append(frame)
        elif self.transport is not None and not self.transport.is_closing():
            self.transport.write(frame)

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run an answer that comes later. With `max_pending` of them outstanding the
        connection stops reading requests until half are answered: the work one client
        can queue is bounded, whatever it pipelines."""
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._done)
        if len(self._tasks) >= self.server.options.max_pending and not self._paused_work:
            self._paused_work = True
            if self.transport is not None and not self.transport.is_closing():
                self.transport.pause_reading()

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if self._paused_work and len(self._tasks) <= self.server.options.max_pending // 2:
            self._paused_work = False
            self._resume_reading()

    def abort(self) -> None:
        if self.transport is not None:
            self.transport.abort()

    def close(self) -> None:
        """Close after the answers already queued."""
        self._uncork()
        if self.transport is not None:
            self.transport.close()


class DiscoveryProtocol(asyncio.DatagramProtocol):
    """UDP 48899: one answer per request datagram, to its sender."""

    def __init__(self, server: Port) -> None:
        self.server = server
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # (the selector loop's datagram transport is not an asyncio.DatagramTransport
        # subclass on every Python: no isinstance check)
        self.transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: Any) -> None:
        reply = self.server.answer_datagram(data)
        if reply is not None and self.transport is not None:
            self.transport.sendto(reply, addr)
