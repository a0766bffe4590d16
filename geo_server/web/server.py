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

Every request passes `guard.Guard` first (Host, Origin, JSON bodies, the run's token;
docs/web.md §4); a page may not send on its WebSocket, and a machine has at most
`max_pages` of them open.

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
import re
import secrets
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from aiohttp import WSCloseCode, WSMsgType, web

from geo_server import __version__, access
from geo_server.aio import wait_set
from geo_server.dictionary import MAX_AXIS, loads_json
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.model import MachineConfig
from geo_server.service import ObjectService
from geo_server.transports.tcp import BACKLOG, Gate, Listener
from geo_server.web.guard import Guard, refusal
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
    #: `geo-server run --read-only` / `--http-read-only`: edits, reload and save refused
    #: (0x704), the page's edits disabled
    read_only: bool = False
    #: Host header values accepted besides the bound address and its loopback names
    #: (`--http-allowed-hosts`; `name:port`, or `name` for the bound port and for a
    #: proxy that forwards the name alone); any other Host is refused (421)
    allowed_hosts: tuple[str, ...] = ()
    #: The secret every write, reload and save carries (`X-Geo-Token`; `--http-token`);
    #: "" draws a new one (`secrets`) each run, printed in the page's URL at start
    token: str = ""
    #: HTTP Basic authentication on every request when set (`--http-user/--http-password`)
    user: str = ""
    password: str = ""
    #: Open pages (WebSockets) of one machine; one more is refused (503). Each costs a
    #: send of the shared push text 10 times a second on the loop every interface shares
    max_pages: int = 32
    #: Largest WebSocket message a page may send, in bytes; the page sends none, so any
    #: message closes its socket (1008), a larger one at its header, unread (1009)
    ws_max_message: int = 1024
    #: Pings a WebSocket peer may send in a burst, refilled at one a second; beyond
    #: them its socket is closed (1008). (Browsers send none.)
    ws_ping_burst: int = 10
    #: Bytes a page may leave unread before it is dropped (an asyncio transport's
    #: high-water mark): a page that stops reading is closed, never waited for
    ws_backlog: int = 64 * 1024
    #: Seconds one push to one page may take before that page is dropped
    ws_send_timeout: float = 1.0
    #: Largest request body, in bytes (413 past it): a write is under 200 bytes
    max_body: int = 64 * 1024
    #: Simultaneous HTTP connections (open pages' WebSockets included); one beyond is
    #: closed at once, before aiohttp sees it (`bind`). Shrunk at start when the
    #: descriptor limit is low (geo_server/descriptors.py).
    max_connections: int = 64
    #: Seconds a connection may stay without a complete request head: from its opening
    #: and after each answer (aiohttp's keep-alive timeout, 3630 s by default, also
    #: closes a connection still waiting for its head). A slow client cannot hold one.
    keepalive_timeout: float = 5.0
    #: Seconds a request's body may take to arrive (408 past it).
    body_timeout: float = 10.0
    #: Request head bounds: one request or header line, header count (431/400 past them).
    max_line_size: int = 8190
    max_headers: int = 32


def parse_http(text: str) -> tuple[str, int]:
    """`--http HOST:PORT` (or just `PORT`) -> (host, port); ValueError says why not."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "127.0.0.1", text
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    return host.strip("[]") or "127.0.0.1", int(port)


#: What a token given with `--http-token` may be made of: it travels in a URL and a header.
_TOKEN = re.compile(r"[A-Za-z0-9._~-]{1,256}")


def http_options(args: Any, **more: Any) -> HmiOptions:
    """`HmiOptions` from `geo-server run`'s `--http…` options, for one machine and a
    fleet alike (ValueError says what is wrong with them)."""
    host, port = parse_http(args.http)
    token = args.http_token or ""
    if token and not _TOKEN.fullmatch(token):
        raise ValueError("--http-token: 1 to 256 letters, digits and . _ ~ -")
    if bool(args.http_user) != bool(args.http_password):
        raise ValueError("--http-user and --http-password go together")
    hosts = tuple(h.strip() for item in args.http_allowed_hosts or () for h in item.split(","))
    return HmiOptions(
        host=host,
        port=port,
        read_only=bool(args.read_only or args.http_read_only),
        allowed_hosts=tuple(h for h in hosts if h),
        token=token,
        user=args.http_user or "",
        password=args.http_password or "",
        **more,
    )


def access_note(options: HmiOptions) -> str:
    """What `geo-server run` says after the page's URL: who may do what."""
    note = "read-only" if options.read_only else "edits need the token in this URL"
    return note + (f"; HTTP Basic user {options.user!r}" if options.user else "")


