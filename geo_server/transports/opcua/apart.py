"""OPC UA in a process of its own (docs/design.md §9.1 *OPC UA apart*).

asyncua's work is pure Python. On a thread of its own in the server's process, a flood
of Reads or a thousand monitored items still made ADS and Modbus wait for the
interpreter lock: their p99 rose 3× and 11× (bench/opcua_attacks.py), against 1.2× and
1.6× with OPC UA served from another process. `geo-server run` therefore serves OPC UA
from a child process: `OpcUaProcess` (the server's process) starts it and answers it,
`serve` (the child's composition root) runs `OpcUaInterface` over one `RemoteService`
per machine, the machine's service as OPC UA types it (`geo_server.seam.OpcUaService`).

The two talk over one pipe of pickled tuples; each side reads it on a thread of its own
and hands what it read to its owner (the server's event loop; in the child, the caller
waiting or the listener):

- child to server: `("call", id, machine, op, args)` an operation of the machine's
  service (`_OPERATIONS`), answered `("reply", id, ok, value or exception)`;
  `("listen", machine, on)` its published snapshots, each sent `("snap", machine,
  fields)`; `("demand", machine, step, at_rest)` the cycles its monitored items want
  (`step` 0: none); `("events", machine, on)` its warnings and errors, each sent
  `("event", machine, event)`; `("status", {machine: {key: dict}})` what each machine's
  status shows of OPC UA, twice a second; `("ready", port)` or `("failed", exception)`;
- server to child: `("stop",)`.

The child ignores SIGINT (a terminal's Ctrl-C reaches the whole process group; the
server stops it) and ends when the pipe does: a server that died leaves no OPC UA behind.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import io
import itertools
import logging
import multiprocessing
import pickle
import queue
import signal
import sys
import threading
from collections import deque
from collections.abc import Awaitable, Callable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from geo_server import timeslice
from geo_server.dictionary import ObjectDef
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.faults import FaultError
from geo_server.seam import ChosenCycles, Facts, OpcUaService, PreparedWrite
from geo_server.snapshot import ObjectLayout, Snapshot
from geo_server.transports.opcua.monitoring import Demand
from geo_server.transports.opcua.server import (
    HOST_WAIT_S,
    OpcUaInterface,
    OpcUaOptions,
    probe_port,
)
from geo_server.transports.opcua.status import ITEMS_STATUS, STATUS_KEYS
from geo_server.transports.share import LoopShare

log = logging.getLogger(__name__)

#: how long the server waits for the child to stop before it kills it: its own close
#: takes milliseconds, at most twice `CLOSE_WAIT_S` (1.5 s) when asyncua's server hangs,
#: and then it is killed mid-close; SIGTERM ends the server within 2 s
STOP_WAIT_S = 1.2
#: snapshots of one machine waiting to be sent to the child, past which its oldest are
#: dropped (counted: its status's `opcua_items` `samples_late`), as the child's own
#: monitoring drops the oldest it has not sampled
SNAP_BACKLOG = 256
#: the longest message the server reads from the child (its requests are small: names,
#: numbers, an OPC UA write's values, bounded by `guard.MAX_REQUEST`)
MAX_MESSAGE = 8 << 20
#: the most messages the server's writer sends in one (its queue's waiting ones)
SEND_BATCH = 64
#: how often the child sends what each machine's status shows of OPC UA (seconds)
STATUS_PERIOD_S = 0.5
#: the longest a write's check or a fault's injection waits for the server's answer
#: (a write's application and a method wait for as long as the service makes them)
CALL_WAIT_S = 5.0


# ---------------------------------------------------------------------- the server's side


def _current(service: OpcUaService) -> tuple[Any, ...]:
    return service.current().wire()


def _prepare(service: OpcUaService, name: str, axis: int, value: Any) -> Any:
    return _plain(service.prepare_name(name, axis, value).value)


def _plain(value: Any) -> Any:
    """A checked value as the child sends it back with the write: the server reads
    nothing but plain values from it (`_Restricted`)."""
    return value.item() if isinstance(value, np.generic) else value


async def _apply(service: OpcUaService, writes: list[tuple[str, int, Any]]) -> Any:
    # (each value was checked by `_prepare` already: checking it again changes nothing)
    return await service.apply_writes([service.prepare_name(n, a, v) for n, a, v in writes])


async def _command(service: OpcUaService, name: str) -> Any:
    return await service.commands.run_applied(name)


async def _nc_run(service: OpcUaService, text: str) -> int:
    return await service.nc.run_applied(text)


async def _nc_reset(service: OpcUaService) -> int:
    return await service.nc.reset_applied()


async def _inject(service: OpcUaService, fault: str) -> Any:
    return await asyncio.to_thread(service.faults.inject, fault)


async def _clear(service: OpcUaService, ident: int | None) -> Any:
    return await asyncio.to_thread(service.faults.clear, ident)


#: what the child may ask of a machine's service: the operations OPC UA uses, each run
#: on the server's event loop as the interface ran them in this process
_OPERATIONS: dict[str, Callable[..., Any]] = {
    "current": _current,
    "prepare": _prepare,
    "apply": _apply,
    "command": _command,
    "nc_run": _nc_run,
    "nc_reset": _nc_reset,
    "inject": _inject,
    "clear": _clear,
}


class OpcUaProcess:
    """`OpcUaInterface` served from a child process (see the module): the server the
    composition root starts and closes, its machines' services answering the child on
    the event loop `start` is called on."""

    def __init__(
        self,
        services: Mapping[str, OpcUaService],
        options: OpcUaOptions,
        shares: Mapping[str, LoopShare] | None = None,
    ) -> None:
        self.services = dict(services)
        self.options = options
        #: a fleet's machines' shares of the loop: their rates, for the child's own
        self.shares = {m: (s.rate, s.burst) for m, s in (shares or {}).items()}
        self.port = 0
        #: told when the child serves (None) or could not start (its exception)
        self.on_started: Callable[[BaseException | None], None] | None = None
        self.failure: BaseException | None = None
        #: per machine, snapshots not sent because the child was `SNAP_BACKLOG` behind
        #: (written by whichever thread publishes the machine's; in its status's
        #: `opcua_items` they count as `samples_late`, with the child's own)
        self.dropped: dict[str, int] = {}
        self._proc: Any = None  # multiprocessing's Process (its type is per context)
        self._conn: Any = None  # multiprocessing's Connection
        self._loop: asyncio.AbstractEventLoop | None = None
        self._out: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        #: per machine, the snapshots not sent yet (`_snapshots_of`; its marker in `_out`)
        self._snaps: dict[str, deque[Snapshot]] = {}
        self._ready: asyncio.Future[None] | None = None
        self._spawning: asyncio.Future[None] | None = None
        #: machine -> what the child holds of it ("listen", "events", "demand") -> its end
        self._held: dict[str, dict[str, Callable[[], None]]] = {}
        self._demands: dict[str, Demand] = {}
        self._tasks: set[asyncio.Future[Any]] = set()
        self._closing = False
        #: the child's pipe has ended (its process is gone or going)
        self.ended = False

    @property
    def endpoint(self) -> str:
        host, _ = self.options.host_port
        return f"opc.tcp://{host}:{self.port}"

    @property
    def pid(self) -> int | None:
        """OPC UA's process, once started."""
        return None if self._proc is None else int(self._proc.pid)

    async def start(self) -> None:
        """Check the port, then start the child (and the threads that read and write its
        pipe) in the background, as `OpcUaInterface` builds its server: the composition
        root starts the cycle once every interface's `start` returned. With
        `options.background` off, return once it serves."""
        loop = self._loop = asyncio.get_running_loop()
        host, port = self.options.host_port
        if port:
            await asyncio.to_thread(probe_port, host, port)
        self.port = port
        self._ready = loop.create_future()
        if self._closing:  # (closed while the port was checked: nothing to start)
            return
        self._spawning = asyncio.ensure_future(self._spawn())
        if not self.options.background:
            await asyncio.shield(self._ready)

    async def _spawn(self) -> None:
        try:
            ctx = multiprocessing.get_context("spawn")
            mine, theirs = ctx.Pipe()
            facts = {m: Facts.of(s.info) for m, s in self.services.items()}
            proc = ctx.Process(
                target=serve,
                args=(theirs, self.options, facts, self.shares),
                name="geo-opcua",
                daemon=True,
            )
            try:
                await asyncio.to_thread(_started_without_sigint, proc)
            finally:
                theirs.close()
        except Exception as exc:  # (no process: said as a start that failed)
            self._started(exc)
            return
        self._proc, self._conn = proc, mine
        for target, name in ((self._read, "opcua-in"), (self._write, "opcua-out")):
            threading.Thread(target=target, name=name, daemon=True).start()

    async def close(self) -> None:
        """Stop the child (killed when it has not ended within `STOP_WAIT_S`) and give
        back what it held of the machines."""
        self._closing = True
        spawning = self._spawning
        if spawning is not None and not spawning.done():
            with contextlib.suppress(BaseException):
                await spawning
        proc = self._proc
        if proc is None:
            return
        self._out.put(("stop",))
        await asyncio.to_thread(proc.join, STOP_WAIT_S)
        if proc.is_alive():
            log.warning("opcua: its process did not stop in %.1f s: killed", STOP_WAIT_S)
            proc.kill()
            await asyncio.to_thread(proc.join, 1.0)
        self._out.put(None)
        self._release_all()
        for task in list(self._tasks):
            task.cancel()
        with contextlib.suppress(OSError):
            self._conn.close()

    # -------------------------------------------------------------- the pipe's threads

    def _read(self) -> None:
        """The pipe's reader: each message, at most `MAX_MESSAGE` bytes and made only
        of plain values and the errors the interface raises (`_Restricted`: the child
        faces the network, the server trusts none of its objects), handed to the event
        loop; a Read's snapshot answered here when it needs no catch-up."""
        loop = self._loop
        assert loop is not None
        try:
            while True:
                msg = _Restricted.loads(self._conn.recv_bytes(MAX_MESSAGE))
                if not self._answered_here(msg):
                    loop.call_soon_threadsafe(self._on_message, msg)
        except Exception as exc:  # (EOF; a message too long or not of plain values)
            if not isinstance(exc, EOFError):
                # trusted no further: it ends, as if it had died (`_ended` says so)
                log.error("opcua: a message of its process refused (%s): it is stopped", exc)
                with contextlib.suppress(Exception):
                    self._proc.kill()
            with contextlib.suppress(RuntimeError):  # (the loop has ended: nobody listens)
                loop.call_soon_threadsafe(self._ended)

    def _answered_here(self, msg: Any) -> bool:
        """A Read's snapshot when the published one is the one due (`current_if_due`, a
        look without the engine's lock, as the interface's own thread did in one
        process): no turn of the event loop."""
        if not (isinstance(msg, tuple) and len(msg) == 5 and msg[:1] == ("call",)):
            return False
        _, rid, machine, op, _args = msg
        service = self.services.get(machine) if isinstance(machine, str) else None
        if op != "current" or service is None or self._closing:
            return False
        try:
            snap = service.current_if_due()
        except AdsError as exc:
            self._reply(rid, False, exc)
            return True
        if snap is None:
            return False
        self._reply(rid, True, snap.wire())
        return True

    def _write(self) -> None:
        """The pipe's writer: the loop's answers and the events in the order they were
        put, and each machine's waiting snapshots, at most `SEND_BATCH` at a time (the
        rest after what was put meanwhile: an answer never waits behind a backlog), in
        one message (`("batch", [...])`: a batch of the exact engine's cycles is one
        send, not sixteen)."""
        out = self._out
        while True:
            batch = [out.get()]
            while len(batch) < SEND_BATCH and not out.empty():
                batch.append(out.get_nowait())
            msgs: list[tuple[Any, ...]] = []
            for m in batch:
                if m is None:
                    self._send(msgs)
                    return
                if m[0] != "snaps":
                    msgs.append(m)
                elif len(msgs) < SEND_BATCH:
                    msgs += self._taken(m[1], SEND_BATCH - len(msgs))
                else:  # (this send is full: after what was put meanwhile)
                    out.put(m)
            if not self._send(msgs):
                return

    def _taken(self, machine: str, most: int) -> list[tuple[Any, ...]]:
        """Up to `most` of the machine's waiting snapshots; its marker is put back when
        more wait. (One thread publishes a machine's snapshots at a time, the engine
        lock's holder, and this one takes them: a marker is never lost, at worst one
        more is put.)"""
        waiting = self._snaps.get(machine)
        taken: list[tuple[Any, ...]] = []
        while waiting and len(taken) < most:
            with contextlib.suppress(IndexError):
                taken.append(("snap", machine, waiting.popleft().wire()))
        if waiting:
            self._out.put(("snaps", machine))
        return taken

    def _send(self, msgs: list[tuple[Any, ...]]) -> bool:
        """False when the child is gone (`_read` says so)."""
        try:
            if len(msgs) == 1:
                self._conn.send(msgs[0])
            elif msgs:
                self._conn.send(("batch", msgs))
        except (OSError, ValueError):
            return False
        except Exception:  # (a value that cannot be pickled: each on its own, said)
            if len(msgs) > 1:
                return all(self._send([m]) for m in msgs)
            log.exception("opcua: a message to its process could not be sent: %s", msgs[0][0])
            if msgs[0][0] == "reply":
                error = AdsError(AdsErrorCode.DEVICE_ERROR, "the answer could not be sent")
                return self._send([("reply", msgs[0][1], False, error)])
        return True

    # ------------------------------------------------------------- on the event loop

    def _on_message(self, msg: tuple[Any, ...]) -> None:
        if self._closing or not isinstance(msg, tuple) or not msg:
            return  # (a request still on its way when the server closed)
        kind = msg[0]
        if kind == "call":
            self._call(*msg[1:])
        elif kind in ("listen", "events"):
            self._listen(kind, msg[1], bool(msg[2]))
        elif kind == "demand":
            self._demand(msg[1], int(msg[2]), bool(msg[3]))
        elif kind == "status":
            for machine, extra in msg[1].items():
                service = self.services.get(machine)
                if service is None:
                    continue
                shown = _shown(extra)  # (what OPC UA may show, nothing else of the status)
                items = shown.get(ITEMS_STATUS)
                if items is not None and machine in self.dropped:
                    items["samples_late"] = items.get("samples_late", 0) + self.dropped[machine]
                service.status_extra.update(shown)
        elif kind == "ready":
            self.port = int(msg[1])
            self._started(None)
        elif kind == "failed":
            self._started(msg[1])

    def _started(self, failure: BaseException | None) -> None:
        ready = self._ready
        if ready is None or ready.done():
            return
        self.failure = failure
        if failure is None:
            ready.set_result(None)
        else:
            ready.set_exception(failure)
            ready.exception()  # (retrieved: a background start says it through `on_started`)
        if self.on_started is not None and self.options.background and not self._closing:
            self.on_started(failure)

    def _ended(self) -> None:
        """The child's pipe ended: what it held is given back; unless the server is
        stopping, that is an error (it is said once)."""
        self.ended = True
        self._release_all()
        for service in self.services.values():  # (nothing of OPC UA to show any more)
            for key in STATUS_KEYS:
                service.status_extra.pop(key, None)
        if self._closing or self.failure is not None:  # (its failed start: said once)
            return
        failure = RuntimeError("OPC UA's process ended")
        if self._ready is not None and not self._ready.done():
            self._started(failure)
            return
        log.error("opcua: %s; the other interfaces keep serving", failure)

    def _call(self, rid: int, machine: str, op: str, args: tuple[Any, ...]) -> None:
        service = self.services.get(machine)
        work = _OPERATIONS.get(op)
        if service is None or work is None:
            self._reply(rid, False, AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"{op} {machine}"))
            return
        try:
            result = work(service, *args)
        except Exception as exc:
            self._reply(rid, False, exc)
            return
        if not isinstance(result, Awaitable):
            self._reply(rid, True, result)
            return
        task = asyncio.ensure_future(result)
        self._tasks.add(task)

        def done(t: asyncio.Future[Any]) -> None:
            self._tasks.discard(t)
            if t.cancelled():
                return
            exc = t.exception()
            self._reply(rid, exc is None, t.result() if exc is None else exc)

        task.add_done_callback(done)

    def _reply(self, rid: int, ok: bool, value: Any) -> None:
        self._out.put(("reply", rid, ok, value if ok else _portable(value)))

    def _listen(self, kind: str, machine: str, on: bool) -> None:
        service = self.services.get(machine)
        held = self._held.setdefault(machine, {})
        if not on or service is None:
            release = held.pop(kind, None)
            if release is not None:
                release()
            return
        if kind in held:
            return
        if kind == "listen":
            held[kind] = service.subscribe(self._snapshots_of(machine))
        else:
            held[kind] = service.subscribe_events(self._events_of(machine))

    def _snapshots_of(self, machine: str) -> Callable[[Snapshot], None]:
        out = self._out
        waiting = self._snaps.setdefault(machine, deque())

        def on_cycle(snap: Snapshot) -> None:  # the publishing thread: hand over, return
            # (deque appends and pops are atomic; the writer is told once for all the
            # snapshots that arrive until it takes them)
            if len(waiting) >= SNAP_BACKLOG:
                with contextlib.suppress(IndexError):
                    waiting.popleft()
                    self.dropped[machine] = self.dropped.get(machine, 0) + 1
            waiting.append(snap)
            if len(waiting) == 1:
                out.put(("snaps", machine))

        return on_cycle

    def _events_of(self, machine: str) -> Callable[[Event], None]:
        out = self._out

        def on_event(event: Event) -> None:  # the reporting thread: hand over, return
            out.put(("event", machine, event))

        return on_event

    def _demand(self, machine: str, step: int, at_rest: bool) -> None:
        service = self.services.get(machine)
        held = self._held.setdefault(machine, {})
        if step <= 0 or service is None:
            release = held.pop("demand", None)
            self._demands.pop(machine, None)
            if release is not None:
                release()
            return
        wanted = self._demands.get(machine)
        if wanted is None:
            wanted = self._demands[machine] = Demand(step, at_rest)
            held["demand"] = service.demand_cycles(wanted)
        else:
            wanted.set(step, at_rest)

    def _release_all(self) -> None:
        for held in self._held.values():
            for release in held.values():
                release()
            held.clear()
        self._demands.clear()


