"""The Zenoh interface (SPEC §7): a thin shell over the object service.

Zenoh calls our queryable callback on one of its own threads. The callback only hands
the query to the asyncio loop (`call_soon_threadsafe`); everything else — reading the
snapshot, validating a write, waiting for it to be applied — happens on the loop, so
Zenoh's dispatch is never blocked and the GEO cycle never waits on Zenoh. Reload/save
(by `cmd/…` key or by writing `SIM::reload`/`SIM::save`) run in a worker thread, so the
loop, which ADS and Modbus may share, is not blocked while list files are read or written.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from geo_server.dictionary import AdsError, AdsErrorCode, ObjectDef
from geo_server.machine.machine import Event
from geo_server.machine.snapshot import Snapshot
from geo_server.service import ADSERR_DEVICE_SYNTAX, ObjectService
from geo_server.transports.keys import KeySpace, Route

log = logging.getLogger(__name__)

OCTET = zenoh.Encoding.APPLICATION_OCTET_STREAM
JSON = zenoh.Encoding.APPLICATION_JSON
MAX_PAYLOAD = 64 * 1024  # NC text or JSON larger than this is refused
WRITE_TIMEOUT_S = 2.0
ADSERR_TIMEOUT = 0x719  # ADS DEVICE_TIMEOUT: a write not applied within WRITE_TIMEOUT_S


@dataclass
class ZenohOptions:
    """How the server joins a Zenoh network (SPEC §7)."""

    machine: str = "local"
    mode: str = "peer"  # "peer" | "client"
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    config_file: str | None = None  # a Zenoh JSON5 config for anything else (TLS, ACL)
    publish_period: float = 0.05
    status_period: float = 1.0
    read_only: bool = False

    def zenoh_config(self) -> zenoh.Config:
        cfg = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        if self.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        return cfg


def _error_payload(exc: AdsError) -> bytes:
    return json.dumps(exc.as_dict()).encode()


def _json_value(payload: bytes, obj: ObjectDef) -> Any:
    try:
        value = json.loads(payload)
    # RecursionError: deeply nested JSON ("[[[[…]]]]", well within MAX_PAYLOAD) is bad
    # data like any other (0x706), not an internal error (found by tests/test_robust_fuzz.py)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise AdsError(
            AdsErrorCode.INVALID_DATA, f"{obj.name}: payload is not JSON ({exc})", obj.name
        ) from None
    if isinstance(value, dict):
        if "value" not in value:
            raise AdsError(AdsErrorCode.INVALID_DATA, 'JSON object needs a "value"', obj.name)
        value = value["value"]
    if isinstance(value, list | dict) or value is None:
        raise AdsError(AdsErrorCode.INVALID_DATA, f"{obj.name}: not a scalar: {value!r}", obj.name)
    return value


class ZenohInterface:
    """Serve one machine's objects on a Zenoh session."""

    def __init__(self, service: ObjectService, options: ZenohOptions | None = None) -> None:
        self.service = service
        self.options = options or ZenohOptions()
        self.keys = KeySpace(self.options.machine, service.dictionary, service.axes)
        # KeyExprs built once: a wildcard get intersects every readable key and the
        # publish loop puts every cycle; building (and validating) a KeyExpr from a str
        # each time is pure overhead on the loop the GEO cycle shares the GIL with.
        self._readable = [
            (zenoh.KeyExpr(key), key, route) for key, route in self.keys.readable_keys().items()
        ]
        self._status_ke = zenoh.KeyExpr(f"{self.keys.prefix}/status")
        self._errors_ke = zenoh.KeyExpr(f"{self.keys.prefix}/errors")
        self._session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self._tasks: set[asyncio.Task] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._unsubscribe: list[Any] = []
        self.queries = 0

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._session = await self._loop.run_in_executor(
            None, zenoh.open, self.options.zenoh_config()
        )
        s = self._session
        prefix = self.keys.prefix
        self._entities.append(s.declare_queryable(f"{prefix}/**", self._on_query))
        self._entities.append(s.liveliness().declare_token(self.keys.alive_key))
        self._unsubscribe.append(self.service.subscribe_events(self._on_event))
        self._spawn(self._publish_loop())
        self._spawn(self._status_loop())

    async def close(self) -> None:
        for unsub in self._unsubscribe:
            unsub()
        self._unsubscribe.clear()
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for ent in reversed(self._entities):
            ent.undeclare()
        self._entities.clear()
        if self._session is not None:
            session, self._session = self._session, None
            await asyncio.get_running_loop().run_in_executor(None, session.close)

    @property
    def endpoints(self) -> list[str]:
        return list(self.options.listen)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ queries

    def _on_query(self, query: zenoh.Query) -> None:
        """Zenoh thread: hand the query to the loop and return at once."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            # The loop may close between the check and the hand-off (server shutting
            # down while a query arrives): call_soon_threadsafe then raises RuntimeError
            # on Zenoh's thread. Nobody is left to answer; the query ends when Zenoh
            # drops it. The coroutine is created on the loop (`_accept`), so a failed
            # hand-off leaves no never-awaited coroutine behind.
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._accept, query)

    def _accept(self, query: zenoh.Query) -> None:
        self._spawn(self._handle(query))

    async def _handle(self, query: zenoh.Query) -> None:
        self.queries += 1
        try:
            payload = query.payload.to_bytes() if query.payload is not None else None
            key = str(query.key_expr)
            if payload is not None and len(payload) > MAX_PAYLOAD:
                raise AdsError(
                    AdsErrorCode.INVALID_SIZE,
                    f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}",
                )
            if "*" in key:
                if payload is not None:
                    raise AdsError(AdsErrorCode.INVALID_ACCESS, "a write needs a concrete key")
                self._answer_wildcard(query)
            else:
                await self._answer(query, key, self.keys.parse(key), payload)
        except AdsError as exc:
            query.reply_err(_error_payload(exc), encoding=JSON)
        except Exception as exc:  # never let one bad query take the interface down
            log.exception("zenoh query failed")
            err = AdsError(0x700, f"internal error: {exc}")
            query.reply_err(_error_payload(err), encoding=JSON)
        finally:
            query.drop()

    def _answer_wildcard(self, query: zenoh.Query) -> None:
        """One reply per concrete key the wildcard matches, all from one snapshot.

        A wildcard that matches none of our keys (an unconfigured axis, a misspelt
        field) is answered with `reply_err` (SPEC §7: every get is answered), not with
        silence that the client can only tell from its own timeout.
        """
        snap = self.service.snapshot
        ke = query.key_expr
        matched = [(key, route) for kexpr, key, route in self._readable if kexpr.intersects(ke)]
        if not matched:
            raise self.keys.no_match(str(ke))
        for key, route in matched:
            payload, enc = self._read(route, snap)
            query.reply(key, payload, encoding=enc)

    def _read(self, route: Route, snap: Snapshot) -> tuple[bytes, zenoh.Encoding]:
        if route.kind == "raw":
            data = self.service.read(route.index_group, route.index_offset, None, snap)
            return data, OCTET
        if route.kind == "named":
            assert route.obj is not None
            return json.dumps(snap.value(route.obj, route.axis)).encode(), JSON
        if route.kind == "status":
            return json.dumps(self.service.status()).encode(), JSON
        if route.kind == "errors":
            return json.dumps(self.service.errors()).encode(), JSON
        raise AdsError(
            AdsErrorCode.INVALID_ACCESS, f"{route.kind} needs a payload (get with payload runs it)"
        )

    async def _answer(
        self, query: zenoh.Query, key: str, route: Route, payload: bytes | None
    ) -> None:
        if payload is None:
            data, enc = self._read(route, self.service.snapshot)
            query.reply(key, data, encoding=enc)
            return
        if self.options.read_only:
            raise AdsError(AdsErrorCode.INVALID_ACCESS, "this interface is read-only")
        # write_async/write_name_async: SIM::reload / SIM::save run in a worker thread
        if route.kind == "raw":
            fut = await self.service.write_async(route.index_group, route.index_offset, payload)
            await self._applied(fut)
            query.reply(key, payload, encoding=OCTET)
        elif route.kind == "named":
            assert route.obj is not None
            value = route.obj.coerce(_json_value(payload, route.obj))
            fut = await self.service.write_name_async(route.obj.name, route.axis, value)
            await self._applied(fut)
            query.reply(key, json.dumps(value).encode(), encoding=JSON)
        elif route.kind in ("reload", "save"):
            fn = self.service.reload if route.kind == "reload" else self.service.save
            result = await asyncio.get_running_loop().run_in_executor(None, fn)
            if not result.ok:
                body = {
                    "ads_error": ADSERR_DEVICE_SYNTAX,
                    "name": route.kind,
                    "message": "; ".join(result.errors),
                    **result.as_dict(),
                }
                query.reply_err(json.dumps(body).encode(), encoding=JSON)
                return
            query.reply(key, json.dumps(result.as_dict()).encode(), encoding=JSON)
        elif route.kind == "nc":
            result = await self._run_nc(payload)
            query.reply(key, json.dumps(result).encode(), encoding=JSON)
        elif route.kind == "reset":
            await self._applied(self.service.reset())
            body = {"ok": True, "command": "reset", "cycle": self.service.snapshot.cycle}
            query.reply(key, json.dumps(body).encode(), encoding=JSON)
        else:
            raise AdsError(AdsErrorCode.INVALID_ACCESS, f"{key} cannot be written")

    async def _run_nc(self, payload: bytes) -> dict[str, Any]:
        try:
            text = payload.decode("utf-8")
        except UnicodeDecodeError:
            raise AdsError(ADSERR_DEVICE_SYNTAX, "NC text must be UTF-8") from None
        await self._applied(self.service.run_nc(text))
        return {"ok": True, "lines": text.count("\n") + 1, "cycle": self.service.snapshot.cycle}

    async def _applied(self, fut: Any) -> None:
        """Wait until a queued write has been applied (real-time and free-running modes).

        In stepped mode nobody runs the next cycle until the test steps, so the write is
        acknowledged as soon as it is validated and queued.
        """
        if fut.done():
            fut.result()
            return
        if self.service.scheduler.running:
            try:
                await asyncio.wait_for(asyncio.wrap_future(fut), WRITE_TIMEOUT_S)
            except TimeoutError:
                # Like the ADS interface (0x719 DEVICE_TIMEOUT), not an anonymous 0x700
                # "internal error: " (found by tests/test_robust_fuzz.py).
                raise AdsError(
                    ADSERR_TIMEOUT, f"write not applied within {WRITE_TIMEOUT_S} s"
                ) from None

    # ------------------------------------------------------------------ publications

    async def _publish_loop(self) -> None:
        """Put changed named values at most every `publish_period` (SPEC §7).

        Changes are found with one array comparison against the last published
        snapshot, so an idle machine costs almost nothing (the GEO cycle thread shares
        the GIL with this loop).
        """
        routes = self.keys.named_routes()
        lay = self.service.snapshot.layout
        slot = {a: i for i, a in enumerate(self.service.axes)}
        axis_keys: dict[tuple[int, int], str] = {}
        machine_keys: dict[int, str] = {}
        for key, route in routes.items():
            assert route.obj is not None
            if route.obj.scope == "machine":
                machine_keys[lay.machine_index[route.obj.name]] = key
            else:
                axis_keys[(slot[route.axis], lay.column[route.obj.name])] = key
        objs = {key: (zenoh.KeyExpr(key), route) for key, route in routes.items()}
        last: Snapshot | None = None
        while True:
            snap = self.service.snapshot
            if self._session is not None and (last is None or snap.cycle != last.cycle):
                if last is None:
                    changed = list(objs)
                else:
                    rows, cols = np.nonzero(snap.values != last.values)
                    changed = [
                        axis_keys[(r, c)]
                        for r, c in zip(rows.tolist(), cols.tolist(), strict=True)
                        if (r, c) in axis_keys
                    ]
                    changed += [
                        machine_keys[i]
                        for i in np.nonzero(snap.machine != last.machine)[0].tolist()
                        if i in machine_keys
                    ]
                for key in changed:
                    kexpr, route = objs[key]
                    assert route.obj is not None
                    value = snap.value(route.obj, route.axis)
                    self._session.put(kexpr, json.dumps(value).encode(), encoding=JSON)
                last = snap
            await asyncio.sleep(self.options.publish_period)

    async def _status_loop(self) -> None:
        while True:
            if self._session is not None:
                self._session.put(
                    self._status_ke, json.dumps(self.service.status()).encode(), encoding=JSON
                )
            await asyncio.sleep(self.options.status_period)

    def _on_event(self, event: Event) -> None:
        """Cycle thread: hand a new warning/error to the loop for publication."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            # The loop may close between the check and the hand-off; the event is still
            # in `errors` for a later get, so dropping its publication is harmless, while
            # a RuntimeError here would fail the cycle (or command) that raised the event.
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._put_event, event)

    def _put_event(self, event: Event) -> None:
        if self._session is not None:
            self._session.put(self._errors_ke, json.dumps(event.as_dict()).encode(), encoding=JSON)


_MISSING = object()


def load_config_file(path: str | Path) -> str:
    """Validate that a Zenoh JSON5 config file can be read (clear error at start-up)."""
    zenoh.Config.from_file(str(path))
    return str(path)