def _with_token(options: HmiOptions) -> HmiOptions:
    """The options with this run's token: the one given, else a new random one."""
    return options if options.token else replace(options, token=secrets.token_urlsafe(24))


def _guard(options: HmiOptions) -> Guard:
    return Guard(
        options.token, options.allowed_hosts, options.user, options.password, options.max_body
    )


class HmiServer:
    """Serve the web HMI of one machine."""

    def __init__(self, service: ObjectService, options: HmiOptions | None = None) -> None:
        self.service = service
        self.options = _with_token(options or HmiOptions())
        self.guard = _guard(self.options)
        d = service.info.dictionary
        self.tempc = [object_info(o) for o in writable_tempc(d)]
        self._writable = {o.name for o in writable_tempc(d)}
        #: open pages: each socket with its transport (to drop a page that stops reading)
        self.sockets: dict[web.WebSocketResponse, asyncio.Transport] = {}
        #: sockets being opened or open (the `max_pages` count)
        self._pages = 0
        self._runner: web.AppRunner | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._unsubscribe: Callable[[], None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        #: set while a page is open (wakes the sampling at once when one opens)
        self._watched = asyncio.Event()
        self._cfg: MachineConfig = service.info.config
        self._tables_json = ""
        self.view = LiveView(d, self._cfg, service.info.axes)
        self.trends = self._new_trends()
        #: pushes sent (samples taken while a page was open)
        self.pushes = 0
        #: trend samples taken, pushed or not
        self.samples = 0
        self.address = ""

    def _new_trends(self) -> Trends:
        series = len(self.service.info.axes) * len(self.view.trend_fields)
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
        app = web.Application(
            middlewares=[self.guard.middleware], client_max_size=self.options.max_body
        )
        app.add_routes([*self.routes(), *common_routes()])
        self._runner, self.address = await bind(app, self.options)
        self.guard.bind_to(self.address)
        await self.start_sampling()

    @property
    def url(self) -> str:
        """The page's address with the run's token, as `geo-server run` prints it."""
        return f"http://{self.address}/?token={self.options.token}"

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
        cfg = svc.info.config
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
                for a in svc.info.axes
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
        cfg = self.service.info.config
        if cfg is self._cfg:
            return False
        self._cfg, self._tables_json = cfg, ""
        fields = self.view.trend_fields
        self.view = LiveView(self.service.info.dictionary, cfg, self.service.info.axes)
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
        await wait_set(self._watched, idle if idle > 0 else None)

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
        """The same text to every page; a page that does not read is dropped, not
        waited for (its unsent data past `ws_backlog`, or a send that takes longer than
        `ws_send_timeout`), so it cannot hold the pushes of the others."""
        for ws, transport in list(self.sockets.items()):
            if ws.closed or transport.get_write_buffer_size() > self.options.ws_backlog:
                self._drop(ws, transport)
                continue
            try:
                async with asyncio.timeout(self.options.ws_send_timeout):
                    await ws.send_str(text)
            except TimeoutError:
                self._drop(ws, transport)
            except (ConnectionError, RuntimeError):
                pass

    def _drop(self, ws: web.WebSocketResponse, transport: asyncio.Transport) -> None:
        self.sockets.pop(ws, None)
        transport.abort()

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

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        """A page's socket: at most `max_pages` per machine (503 beyond). The page sends
        nothing: a message closes the socket (1008; one over `ws_max_message` bytes at
        its header, unread: 1009), and so do pings beyond `ws_ping_burst`. Pushes are
        not compressed: one JSON text is sent as is to every page."""
        if self._pages >= self.options.max_pages:
            return refusal(
                503,
                f"{self._pages} pages of this machine are open, the most it serves "
                "(HmiOptions.max_pages); close one",
            )
        self._pages += 1
        ws = web.WebSocketResponse(
            heartbeat=20,
            autoping=False,  # pings counted here (`_PingBudget`)
            compress=False,
            max_msg_size=self.options.ws_max_message,
        )
        try:
            await ws.prepare(request)
            transport = request.transport
            if not isinstance(transport, asyncio.Transport):  # closed while opening
                return ws
            await ws.send_str(json.dumps(self.hello()))
            self.sockets[ws] = transport
            self._watched.set()
            pings = _PingBudget(self.options.ws_ping_burst)
            async for msg in ws:  # until the close
                if msg.type == WSMsgType.PING and pings.take():
                    await ws.pong(msg.data)
                elif msg.type == WSMsgType.PONG:  # the heartbeat's answer
                    continue
                else:  # a message, too many pings or an error: this peer is not the page
                    why = b"too many pings" if msg.type == WSMsgType.PING else b"send nothing"
                    await ws.close(code=WSCloseCode.POLICY_VIOLATION, message=why)
                    break
        finally:
            self._pages -= 1
            self.sockets.pop(ws, None)
        return ws

    async def _tables(self, request: web.Request) -> web.Response:
        self._reconfigured()
        if not self._tables_json:  # once per configuration, off the loop (tens of ms)
            cfg = self._cfg
            text = await asyncio.to_thread(_tables_json, cfg, self.service.info.axes)
            if cfg is self._cfg:
                self._tables_json = text
            return web.Response(text=text, content_type="application/json")
        return web.Response(text=self._tables_json, content_type="application/json")

    async def _state(self, request: web.Request) -> web.Response:
        return web.json_response(self.hello())

    async def _write(self, request: web.Request) -> web.Response:
        """A TEMPC edit: the object service's write path, range checks and messages.
        The body is read as Zenoh reads a payload (`loads_json`) and the value checked
        by the same strict rule (`ObjectDef.coerce_json`): `"4100"` or `true` for a
        REAL64 is refused (0x706), as is malformed JSON; a body of another shape 0x70B."""
        if self.options.read_only:
            return _refused(READ_ONLY)
        try:
            name, axis, value = _write_body(loads_json(await request.read(), "the body"))
            obj = self.service.lookup(name, axis)
            if obj.name not in self._writable:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDACCESS,
                    f"{obj.name} is not a writable TEMPC parameter",
                    obj.name,
                )
            value = obj.coerce_json(value)
            stored = await access.write_name_applied(self.service, obj.name, axis, value)
        except AdsError as exc:
            return _refused(exc)
        return web.json_response({"ok": True, "name": obj.name, "axis": axis, "value": stored})

    async def _command(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if self.options.read_only:
            return _refused(READ_ONLY)
        if name not in ("reload", "save"):
            return _refused(AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"unknown command {name!r}"))
        result = await self.service.commands.run_applied(name)
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
    (a taken port: RuntimeError with the one-line reason `geo-server run` prints).

    Connections are bounded as on every interface (docs/security.md): at most
    `max_connections` (`_CappedSite`), each closed when its request head is not complete
    `keepalive_timeout` seconds after it opened or after its last answer, a body that
    takes longer than `body_timeout` answered 408, and bounded request heads."""
    app.middlewares.append(_body_deadline(options.body_timeout))
    runner = web.AppRunner(
        app,
        access_log=None,
        keepalive_timeout=options.keepalive_timeout,
        max_line_size=options.max_line_size,
        max_field_size=options.max_line_size,
        max_headers=options.max_headers,
        lingering_time=min(options.body_timeout, 2.0),
    )
    await runner.setup()
    host, port = options.host, options.port
    try:
        await _CappedSite(runner, host, port, options.max_connections).start()
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


class _CappedSite(web.BaseSite):
    """aiohttp's TCP site with a connection cap: aiohttp has none, so each accepted
    connection goes through a `Gate` that closes it past `max_connections` before
    aiohttp's handler exists (the same `Listener` bookkeeping as ADS and Modbus)."""

    def __init__(self, runner: web.BaseRunner, host: str, port: int, cap: int) -> None:
        super().__init__(runner, backlog=BACKLOG)
        self._host, self._port = host, port
        self.listener = Listener(host, port, cap)

    @property
    def name(self) -> str:
        return f"http://{self._host}:{self._port}"

    async def start(self) -> None:
        await super().start()
        server = self._runner.server
        assert server is not None  # the runner was set up
        self._server = await asyncio.get_running_loop().create_server(
            lambda: Gate(self.listener, server), self._host, self._port, backlog=BACKLOG
        )