def _builtin_subclasses(cls: type) -> list[type]:
    found = [c for c in cls.__subclasses__() if c.__module__ == "builtins"]
    return found + [s for c in found for s in _builtin_subclasses(c)]


def _shown(extra: Any) -> dict[str, dict[str, int | float]]:
    """The child's status of one machine, only its keys, only numbers in them."""
    if not isinstance(extra, dict):
        return {}
    return {
        key: {k: v for k, v in part.items() if isinstance(k, str) and type(v) in (int, float)}
        for key in STATUS_KEYS
        if isinstance(part := extra.get(key), dict)
    }


class _Restricted(pickle.Unpickler):
    """Unpickles what the child may send: plain values and the errors it passes on,
    nothing that runs code (`find_class` refuses every other class)."""

    ALLOWED: ClassVar[dict[tuple[str, str], Any]] = {
        ("builtins", "RuntimeError"): RuntimeError,
        ("builtins", "ValueError"): ValueError,
        # (an OSError with an errno is rebuilt as the built-in class of that errno)
        **{("builtins", c.__name__): c for c in (OSError, *_builtin_subclasses(OSError))},
        ("geo_server.errors", "AdsError"): AdsError,
        ("geo_server.errors", "AdsErrorCode"): AdsErrorCode,
        ("geo_server.faults", "FaultError"): FaultError,
    }

    def find_class(self, module: str, name: str) -> Any:
        found = self.ALLOWED.get((module, name))
        if found is None:
            raise pickle.UnpicklingError(f"{module}.{name} is not sent by OPC UA's process")
        return found

    @classmethod
    def loads(cls, data: bytes) -> Any:
        return cls(io.BytesIO(data)).load()


