"""The web HMI's server (docs/web.md): aiohttp on the server's asyncio loop, the same
object service as every transport.

    GET  /                      the page (static files shipped in the package)
    GET  /ws                    WebSocket: `hello` on connect, then `live` 10 times a
                                second, `status` every second, `error` as they happen,
                                `tables` after a reload
    GET  /api/tables            every compensation table in engineering units
    GET  /api/state             the `hello` message (machine, axes, trends, errors)
    POST /api/write             {"name", "axis", "value"}: a writable TEMPC object
    POST /api/command/{reload,save}

A fleet (`FleetHmi`): `GET /` the fleet's page, `GET /api/fleet` its status, and each
machine's endpoints above under `/m/<name>/`.

One task samples the machine (`service.current()`: one snapshot per sample) into the
trend ring and sends the same JSON text to every socket: every 100 ms while a page is
open, once a second for the trends while none is.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from geo_server import __version__
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.model import MachineConfig
from geo_server.service import ObjectService
from geo_server.web.tables import tables
from geo_server.web.views import (
    COMPENSATIONS,
    TRENDS,
    LiveView,
    Trends,
    object_info,
    writable_tempc,
)

log = logging.getLogger(__name__)
#: errno of a port in use: Linux, macOS, Windows
_IN_USE = (errno.EADDRINUSE, 48, 98, 10048)
STATIC = Path(__file__).resolve().parent / "static"


@dataclass
class HmiOptions:
    """Where the web HMI listens and how often it samples."""

    host: str = "127.0.0.1"
    port: int = 8080
    machine: str = "local"
    #: seconds between pushes (and trend samples) while a page is open
    period: float = 0.1
    #: seconds between trend samples while no page is open (0: none at all)
    idle_period: float = 1.0
    #: seconds of trend kept for a page opened later
    trend_seconds: float = 600.0
    #: the machine is one of a fleet (its page links back to the fleet's)
    fleet: bool = False
    #: `geo-server run --read-only`: edits, reload and save refused (0x704)
    read_only: bool = False


def parse_http(text: str) -> tuple[str, int]:
    """`--http HOST:PORT` (or just `PORT`) -> (host, port); ValueError says why not."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "127.0.0.1", text
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    return host.strip("[]") or "127.0.0.1", int(port)


