"""Looking for rivals on the network: the I/O of rival detection (docs/design.md §7).

Another Zenoh session that answers queries for this machine's keys (an impostor, or a
second server started with the same machine name) is looked for at start, whenever Zenoh
reports a matching queryable or a liveliness change on `cnc/<m>/alive`, and every
`rival_check_period`. `RivalWatch` declares what tells it so and sends the probes; what
the answers mean, and what is reported, is `rivals.Rivals` (sans-I/O)."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from geo_server.aio import wait_set
from geo_server.transports.zenoh.keys import KeySpace
from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.rivals import Rivals

#: Seconds a rival probe (a get to other sessions) may take; Zenoh ends it then.
PROBE_TIMEOUT_S = 1.0
#: Least seconds between two rival probes, however often Zenoh reports changes.
PROBE_MIN_GAP_S = 0.25


def to_loop(loop: asyncio.AbstractEventLoop | None, fn: Callable[..., object], *args: Any) -> None:
    """Another thread: run `fn(*args)` on `loop` (dropped once the loop is gone). The loop
    may close between the check and the hand-off (server shutting down):
    call_soon_threadsafe then raises RuntimeError, which must not reach the caller's
    thread."""
    if loop is not None and not loop.is_closed():
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(fn, *args)


class RivalWatch:
    """The rival detection of one machine's Zenoh interface: its entities on the
    session, its probes, and `rivals`, what they found. Everything but the probes' gets
    (a worker thread) and Zenoh's callbacks (handed over) runs on the event loop."""

    def __init__(self, keys: KeySpace, options: ZenohOptions, rivals: Rivals) -> None:
        self.keys = keys
        self.options = options
        self.rivals = rivals
        #: held while a probe's get is sent (a worker thread) and by the interface's
        #: `close`: a probe never sends a read on a session being closed
        self.probing = threading.Lock()
        self.probes_started = 0
        self._session: zenoh.Session | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wanted: asyncio.Event | None = None

    async def start(self, session: zenoh.Session, entities: list[Any]) -> None:
        """Look for a rival's liveliness token, then declare ours, and what reports
        changes, into `entities` (undeclared by the interface when it closes)."""
        self._session, self._loop = session, asyncio.get_running_loop()
        self._wanted = asyncio.Event()
        alive = self.keys.alive_key
        # Zenoh merges the liveliness tokens of one key: once ours is declared, a second
        # one on `alive` is invisible as such. So look for one before declaring ours.
        if await self._loop.run_in_executor(None, self._token_held):
            self.rivals.token_held(alive)
        entities.append(session.liveliness().declare_token(alive))
        # Liveliness changes on our key (another token coming or going) call for a look.
        entities.append(session.liveliness().declare_subscriber(alive, self._on_alive))
        # A remote queryable covering all of cnc/<m>/** (as a second server, or an
        # impostor copying one, declares it) turns this querier's matching status on.
        querier = session.declare_querier(
            f"{self.keys.prefix}/**",
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            allowed_destination=zenoh.Locality.REMOTE,
            timeout=PROBE_TIMEOUT_S,
        )
        entities.append(querier)
        entities.append(querier.declare_matching_listener(self._on_matching))

    def stop(self) -> None:
        """No probe is sent after this (the interface closes the session)."""
        self._session = None

    def _token_held(self) -> bool:
        """Worker thread: does another session hold our liveliness token already?"""
        session = self._session
        if session is None:
            return False
        replies = session.liveliness().get(self.keys.alive_key, timeout=PROBE_TIMEOUT_S)
        return any(r.ok is not None for r in replies)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        to_loop(self._loop, self._alive_changed, sample.kind == zenoh.SampleKind.DELETE)

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        to_loop(self._loop, self._matching_changed, bool(status.matching))

    def _alive_changed(self, deleted: bool) -> None:
        if deleted:
            self.rivals.token_gone()
        self._want_probe()

    def _matching_changed(self, matching: bool) -> None:
        self.rivals.queryable(matching)
        self._want_probe()

    def _want_probe(self) -> None:
        if self._wanted is not None:
            self._wanted.set()

    async def run(self) -> None:
        """Look for rivals now, on every hint from Zenoh, and every `rival_check_period`
        (the first period longer by `spread` of it)."""
        assert self._wanted is not None
        loop = asyncio.get_running_loop()
        shift = self.options.spread * self.options.rival_check_period
        while True:
            self._wanted.clear()
            if self._session is not None:
                self.probes_started += 1
                # a worker thread: Zenoh starts a thread for the replies' callbacks, and
                # starting one waits for the interpreter lock (milliseconds in a fleet)
                await loop.run_in_executor(None, self._start_probe, self.probes_started)
            await asyncio.sleep(PROBE_MIN_GAP_S)
            await wait_set(self._wanted, self.options.rival_check_period + shift)
            shift = 0.0

    def _start_probe(self, number: int) -> None:
        """Ask every *other* session's queryables for `cnc/<m>/status` (no waiting);
        `number`: the probe's, counted on the loop.

        The replies name their sender (`Reply.replier_id`); the answer is evaluated
        when Zenoh ends the query (all answered, or `PROBE_TIMEOUT_S`).
        """
        with self.probing:
            session = self._session
            if session is not None:
                self._send_probe(session, number)

    def _send_probe(self, session: zenoh.Session, number: int) -> None:
        """`_start_probe`'s get (under its lock)."""
        found: set[str] = set()

        def on_reply(reply: zenoh.Reply) -> None:
            rid = reply.replier_id
            if rid is not None:
                found.add(str(rid.zid))

        def on_done() -> None:
            to_loop(self._loop, self.rivals.probe_done, number, frozenset(found))

        session.get(
            f"{self.keys.prefix}/status",
            zenoh.handlers.Callback(on_reply, on_done),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            allowed_destination=zenoh.Locality.REMOTE,
            timeout=PROBE_TIMEOUT_S,
        )