def _started_without_sigint(proc: Any) -> None:
    """`proc.start()` with SIGINT blocked in this thread, so the child inherits it
    blocked until `serve` ignores it: a terminal's Ctrl-C reaches the whole process
    group, and a child still importing would end with a traceback (POSIX; Windows
    sends no SIGINT to it)."""
    if sys.platform == "win32":
        proc.start()
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        proc.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


# ---------------------------------------------------------------------- the child's side


class Link:
    """The child's end of the pipe: requests and their answers, and the snapshots and
    events the server sends, handed to their listeners on the reading thread (as the
    cycle's thread calls them in the server's process)."""

    def __init__(self, conn: Any, layouts: Mapping[str, ObjectLayout]) -> None:
        self._conn = conn
        self._layouts = dict(layouts)
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._calls: dict[int, concurrent.futures.Future[Any]] = {}
        self.snapshots: dict[str, list[Callable[[Snapshot], None]]] = {}
        self.events: dict[str, list[Callable[[Event], None]]] = {}
        #: called (on the reading thread) when the server says stop or has gone
        self.on_stop: Callable[[], None] = lambda: None
        self._gone = False

    def start(self) -> None:
        threading.Thread(target=self._read, name="opcua-link", daemon=True).start()

    def snapshot(self, machine: str, fields: tuple[Any, ...]) -> Snapshot:
        """A snapshot of `machine` from what the pipe carried."""
        return Snapshot.from_wire(fields, self._layouts[machine])

    def send(self, msg: tuple[Any, ...]) -> None:
        with self._lock:
            if self._gone:
                return
            try:
                self._conn.send(msg)
            except (OSError, ValueError):
                self._gone = True

    def call(self, machine: str, op: str, *args: Any, wait: float) -> Any:
        """The answer of the server to `op` (blocking this thread at most `wait` s;
        then 0x707, as a main loop that does not answer in time is in one process)."""
        pending = self._request(machine, op, args)
        try:
            return pending.result(wait)
        except concurrent.futures.TimeoutError:
            pending.cancel()
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY, "the server's main loop did not answer in time"
            ) from None

    async def acall(self, machine: str, op: str, *args: Any) -> Any:
        return await asyncio.wrap_future(self._request(machine, op, args))

    def _request(
        self, machine: str, op: str, args: tuple[Any, ...]
    ) -> concurrent.futures.Future[Any]:
        rid = next(self._ids)
        pending: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._calls[rid] = pending
        pending.add_done_callback(lambda _f: self._calls.pop(rid, None))
        if self._gone:
            pending.set_exception(AdsError(AdsErrorCode.DEVICE_NOTREADY, "the server is gone"))
        else:
            self.send(("call", rid, machine, op, args))
        return pending

    def _read(self) -> None:
        try:
            while True:
                msg = self._conn.recv()
                for one in msg[1] if msg[0] == "batch" else (msg,):
                    try:
                        if not self._handle(one):
                            raise EOFError
                    except EOFError:
                        raise
                    except Exception:  # (a listener's fault: said, the others go on)
                        log.exception("opcua: a message of the server failed: %s", one[0])
        except (EOFError, OSError):
            pass
        self._gone = True
        for pending in list(self._calls.values()):
            if pending.set_running_or_notify_cancel():
                pending.set_exception(AdsError(AdsErrorCode.DEVICE_NOTREADY, "the server is gone"))
        self.on_stop()

    def _handle(self, msg: tuple[Any, ...]) -> bool:
        """One message of the server; False: stop."""
        kind = msg[0]
        if kind == "reply":
            pending = self._calls.pop(msg[1], None)
            if pending is not None and pending.set_running_or_notify_cancel():
                if msg[2]:
                    pending.set_result(msg[3])
                else:
                    pending.set_exception(msg[3])
        elif kind == "snap":
            snap = self.snapshot(msg[1], msg[2])
            for listener in list(self.snapshots.get(msg[1], ())):
                listener(snap)
        elif kind == "event":
            for on_event in list(self.events.get(msg[1], ())):
                on_event(msg[2])
        elif kind == "stop":
            return False
        return True