class HmiServer:
    """Serve the web HMI of one machine."""

    def __init__(self, service: ObjectService, options: HmiOptions | None = None) -> None:
        self.service = service
        self.options = options or HmiOptions()
        d = service.dictionary
        self.tempc = [object_info(o) for o in writable_tempc(d)]
        self._writable = {o.name for o in writable_tempc(d)}
        self.sockets: set[web.WebSocketResponse] = set()
        self._runner: web.AppRunner | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._unsubscribe: Callable[[], None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        #: set while a page is open (wakes the sampling at once when one opens)
        self._watched = asyncio.Event()
        self._cfg: MachineConfig = service.machine.cfg
        self._tables_json = ""
        self.view = LiveView(d, self._cfg, service.axes)
        self.trends = self._new_trends()
        #: pushes sent (samples taken while a page was open)
        self.pushes = 0
        #: trend samples taken, pushed or not
        self.samples = 0
        self.address = ""

    def _new_trends(self) -> Trends:
        series = len(self.service.axes) * len(self.view.trend_fields)
        return Trends(series, self.options.trend_seconds, 1 / self.options.period)

    # ------------------------------------------------------------------ lifecycle

    def routes(self) -> list[web.RouteDef]:
        """The machine's page and API, relative to where it is served: the root for one
        machine, `/m/<name>/` for a machine of a fleet (`FleetHmi`)."""
        return [
            web.get("/", self._index),
            web.get("/ws", self._ws),
            web.get("/api/tables", self._tables),
            web.get("/api/state", self._state),
            web.post("/api/write", self._write),
            web.post("/api/command/{name}", self._command),
        ]

    async def start(self) -> None:
        """Bind the port and start sampling."""
        app = web.Application()
        app.add_routes([*self.routes(), *common_routes()])
        self._runner, self.address = await bind(app, self.options)
        await self.start_sampling()

    async def start_sampling(self) -> None:
        """Sample the machine and push to the sockets (also when served by a `FleetHmi`)."""
        self._loop = asyncio.get_running_loop()
        self._unsubscribe = self.service.subscribe_events(self._on_event)
        self._spawn(self._push_loop())
        self._spawn(self._status_loop())

    async def close(self) -> None:
        """Stop sampling, close every socket and the listener."""
        await self.stop_sampling()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def stop_sampling(self) -> None:
        """Stop sampling and close every socket."""
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for ws in list(self.sockets):
            await ws.close()

    @property
    def port(self) -> int:
        """The bound TCP port (useful with `port=0`)."""
        return port_of(self.address)

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ pushing

    def hello(self) -> dict[str, Any]:
        """The first message of a socket: what the page is built from."""
        svc = self.service
        cfg = svc.machine.cfg
        return {
            "type": "hello",
            "version": __version__,
            "machine": self.options.machine,
            "fleet": self.options.fleet,
            "read_only": self.options.read_only,
            "period": self.options.period,
            "twin": self.view.has_twin,
            "axes": [
                {
                    "axis": a,
                    "name": cfg.axes[a].params.name,
                    "rotary": cfg.axes[a].params.kind != "T",
                }
                for a in svc.axes
            ],
            "comps": [{"key": c.key, "title": c.title} for c in COMPENSATIONS],
            "tempc": self.tempc,
            "trend_fields": [
                {
                    "field": f,
                    "title": TRENDS[f][0],
                    "unit": TRENDS[f][1],
                    "rotary_unit": TRENDS[f][2],
                }
                for f in self.view.trend_fields
            ],
            "trends": self.trends.as_json(),
            "errors": svc.errors(),
            "status": svc.status(),
        }

    def sample(self, push: bool = True) -> str:
        """One sample: the snapshot due now into the trends, as the JSON text of a
        `live` message (a `stalled` one while the GEO cycle is); without `push` (no
        page open) the trends only, and no message ("")."""
        try:
            snap = self.service.current()
        except AdsError as exc:
            stalled = {"type": "stalled", "code": exc.code, "message": exc.message}
            return json.dumps(stalled) if push else ""
        t = time.time()
        self.trends.add(round(t, 3), self.view.trend_sample(snap))
        self.samples += 1
        return json.dumps(self.view.push(snap, t)) if push else ""

    def _reconfigured(self) -> bool:
        """After a reload (from any interface) the tables and units may have changed."""
        cfg = self.service.machine.cfg
        if cfg is self._cfg:
            return False
        self._cfg, self._tables_json = cfg, ""
        fields = self.view.trend_fields
        self.view = LiveView(self.service.dictionary, cfg, self.service.axes)
        if self.view.trend_fields != fields:  # a twin came or went
            self.trends = self._new_trends()
        return True

    async def _wait(self) -> None:
        """Until the next sample: `period` while a page is open; else `idle_period`
        (forever with 0), cut short when a page opens."""
        if self.sockets:
            await asyncio.sleep(self.options.period)
            return
        self._watched.clear()
        idle = self.options.idle_period
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._watched.wait(), idle if idle > 0 else None)

    async def _push_loop(self) -> None:
        while True:
            await self._wait()
            try:
                if self._reconfigured() and self.sockets:
                    await self._broadcast(json.dumps({"type": "tables"}))
                text = self.sample(push=bool(self.sockets))
            except Exception:  # never let one bad sample end the pushes
                log.exception("web HMI: sample failed")
                continue
            if text and self.sockets:
                self.pushes += 1
                await self._broadcast(text)

    async def _status_loop(self) -> None:
        while True:
            await self._watched.wait()
            await asyncio.sleep(1.0)
            if self.sockets:
                await self._broadcast(
                    json.dumps({"type": "status", "status": self.service.status()})
                )

    async def _broadcast(self, text: str) -> None:
        for ws in list(self.sockets):
            if ws.closed:
                self.sockets.discard(ws)
                continue
            with contextlib.suppress(ConnectionError, RuntimeError):
                await ws.send_str(text)

    def _on_event(self, event: Event) -> None:
        """The cycle's thread: hand the event to the loop and return."""
        loop = self._loop
        if loop is None or loop.is_closed() or not self.sockets:
            return
        text = json.dumps({"type": "error", "error": event.as_dict()})
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
            loop.call_soon_threadsafe(self._send_event, text)

    def _send_event(self, text: str) -> None:
        self._spawn(self._broadcast(text))

    # ------------------------------------------------------------------ handlers

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _ws(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=20)
        await ws.prepare(request)
        await ws.send_str(json.dumps(self.hello()))
        self.sockets.add(ws)
        self._watched.set()
        try:
            async for msg in ws:  # the page sends nothing; this waits for the close
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.sockets.discard(ws)
        return ws

    async def _tables(self, request: web.Request) -> web.Response:
        self._reconfigured()
        if not self._tables_json:  # once per configuration, off the loop (tens of ms)
            cfg = self._cfg
            text = await asyncio.to_thread(_tables_json, cfg, self.service.axes)
            if cfg is self._cfg:
                self._tables_json = text
            return web.Response(text=text, content_type="application/json")
        return web.Response(text=self._tables_json, content_type="application/json")

    async def _state(self, request: web.Request) -> web.Response:
        return web.json_response(self.hello())

    async def _write(self, request: web.Request) -> web.Response:
        """A TEMPC edit: the object service's write path, range checks and messages."""
        if self.options.read_only:
            return _refused(READ_ONLY)
        try:
            body = await request.json()
            name, axis, value = str(body["name"]), int(body["axis"]), body["value"]
        except (ValueError, KeyError, TypeError):
            return _refused(
                AdsError(
                    AdsErrorCode.DEVICE_INVALIDPARM,
                    'expected JSON {"name": …, "axis": …, "value": …}',
                )
            )
        try:
            obj = self.service.lookup(name, axis)
            if obj.name not in self._writable:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDACCESS,
                    f"{obj.name} is not a writable TEMPC parameter",
                    obj.name,
                )
            stored = await self.service.write_name_applied(obj.name, axis, value)
        except AdsError as exc:
            return _refused(exc)
        return web.json_response({"ok": True, "name": obj.name, "axis": axis, "value": stored})

    async def _command(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if self.options.read_only:
            return _refused(READ_ONLY)
        if name not in ("reload", "save"):
            return _refused(AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"unknown command {name!r}"))
        result = await self.service.command(name)
        body = result.as_dict()
        if not result.ok:
            body = {**result.error().as_dict(), **body}
            return web.json_response(body, status=400)
        return web.json_response(body)