def _body_deadline(seconds: float) -> Any:
    """Middleware: a request's body is read within `seconds` (408 past it) before its
    handler runs; the handler then reads it from memory."""

    @web.middleware
    async def deadline(
        request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if request.body_exists and not request.headers.get("Upgrade"):
            try:
                async with asyncio.timeout(seconds):
                    await request.read()
            except TimeoutError:
                raise web.HTTPRequestTimeout(
                    text=f"the request body did not arrive within {seconds:g} s"
                ) from None
        return await handler(request)

    return deadline


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
        self.options = _with_token(options or HmiOptions())  # one token for every machine
        self.guard = _guard(self.options)
        self.pages = {
            name: HmiServer(svc, replace(self.options, machine=name, fleet=True))
            for name, svc in services.items()
        }
        self._fleet_status = fleet_status
        self._runner: web.AppRunner | None = None
        self.address = ""

    async def start(self) -> None:
        """Bind the port and start every machine's sampling."""
        # /m/<name> -> /m/<name>/: the page's relative addresses need the slash. The
        # guard is the parent application's: it runs for every machine's routes too.
        app = web.Application(
            middlewares=[self.guard.middleware, web.normalize_path_middleware(append_slash=True)],
            client_max_size=self.options.max_body,
        )
        app.add_routes(
            [web.get("/", self._index), web.get("/api/fleet", self._fleet), *common_routes()]
        )
        for name, page in self.pages.items():
            sub = web.Application()
            sub.add_routes(page.routes())
            app.add_subapp(f"/m/{name}", sub)
        app.router.add_route("*", "/m/{name}/{rest:.*}", self._unknown)
        self._runner, self.address = await bind(app, self.options)
        self.guard.bind_to(self.address)
        for page in self.pages.values():
            await page.start_sampling()

    @property
    def url(self) -> str:
        """The fleet page's address with the run's token, as `geo-server run` prints it."""
        return f"http://{self.address}/?token={self.options.token}"

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


def _write_body(body: Any) -> tuple[str, int, Any]:
    """`{"name": str, "axis": int, "value": …}` of `POST /api/write`, nothing else (0x70B)."""
    if not isinstance(body, dict) or set(body) != {"name", "axis", "value"}:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDPARM, 'expected JSON {"name": …, "axis": …, "value": …}'
        )
    name, axis = body["name"], body["axis"]
    if not isinstance(name, str):
        raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, '"name" must be a string')
    if isinstance(axis, bool) or not isinstance(axis, int) or not 0 <= axis <= MAX_AXIS:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, f'"axis" must be an integer 0 … {MAX_AXIS}')
    return name, axis, body["value"]


class _PingBudget:
    """`burst` pings at once, one more per second after that (a token bucket)."""

    def __init__(self, burst: int) -> None:
        self.burst = float(burst)
        self.left = float(burst)
        self.last = time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.left = min(self.burst, self.left + (now - self.last))
        self.last = now
        if self.left < 1:
            return False
        self.left -= 1
        return True


def _refused(exc: AdsError) -> web.Response:
    return web.json_response(
        {"ok": False, "code": exc.code, "message": exc.message, "name": exc.name}, status=400
    )