class _Nc:
    def __init__(self, link: Link, machine: str) -> None:
        self._link, self._machine = link, machine

    async def run_applied(self, text: str, *, timeout: float | None = None) -> int:
        return int(await self._link.acall(self._machine, "nc_run", text))

    async def reset_applied(self, *, timeout: float | None = None) -> int:
        return int(await self._link.acall(self._machine, "nc_reset"))


class _Commands:
    def __init__(self, link: Link, machine: str) -> None:
        self._link, self._machine = link, machine

    async def run_applied(self, name: str, value: Any = None) -> Any:
        return await self._link.acall(self._machine, "command", name)


class _Faults:
    def __init__(self, link: Link, machine: str) -> None:
        self._link, self._machine = link, machine

    def inject(self, fault: str) -> dict[str, Any]:
        injected: dict[str, Any] = self._link.call(self._machine, "inject", fault, wait=CALL_WAIT_S)
        return injected

    def clear(self, ident: int | None = None) -> list[dict[str, Any]]:
        cleared: list[dict[str, Any]] = self._link.call(
            self._machine, "clear", ident, wait=CALL_WAIT_S
        )
        return cleared


class RemoteService:
    """A machine's service in OPC UA's own process (`seam.OpcUaService`): its facts
    sent once, everything else asked of the server's service over the `Link`."""

    def __init__(self, link: Link, machine: str, facts: Facts) -> None:
        self._link, self._machine = link, machine
        self.info = facts
        self.status_extra: dict[str, Any] = {}
        self.nc = _Nc(link, machine)
        self.commands = _Commands(link, machine)
        self.faults = _Faults(link, machine)

    def current(
        self, *, stale_ok: bool = False, wait: float | None = None, at_rest_ok: bool = False
    ) -> Snapshot:
        return self._link.snapshot(
            self._machine, self._link.call(self._machine, "current", wait=HOST_WAIT_S)
        )

    def current_if_due(self) -> Snapshot | None:
        """`current` from here: the server's loop catches the machine up, as it did for
        the interface's own thread in one process."""
        return self.current()

    def subscribe(self, callback: Callable[[Snapshot], None]) -> Callable[[], None]:
        return self._listen(self._link.snapshots, "listen", callback)

    def subscribe_events(self, callback: Callable[[Event], None]) -> Callable[[], None]:
        return self._listen(self._link.events, "events", callback)

    def _listen(self, table: dict[str, list[Any]], kind: str, callback: Any) -> Callable[[], None]:
        listeners = table.setdefault(self._machine, [])
        listeners.append(callback)
        if len(listeners) == 1:
            self._link.send((kind, self._machine, True))

        def stop() -> None:
            with contextlib.suppress(ValueError):
                listeners.remove(callback)
                if not listeners:
                    self._link.send((kind, self._machine, False))

        return stop

    def demand_cycles(self, demand: ChosenCycles | None = None) -> Callable[[], None]:
        """The server's engine publishes the cycles `demand` wants (a `Demand`: told
        of each change; None: every cycle)."""
        machine, send = self._machine, self._link.send
        if isinstance(demand, Demand):
            wanted = demand

            sent: list[tuple[int, bool]] = []

            def changed() -> None:  # (each change once: items made often leave it as it was)
                now = (wanted.step, wanted.at_rest)
                if sent[-1:] != [now]:
                    sent[:] = [now]
                    send(("demand", machine, *now))

            wanted.changed = changed
            changed()
        else:
            send(("demand", machine, 1, True))

        def release() -> None:
            if isinstance(demand, Demand):
                demand.changed = None
            send(("demand", machine, 0, False))

        return release

    def prepare_name(self, name: str | ObjectDef, axis: int, value: Any) -> PreparedWrite:
        """Checked here, as the service checks it (its object writable on an axis the
        machine has, the value its type's); only a refusal goes to the server, whose
        check says it again and notes it in the machine's error list, as in one
        process. The server checks every write again when it applies it (`_apply`)."""
        obj = self.info.dictionary.by_name(name) if isinstance(name, str) else name
        if obj.writable and (obj.scope != "axis" or axis in self.info.axes):
            with contextlib.suppress(AdsError):
                return PreparedWrite(obj, axis, _plain(obj.coerce(value)))
        checked = self._link.call(self._machine, "prepare", obj.name, axis, value, wait=HOST_WAIT_S)
        return PreparedWrite(obj, axis, checked)

    async def apply_writes(
        self, writes: Sequence[PreparedWrite], timeout: float | None = None
    ) -> list[AdsError | None]:
        answer: list[AdsError | None] = await self._link.acall(
            self._machine, "apply", [(w.obj.name, w.axis, w.value) for w in writes]
        )
        return answer