def common_routes() -> list[web.AbstractRouteDef]:
    """What every page shares: the static files and the icon, at the root."""
    return [web.get("/favicon.ico", _favicon), web.static("/static", STATIC)]


async def _favicon(request: web.Request) -> web.StreamResponse:
    return web.FileResponse(STATIC / "favicon.svg", headers={"Content-Type": "image/svg+xml"})


async def bind(app: web.Application, options: HmiOptions) -> tuple[web.AppRunner, str]:
    """Serve `app` on the options' host and port: the runner and the bound address
    (a taken port: RuntimeError with the one-line reason `geo-server run` prints)."""
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    host, port = options.host, options.port
    try:
        await web.TCPSite(runner, host, port).start()
    except OSError as exc:
        await runner.cleanup()
        if exc.errno not in _IN_USE:
            raise
        # said here in full: geo_server.interfaces knows no option for this port
        raise RuntimeError(
            f"{host}:{port} is taken (another geo-server?); choose another "
            "--http HOST:PORT or stop the other server"
        ) from exc
    except BaseException:  # cancelled while starting: nothing left listening
        await runner.cleanup()
        raise
    host, port = runner.addresses[0][:2]
    return runner, f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def port_of(address: str) -> int:
    """The port of a bound address `bind` returned (0 before it is bound)."""
    return int(address.rpartition(":")[2]) if address else 0


class FleetHmi:
    """The web HMI of a fleet (docs/web.md §3): `/` lists every machine (name, cycle,
    engine, overruns, stalled, NetId, Modbus port; `GET /api/fleet` as JSON) and
    `/m/<name>/` is that machine's page, the same page and API as for one machine."""

    def __init__(
        self,
        services: dict[str, ObjectService],
        fleet_status: Callable[[], dict[str, Any]],
        options: HmiOptions | None = None,
    ) -> None:
        self.options = options or HmiOptions()
        self.pages = {
            name: HmiServer(svc, replace(self.options, machine=name, fleet=True))
            for name, svc in services.items()
        }
        self._fleet_status = fleet_status
        self._runner: web.AppRunner | None = None
        self.address = ""

    async def start(self) -> None:
        """Bind the port and start every machine's sampling."""
        # /m/<name> -> /m/<name>/: the page's relative addresses need the slash
        app = web.Application(middlewares=[web.normalize_path_middleware(append_slash=True)])
        app.add_routes(
            [web.get("/", self._index), web.get("/api/fleet", self._fleet), *common_routes()]
        )
        for name, page in self.pages.items():
            sub = web.Application()
            sub.add_routes(page.routes())
            app.add_subapp(f"/m/{name}", sub)
        app.router.add_route("*", "/m/{name}/{rest:.*}", self._unknown)
        self._runner, self.address = await bind(app, self.options)
        for page in self.pages.values():
            await page.start_sampling()

    async def close(self) -> None:
        for page in self.pages.values():
            await page.stop_sampling()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    @property
    def port(self) -> int:
        return port_of(self.address)

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "fleet.html")

    async def _fleet(self, request: web.Request) -> web.Response:
        return web.json_response(self._fleet_status())

    async def _unknown(self, request: web.Request) -> web.StreamResponse:
        names = ", ".join(self.pages)
        raise web.HTTPNotFound(
            text=f"no machine {request.match_info['name']!r} in this fleet (machines: {names})"
        )


def _tables_json(cfg: MachineConfig, axes: tuple[int, ...]) -> str:
    return json.dumps(tables(cfg, axes))


def _trend_field(field: str) -> dict[str, str]:
    title, unit, rotary_unit = TRENDS[field]
    return {"field": field, "title": title, "unit": unit, "rotary_unit": rotary_unit}


#: what a read-only server (`geo-server run --read-only`) answers an edit or a command
READ_ONLY = AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, "this interface is read-only")


def _refused(exc: AdsError) -> web.Response:
    return web.json_response(
        {"ok": False, "code": exc.code, "message": exc.message, "name": exc.name}, status=400
    )
