"""The Zenoh interface (docs/design.md §7): a thin shell over the object service.

Zenoh calls our queryable callback on one of its own threads. The callback only hands
the query to the asyncio loop (`call_soon_threadsafe`); everything else — reading the
snapshot, validating a write, waiting for it to be applied — happens on the loop, so
Zenoh's dispatch is never blocked and the GEO cycle never waits on Zenoh. Reload/save
(by `cmd/…` key or by writing `SIM::reload`/`SIM::save`) run in a worker thread, so the
loop, which ADS and Modbus may share, is not blocked while list files are read or written;
NC text is parsed in a worker thread too.

Limits: the Zenoh transport itself is bounded (`ZenohOptions`: handshake time, pending
handshakes, sessions, links), so idle connections cannot lock new sessions out for long;
payloads, NC text and JSON numbers are bounded before they are parsed.

Beside it: what a get that reads is answered with (`reads.py`, a plain read on Zenoh's
thread), and the look for rivals, other sessions claiming this machine (`watch.py`, over
the sans-I/O `rivals.py`); one found is listed under `zenoh_rivals` in the status JSON and
reported once in the errors list.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import json
import logging
import threading
import time
from collections import deque
from collections.abc import Awaitable, Coroutine
from typing import Any

import zenoh

from geo_server import access
from geo_server.aio import wait_set
from geo_server.commands.requests import fault_command, record_command
from geo_server.dictionary import ObjectDef, loads_json
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.faults import carry_out
from geo_server.service import ObjectService
from geo_server.snapshot import Snapshot
from geo_server.transports.zenoh.keys import KeySpace, Route
from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.reads import JSON, OCTET, Reads, Reply, error_payload
from geo_server.transports.zenoh.rivals import Rivals
from geo_server.transports.zenoh.watch import RivalWatch, to_loop

log = logging.getLogger(__name__)

MAX_PAYLOAD = 64 * 1024  # NC text or JSON larger than this is refused
#: Refused puts waiting to be listed in the errors list (`_refused`); beyond, they are
#: counted and listed as one line.
MAX_REFUSALS_WAITING = 64
#: seconds `close` waits for Zenoh to undeclare this interface and close its session
CLOSE_WAIT_S = 5.0


def _json_value(payload: bytes, obj: ObjectDef) -> Any:
    """The value of a JSON write, in the object's type (`ObjectDef.coerce_json`).

    The payload is a JSON value of the object's type, or `{"value": <that>}` (the form
    a sensor publishing JSON objects uses); an object with any other key is refused.
    Every refusal is 0x706 (invalid data): a value of the wrong JSON type is invalid
    data, like one out of range; 0x705 stays for payloads of the wrong size. The JSON
    is read by `loads_json` and the value checked by `coerce_json`: the same rule as
    the web HMI's writes.
    """
    value = loads_json(payload, f"{obj.name}: payload", obj.name)
    if isinstance(value, dict):
        if set(value) != {"value"}:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDDATA,
                f'{obj.name}: a JSON object must be {{"value": …}} and nothing else',
                obj.name,
            )
        value = value["value"]
    return obj.coerce_json(value)


def _json_plan(payload: bytes) -> Any:
    """The JSON plan of `cmd/measure` (strict JSON: 0x706 otherwise)."""
    return loads_json(payload, "measure: the plan", "measure", constants=False)


class ZenohInterface:
    """Serve one machine's objects on a Zenoh session."""

    def __init__(
        self,
        service: ObjectService,
        options: ZenohOptions | None = None,
        session: zenoh.Session | None = None,
    ) -> None:
        """`session`: a Zenoh session shared by the machines of a fleet (opened and
        closed by its owner; `options` then only name the machine and its limits);
        None: this interface opens its own from `options`."""
        self.service = service
        self.options = options or ZenohOptions()
        self._shared = session
        self.keys = KeySpace(self.options.machine, service.info.dictionary, service.info.axes)
        #: answered whatever is in flight (`max_pending`): a fault can always be seen and
        #: cleared, also over the transport it holds up (docs/faults.md)
        self._never_busy = frozenset(
            (f"{self.keys.prefix}/cmd/fault", f"{self.keys.prefix}/status")
        )
        #: the answers to gets that read (`reads.py`)
        self.reads = Reads(service, self.keys)
        # KeyExprs built once: the publish loop puts every cycle
        self._status_ke = zenoh.KeyExpr(f"{self.keys.prefix}/status")
        self._errors_ke = zenoh.KeyExpr(f"{self.keys.prefix}/errors")
        self._session: zenoh.Session | None = None
        self._watch: zenoh.Publisher | None = None
        self._watched: asyncio.Event | None = None  # set while a subscriber matches
        #: whether a subscriber matches `cnc/<m>/**` (no watch publisher: always)
        self._watching = True
        self._entities: list[Any] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._unsubscribe: list[Any] = []
        #: gets answered: on Zenoh's queryable thread (`_read_now`) and on the loop
        #: (`_handle`), one counter per writer; `queries` is their sum
        self._queries_here = 0
        self._queries_loop = 0
        #: gets and puts handed to the loop (each counter has one writer: Zenoh's
        #: queryable thread, its subscriber thread, the loop) — their difference is the
        #: work in flight that `max_pending` caps
        self._queries_taken = 0
        self._puts_taken = 0
        self._finished = 0
        #: gets answered 0x716 and puts dropped with `max_pending` in flight (in the
        #: status as `zenoh_busy`; each written by its own Zenoh thread only)
        self.busy: dict[str, int] = {"gets_refused": 0, "puts_dropped": 0}
        self._shed_logged = 0.0
        self.faulted = 0  # queries an injected fault dropped, answered or delayed
        #: puts and deletes of other sessions on this machine's keys, counted once
        #: handled (queued for the cycle, applied if cycles run, or refused and listed)
        self.puts = 0
        self.refused_puts = 0  # of them, refused and listed in the errors list
        #: refused puts waiting to be listed, in the order they were refused, with how
        #: many each line stands for; one task lists them (`_refused`)
        self._refusals: deque[tuple[str, int]] = deque()
        self._unlisted = 0  # refused while MAX_REFUSALS_WAITING waited
        self._lister: asyncio.Task[None] | None = None
        #: Our own Zenoh id (set at start; in the status JSON as `zenoh_id`).
        self.zenoh_id = ""
        #: other sessions found answering for this machine (`rivals.py`, `watch.py`)
        self.rivals = Rivals(self.keys.machine, self.keys.prefix, self._report, self._put_rivals)
        self.watch = RivalWatch(self.keys, self.options, self.rivals)
        #: held while a read is answered on Zenoh's thread (`_read_now`, `_refuse_busy`)
        #: and while the interface undeclares and closes (`close`, and after it the
        #: watch's `probing`, a lock of its own: a probe never sends a read that could be
        #: answered at once to the loop): nothing is sent on a session being closed
        self._closing = threading.Lock()
        self._closed = False  # (no task is started once `close` began: `_spawn`)

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        if self._shared is not None:
            self._session = self._shared
        else:
            self._session = await self._loop.run_in_executor(
                None, zenoh.open, self.options.zenoh_config()
            )
        s = self._session
        prefix = self.keys.prefix
        self.zenoh_id = str(s.info.zid())
        log.info("zenoh session %s serves %s/**", self.zenoh_id, prefix)
        self.service.status_extra["zenoh_id"] = self.zenoh_id
        self.service.status_extra["zenoh_busy"] = self.busy
        self.rivals.own = self.zenoh_id
        self.rivals.publish()
        self._unsubscribe.append(self.service.subscribe_events(self._on_event))
        self._entities.append(s.declare_queryable(f"{prefix}/**", self._on_query))
        await self.watch.start(s, self._entities)  # (its token, its hints of rivals)
        # A put of a value on an object key is a write (docs/design.md §7): bridges
        # through Zenoh's REST or MQTT plugins write with put. Only other sessions' puts:
        # this session's own publications of the values are local.
        self._entities.append(
            s.declare_subscriber(f"{prefix}/**", self._on_put, allowed_origin=zenoh.Locality.REMOTE)
        )
        # Only its matching status is used: does any subscriber listen to this machine?
        # Remote ones only: the put subscriber above (and, in a fleet sharing this
        # session, the other machines') must not keep the publish loop awake.
        self._watch = s.declare_publisher(f"{prefix}/**", allowed_destination=zenoh.Locality.REMOTE)
        self._entities.append(self._watch)
        # the publish loop sleeps while nobody listens; a new subscriber wakes it
        self._watched = asyncio.Event()
        self._entities.append(self._watch.declare_matching_listener(self._on_watch))
        self._watching = _matching(self._watch)
        self._spawn(self._publish_loop())
        if self.options.status_period > 0:
            self._spawn(self._status_loop())
        self._spawn(self.watch.run())

    async def close(self) -> None:
        self._closed = True
        for unsub in self._unsubscribe:
            unsub()
        self._unsubscribe.clear()
        self.service.measurements.cancel()  # a worker thread driving the machine for cmd/measure
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for key in ("zenoh_id", "zenoh_rivals", "zenoh_busy"):
            self.service.status_extra.pop(key, None)
        entities, self._entities = list(reversed(self._entities)), []
        session, self._session = self._session, None
        self.watch.stop()

        done: concurrent.futures.Future[None] = concurrent.futures.Future()

        def shut() -> None:
            # Undeclaring waits for Zenoh callbacks in flight, which hand work to this
            # loop: never block the loop on it (nor on closing the session). A probe's
            # get sent from a worker thread (its task cancelled above, its thread not)
            # finishes first. (`done` is never cancelled: the wait below is shielded.)
            try:
                with self._closing, self.watch.probing:
                    for ent in entities:
                        ent.undeclare()
                    if session is not None and session is not self._shared:
                        session.close()
            except BaseException as exc:
                done.set_exception(exc)
            else:
                done.set_result(None)

        # A thread of its own, not the loop's executor (it never queues behind other
        # blocking work), and a daemon: rarely, under load, Zenoh's undeclare or close
        # has not returned for many seconds (CI, test_reliability_zenoh); a server that
        # shuts down must not hang on it, so after CLOSE_WAIT_S it is left to finish.
        threading.Thread(target=shut, name="zenoh-close", daemon=True).start()
        try:
            await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(done)), CLOSE_WAIT_S)
        except TimeoutError:
            log.warning(
                "zenoh: %s/** not undeclared and closed within %g s; left to finish",
                self.keys.prefix,
                CLOSE_WAIT_S,
            )

    @property
    def endpoints(self) -> list[str]:
        return list(self.options.listen)

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> asyncio.Task[None] | None:
        """`coro` as a task `close` ends; none once it closes (a query or put Zenoh
        handed over meanwhile is dropped: its task would outlive the interface; its
        count in `_in_flight` stays, which nothing reads once the interface is closed)."""
        if self._closed:
            coro.close()
            return None
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # ------------------------------------------------------------------ queries

    def _on_query(self, query: zenoh.Query) -> None:
        """Zenoh thread: a plain read is answered here when it can be at once
        (`_read_now`); anything else is handed to the loop, and this returns at once.
        Once the loop is gone nobody is left to answer; the query ends when Zenoh drops
        it. The coroutine is created on the loop (`_accept`), so a failed hand-off
        leaves no never-awaited coroutine behind."""
        if self._read_now(query):
            return
        if self._in_flight() >= self.options.max_pending and (
            str(query.key_expr) not in self._never_busy
        ):
            self._refuse_busy(query)
            return
        self._queries_taken += 1
        self._to_loop(self._accept, query)

    @property
    def queries(self) -> int:
        """Gets answered, on Zenoh's thread and on the loop."""
        return self._queries_here + self._queries_loop

    def _in_flight(self) -> int:
        return self._queries_taken + self._puts_taken - self._finished

    def _refuse_busy(self, query: zenoh.Query) -> None:
        """Zenoh thread: `max_pending` gets and puts are in flight; 0x716 at once (no
        reply at all while the interface closes)."""
        self.busy["gets_refused"] += 1
        try:
            if self._closing.acquire(timeout=0.05):
                try:
                    if self._session is not None:
                        err = AdsError(
                            AdsErrorCode.DEVICE_NOMOREHDLS,
                            f"more than {self.options.max_pending} requests in flight on "
                            "this interface: try again",
                        )
                        query.reply_err(error_payload(err), encoding=JSON)
                finally:
                    self._closing.release()
        finally:
            query.drop()

    def _read_now(self, query: zenoh.Query) -> bool:
        """Zenoh thread: answer a get without payload of one object's key, with no fault
        injected, when the cycle due is there without waiting (`Reads.plain`); True when
        answered. Anything else — another spelling of the key, a wildcard, a write, a
        command, status and errors, a refusal, an engine busy — goes to the loop, which
        answers it as always."""
        if self._session is None or query.payload is not None or self.service.faults.active:
            return False
        ke = query.key_expr
        key = str(ke)
        if not self.reads.is_plain(key):
            return False
        # never a reply while the interface undeclares and closes (`close` holds the
        # lock; a read that finds it taken goes to the loop, as every read once did)
        if not self._closing.acquire(False):
            return False
        try:
            reply = self.reads.plain(key) if self._session is not None else None
            if reply is None:
                return False
            self._queries_here += 1
            try:
                query.reply(ke, reply[0], encoding=reply[1])  # (as it came: not parsed again)
            finally:
                query.drop()
            return True
        finally:
            self._closing.release()

    def _accept(self, query: zenoh.Query) -> None:
        self._spawn(self._handle(query))

    def _on_put(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: a put or delete of another session on this machine's keys."""
        if self._in_flight() >= self.options.max_pending:
            self.busy["puts_dropped"] += 1
            now = time.monotonic()
            if now - self._shed_logged >= 10.0:
                self._shed_logged = now
                log.warning(
                    "zenoh: %d puts dropped so far, %d gets and puts in flight",
                    self.busy["puts_dropped"],
                    self.options.max_pending,
                )
            return
        delete = sample.kind == zenoh.SampleKind.DELETE
        key = str(sample.key_expr)
        payload = b"" if delete else sample.payload.to_bytes()[: MAX_PAYLOAD + 1]
        self._puts_taken += 1
        self._to_loop(self._accept_put, (key, None if delete else payload))

    def _accept_put(self, put: tuple[str, bytes | None]) -> None:
        self._spawn(self._put(*put))

    async def _put(self, key: str, payload: bytes | None) -> None:
        """A put writes the object of its key as a get with payload does (same checks,
        applied by the cycle after it arrives); with no one to answer, a refusal goes to
        the errors list (`cnc/<m>/errors`, `SIM::last_error`) naming the key. A delete
        removes nothing (an object cannot be deleted): it is reported the same way."""
        try:
            if payload is None:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDACCESS,
                    "an object cannot be deleted (put a value to write it)",
                )
            if len(payload) > MAX_PAYLOAD:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDSIZE, f"payload exceeds {MAX_PAYLOAD} bytes"
                )
            if self.options.read_only:
                raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, "this interface is read-only")
            route = self.keys.parse(key)
            if route.kind not in ("raw", "named"):
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDACCESS,
                    "a put writes objects; commands and NC text take a get with payload",
                )
            await self._write(route, payload)
        except AdsError as exc:
            what = "delete" if payload is None else "put"
            self._refused(f"zenoh {what} {key[:200]}: {exc.message} (ADS 0x{exc.code:X})")
        except Exception:  # never let one bad put take the interface down
            log.exception("zenoh put on %s failed", key[:200])
        finally:
            self.puts += 1
            self._finished += 1

    def _refused(self, text: str) -> None:
        """Loop: list a refused put in the errors list — in the order refusals are found
        (a put refused when it arrives: in the order the puts arrived), by one task, so
        no two worker threads list a burst out of order. The put itself is done: its
        slot of `max_pending` is free at once. Beyond MAX_REFUSALS_WAITING waiting, a
        refusal is only counted, and the count is listed as one line after them: a
        burst of bad puts neither floods the list nor holds work."""
        if len(self._refusals) < MAX_REFUSALS_WAITING:
            self._refusals.append((text, 1))
        else:
            self._unlisted += 1
        if self._lister is None or self._lister.done():
            self._lister = self._spawn(self._list_refusals())

    async def _list_refusals(self) -> None:
        """The task of `_refused`: each line in a worker thread (a report catches the
        cycle up), one after the other."""
        while self._refusals or self._unlisted:
            if self._refusals:
                text, count = self._refusals.popleft()
            else:
                count, self._unlisted = self._unlisted, 0
                text = (
                    f"zenoh: {count} more puts refused and not listed (more than "
                    f"{MAX_REFUSALS_WAITING} refusals waited to be listed)"
                )
            await asyncio.to_thread(self.service.report, text)
            self.refused_puts += count

    async def _write(self, route: Route, payload: bytes) -> Reply:
        """Write the object of a raw or named key: what is stored, as a reply payload."""
        svc = self.service
        if route.kind == "raw":
            await access.write_applied(svc, route.index_group, route.index_offset, payload)
            return payload, OCTET
        assert route.obj is not None
        value = _json_value(payload, route.obj)
        stored = await access.write_name_applied(svc, route.obj.name, route.axis, value)
        return json.dumps(stored).encode(), JSON

    async def _handle(self, query: zenoh.Query) -> None:
        self._queries_loop += 1
        try:
            payload = query.payload.to_bytes() if query.payload is not None else None
            key = str(query.key_expr)
            if payload is not None and len(payload) > MAX_PAYLOAD:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDSIZE,
                    f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}",
                )
            if self.service.faults.active and await self._faulted(query, key, payload):
                return
            if "*" in key:
                if payload is not None:
                    raise AdsError(
                        AdsErrorCode.DEVICE_INVALIDACCESS, "a write needs a concrete key"
                    )
                self.reads.wildcard(query)
            else:
                await self._answer(query, key, self.keys.parse(key), payload)
        except AdsError as exc:
            query.reply_err(error_payload(exc), encoding=JSON)
        except Exception as exc:  # never let one bad query take the interface down
            log.exception("zenoh query failed")
            err = AdsError(AdsErrorCode.DEVICE_ERROR, f"internal error: {exc}")
            query.reply_err(error_payload(err), encoding=JSON)
        finally:
            self._finished += 1
            query.drop()

    async def _faulted(self, query: zenoh.Query, key: str, payload: bytes | None) -> bool:
        """Carry out the injected fault that hits this query (docs/faults.md): True when
        it is dealt with (dropped: the get ends without a reply; or answered with a
        `reply_err`); a delay sleeps, then the query is served (False). The fault
        command and the status are exempt: a fault can always be seen and cleared."""
        name, route = "", None
        if "*" not in key:
            with contextlib.suppress(AdsError):
                route = self.keys.parse(key)
                name = route.obj.name if route.obj is not None else ""
        if route is not None and route.kind in ("fault", "status"):
            return False
        op = "read" if payload is None else "write"
        fault = self.service.faults.decide("zenoh", op, name)
        if fault is None:
            return False
        self.faulted += 1

        async def answered() -> bool:  # dropped, or answered with the error
            return True

        def error(code: int) -> Awaitable[bool]:
            err = AdsError(code, f"injected fault {fault.ident}: {fault.text}")
            query.reply_err(error_payload(err), encoding=JSON)
            return answered()

        async def delayed() -> bool:
            await fault.delay()  # cut short when the fault is cleared
            return False

        # (no Zenoh fault disconnects: a query has no connection of its own to drop)
        return await carry_out(
            fault, drop=answered, error=error, disconnect=answered, delay=delayed
        )

    async def _answer(
        self, query: zenoh.Query, key: str, route: Route, payload: bytes | None
    ) -> None:
        if payload is None:
            data, enc = self.reads.read(route, None)
            query.reply(key, data, encoding=enc)
            return
        if self.options.read_only:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, "this interface is read-only")
        svc = self.service
        if route.kind in ("raw", "named"):
            data, enc = await self._write(route, payload)
            query.reply(key, data, encoding=enc)
        elif route.kind in ("reload", "save"):
            result = await svc.commands.run_applied(route.kind)
            if not result.ok:
                body = {**result.error().as_dict(), **result.as_dict()}
                query.reply_err(json.dumps(body).encode(), encoding=JSON)
                return
            query.reply(key, json.dumps(result.as_dict()).encode(), encoding=JSON)
        elif route.kind == "nc":
            outcome = await self._run_nc(payload)
            query.reply(key, json.dumps(outcome).encode(), encoding=JSON)
        elif route.kind == "measure":
            spec = _json_plan(payload)
            # minutes of motion: in a worker thread, the loop keeps serving everyone else
            outcome = await asyncio.to_thread(svc.measurements.run, spec)
            query.reply(key, json.dumps(outcome).encode(), encoding=JSON)
        elif route.kind == "fault":
            body = await asyncio.to_thread(fault_command, svc.faults, payload)
            query.reply(key, json.dumps(body).encode(), encoding=JSON)
        elif route.kind == "record":
            body = await asyncio.to_thread(record_command, svc, payload, self.options.machine)
            query.reply(key, json.dumps(body).encode(), encoding=JSON)
        elif route.kind == "reset":
            cycle = await svc.nc.reset_applied()
            body = {"ok": True, "command": "reset", "cycle": cycle}
            query.reply(key, json.dumps(body).encode(), encoding=JSON)
        else:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, f"{key} cannot be written")

    async def _run_nc(self, payload: bytes) -> dict[str, Any]:
        """Run NC text: at most `max_nc_bytes` (else 0x705), parsed in a worker thread.

        Parsing and queueing a program takes time in proportion to its length, and on the
        loop that would hold up every other query; so the service parses it off the loop
        (`nc.run_applied`), and the size is checked first, before the text is decoded.
        """
        limit = self.options.max_nc_bytes
        if len(payload) > limit:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"NC text of {len(payload)} bytes exceeds {limit} bytes on this interface "
                "(run a long program from a file: geo-server run --program)",
                "nc",
            )
        try:
            text = payload.decode("utf-8")
        except UnicodeDecodeError:
            raise AdsError(AdsErrorCode.DEVICE_SYNTAX, "NC text must be UTF-8") from None
        cycle = await self.service.nc.run_applied(text)
        return {"ok": True, "lines": text.count("\n") + 1, "cycle": cycle}

    # ------------------------------------------------------------------ rivals

    def _to_loop(self, fn: Any, *args: Any) -> None:
        to_loop(self._loop, fn, *args)

    def _on_watch(self, status: zenoh.MatchingStatus) -> None:
        # (`_watching` is the loop's: `_publish_loop` sets it when it looks again)
        self._to_loop(self._watch_changed, bool(status.matching))

    def _watch_changed(self, matching: bool) -> None:
        if matching and self._watched is not None:  # (the loop clears it when it waits)
            self._watched.set()

    def _report(self, text: str, severity: str) -> None:
        self.service.report(text, severity=severity)

    def _put_rivals(self, rivals: list[dict[str, Any]]) -> None:
        self.service.status_extra["zenoh_rivals"] = rivals

    # ------------------------------------------------------------------ publications

    async def _publish_loop(self) -> None:
        """Put changed named values at most every `publish_period`, while someone
        subscribes to any of this machine's keys.

        `Snapshot.changed` finds what changed since the last publication with one array
        comparison. Whether anybody listens comes from Zenoh itself: the matching status
        of a publisher declared on `cnc/<m>/**` (a subscriber anywhere on the network
        whose key expression intersects it). Nobody listening, nothing is computed: the
        exact engine then has no publication to catch up for (docs/design.md §13), and
        a fleet of unwatched machines costs what their cycles cost.
        """
        named = {
            (route.obj.name, route.axis): (zenoh.KeyExpr(key), route.obj)
            for key, route in self.keys.named_routes().items()
            if route.obj is not None
        }
        watch, watched = self._watch, self._watched
        last: Snapshot | None = None
        recheck = self.options.watch_recheck
        shift = self.options.spread * recheck
        while True:
            if watch is not None and watched is not None and not _matching(watch):
                self._watching = False
                # nobody listens: wait for the matching listener (no polling at rest),
                # and look again now and then in case a status change went unreported
                watched.clear()
                await wait_set(watched, recheck + shift)
                shift = 0.0
                continue
            self._watching = True
            snap = self.service.current(stale_ok=True)  # the cycle due now (docs/design.md §13)
            if self._session is not None and (last is None or snap.cycle != last.cycle):
                for obj, axis in snap.changed(last):
                    entry = named.get((obj.name, axis))
                    if entry is not None:
                        value = snap.value(entry[1], axis)
                        self._session.put(entry[0], json.dumps(value).encode(), encoding=JSON)
                last = snap
            await asyncio.sleep(self.options.publish_period)

    async def _status_loop(self) -> None:
        """Put the status every `status_period` while someone subscribes to this
        machine's keys (as `_publish_loop`: a status is an observation, which makes the
        exact engine catch up; a get of `cnc/<m>/status` is answered whether or not)."""
        while True:
            if self._watching:
                self.publish_status(self.service.status())
            await asyncio.sleep(self.options.status_period)

    def publish_status(self, status: dict[str, Any]) -> None:
        """Put the machine's `status` on `cnc/<m>/status`; from any thread. A fleet's
        machines have no status loop (`status_period` 0): the fleet computes every
        machine's status off the event loop once per period and publishes it here
        (docs/design.md §13.1)."""
        session = self._session
        if session is not None and self._watching:
            session.put(self._status_ke, json.dumps(status).encode(), encoding=JSON)

    def _on_event(self, event: Event) -> None:
        """Cycle thread: hand a new warning/error to the loop for publication. Once the
        loop is gone the event is still in `errors` for a later get, so dropping its
        publication is harmless (raising here would fail the cycle that reported it)."""
        self._to_loop(self._put_event, event)

    def _put_event(self, event: Event) -> None:
        if self._session is not None:
            self._session.put(self._errors_ke, json.dumps(event.as_dict()).encode(), encoding=JSON)


def _matching(publisher: zenoh.Publisher) -> bool:
    """Whether subscribers match `publisher` (zenoh-python returns a `MatchingStatus`;
    its type stubs say bool)."""
    status: Any = publisher.matching_status
    return bool(getattr(status, "matching", status))