def serve(
    conn: Any,
    options: OpcUaOptions,
    facts: Mapping[str, Facts],
    shares: Mapping[str, tuple[float, float]],
) -> None:
    """OPC UA's process (`multiprocessing`'s target): its composition root."""
    # (the server stops it: a Ctrl-C or a SIGTERM sent to the whole process group, as a
    # service manager may, must not end it first)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform != "win32":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.basicConfig(format="%(message)s", level=logging.WARNING)
    # (the slice the server asked for lets its wake-ups preempt: not this process's,
    # which the network drives — an attacker's work must wait its turn; geo_server/timeslice.py)
    timeslice.request(0)
    asyncio.run(_serve(conn, options, facts, shares))


async def _serve(
    conn: Any,
    options: OpcUaOptions,
    facts: Mapping[str, Facts],
    shares: Mapping[str, tuple[float, float]],
) -> None:
    loop = asyncio.get_running_loop()
    layouts: dict[int, ObjectLayout] = {}  # (one per dictionary: a fleet shares one)
    for f in facts.values():
        layouts.setdefault(id(f.dictionary), ObjectLayout(f.dictionary))
    link = Link(conn, {m: layouts[id(f.dictionary)] for m, f in facts.items()})
    services = {m: RemoteService(link, m, f) for m, f in facts.items()}
    machine_shares = {m: LoopShare(rate, burst) for m, (rate, burst) in shares.items()}
    iface = OpcUaInterface(services, dataclasses.replace(options, background=True), machine_shares)
    stop = asyncio.Event()

    def stopping() -> None:  # (the link's reading thread)
        with contextlib.suppress(RuntimeError):  # (the loop has ended already)
            loop.call_soon_threadsafe(stop.set)

    link.on_stop = stopping

    def started(failure: BaseException | None) -> None:
        link.send(("failed", _portable(failure)) if failure else ("ready", iface.port))
        if failure is not None:  # (nothing to serve: this process ends)
            stopping()

    iface.on_started = started
    link.start()
    try:
        await iface.start()
    except Exception as exc:
        link.send(("failed", _portable(exc)))
        return
    try:
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), STATUS_PERIOD_S)
            link.send(("status", {m: _status_of(s) for m, s in services.items()}))
    finally:
        await iface.close()


def _status_of(service: RemoteService) -> dict[str, Any]:
    return {k: dict(v) if isinstance(v, dict) else v for k, v in service.status_extra.items()}


def _portable(exc: BaseException) -> BaseException:
    """`exc` as the other side can rebuild it (`_Restricted`): an AdsError keeps its
    code, a FaultError its text, an OSError its errno (a port in use) and a ValueError
    its text as the built-in classes; any other is a RuntimeError that says what it was."""
    if type(exc) in (AdsError, FaultError):
        return exc
    if isinstance(exc, OSError):  # (with an errno: the built-in class of that errno)
        return OSError(exc.errno, exc.strerror or str(exc)) if exc.errno else OSError(str(exc))
    if isinstance(exc, ValueError):
        return ValueError(str(exc))
    return RuntimeError(f"{type(exc).__name__}: {exc}")


__all__ = ["OpcUaProcess", "RemoteService", "serve"]
