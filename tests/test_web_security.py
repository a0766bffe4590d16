"""The web HMI attacked as a hostile web page, a DNS-rebinding page and a flooding client
would (issue 30; docs/web.md §4): over real sockets on 127.0.0.1, against a real-time
machine (exact engine) served in this process, with aiohttp's client and raw sockets.

Each attack is refused with an HTTP 4xx/5xx and a message, the machine is unchanged
(TEMPC and the list files), and the server keeps serving the page's own requests."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import re
import socket
import subprocess
import threading
from pathlib import Path

import aiohttp
import pytest
from conftest import RUN_HTTP_ONLY

import geo_server.dictionary as dictionary_module
from geo_server import access
from geo_server.cli import build_parser, main
from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService
from geo_server.web.guard import TOKEN_HEADER, Guard
from geo_server.web.server import FleetHmi, HmiOptions, HmiServer, http_options

EVIL = "http://evil.example"
COEFF = "TEMPC::coefficient"
#: lists/achsmd1.lis: temp_comp_coefficient of axis 1
LIST_COEFF = 4000.0


class Served:
    """A real-time machine (or two, as a fleet) with the web HMI on an ephemeral port."""

    def __init__(self, startup: Path, options: HmiOptions, fleet: bool = False) -> None:
        names = ("mill-a", "lathe-b") if fleet else ("local",)
        self.services: dict[str, ObjectService] = {}
        self.schedulers = []
        for name in names:
            machine = Machine(load_machine(startup), homed=True)
            sched = Scheduler(machine, mode="realtime", engine="exact")
            self.services[name] = ObjectService(machine, sched)
            self.schedulers.append(sched)
        self.service = next(iter(self.services.values()))
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.hmi: HmiServer | FleetHmi
        if fleet:
            self.hmi = FleetHmi(self.services, lambda: {"count": len(names)}, options)
        else:
            self.hmi = HmiServer(self.service, options)
        self.run(self.hmi.start())
        for sched in self.schedulers:
            sched.start()
        self.base = f"http://{self.hmi.address}/"
        self.token = self.hmi.options.token
        self.lists = startup.parent

    def run(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(30)

    def on_loop(self, fn):
        """`fn()` on the server's loop (its state is the loop's)."""

        async def call():
            return fn()

        return self.run(call())

    def close(self) -> None:
        self.run(self.hmi.close())
        for sched in self.schedulers:
            sched.stop()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()

    def coefficient(self, name: str | None = None) -> float:
        svc = self.services[name] if name else self.service
        return float(access.read_name(svc, COEFF, 1))

    def list_bytes(self) -> dict[str, bytes]:
        return {p.name: p.read_bytes() for p in sorted(self.lists.glob("*.lis"))}

    def attack(self, fn):
        """Run `fn(session)` in a client loop of this thread (the server has its own)."""

        async def go():
            connector = aiohttp.TCPConnector(limit=0)
            async with aiohttp.ClientSession(connector=connector) as session:
                return await fn(session)

        return asyncio.run(go())

    def json_headers(self, token: str | None = None) -> dict[str, str]:
        return {
            "Content-Type": "application/json",
            TOKEN_HEADER: self.token if token is None else token,
        }


@pytest.fixture
def served(lists_copy):
    s = Served(lists_copy, HmiOptions(port=0, max_pages=3))
    yield s
    s.close()


@pytest.fixture
def fleet(lists_copy):
    s = Served(lists_copy, HmiOptions(port=0), fleet=True)
    yield s
    s.close()


def write_body(value, name: str = COEFF, axis=1) -> bytes:
    return json.dumps({"name": name, "axis": axis, "value": value}).encode()


async def answer(resp: aiohttp.ClientResponse) -> tuple[int, dict]:
    return resp.status, json.loads(await resp.read())


# ---------------------------------------------------------------------- Host (rebinding)

SINGLE_GETS = ("", "ws", "api/state", "api/tables", "static/hmi.js", "favicon.ico")
FLEET_GETS = (
    "",
    "api/fleet",
    "static/fleet.js",
    "m/mill-a",
    "m/mill-a/",
    "m/mill-a/ws",
    "m/mill-a/api/state",
    "m/lathe-b/api/tables",
    "m/nope/",
)


def _foreign_host_refused(served: Served, paths: tuple[str, ...]) -> None:
    async def go(session):
        out = {}
        for path in paths:
            headers = {"Host": f"evil.example:{served.hmi.port}"}
            if path.endswith("ws"):  # a WebSocket upgrade, as the page's script opens it
                headers |= {"Upgrade": "websocket", "Connection": "Upgrade"}
                headers |= {
                    "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
                    "Sec-WebSocket-Version": "13",
                }
            async with session.get(served.base + path, headers=headers, allow_redirects=False) as r:
                out[path] = await answer(r)
        return out

    for path, (status, body) in served.attack(go).items():
        assert status == 421, path
        assert body["message"].startswith(
            f"Host 'evil.example:{served.hmi.port}' is not an address"
        )


def test_a_foreign_host_reads_nothing(served):
    """A DNS-rebinding page (its own name in Host) gets none of the page, the state,
    the tables, the static files or a WebSocket."""
    _foreign_host_refused(served, SINGLE_GETS)
    assert served.on_loop(lambda: len(served.hmi.sockets)) == 0


def test_a_foreign_host_reads_nothing_of_a_fleet(fleet):
    _foreign_host_refused(fleet, FLEET_GETS)


def test_the_servers_own_names_are_answered(lists_copy):
    """The bound address, its loopback equivalents and `--http-allowed-hosts`."""
    s = Served(lists_copy, HmiOptions(port=0, allowed_hosts=("hmi.example", "other.example:81")))
    try:
        port = s.hmi.port
        good = [f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}", "hmi.example"]
        good += [f"HMI.example:{port}", "other.example:81"]
        bad = ["hmi.example:1", "other.example", f"127.0.0.2:{port}", "", f"evil.example:{port}"]

        async def go(session):
            out = {}
            for host in good + bad:
                async with session.get(s.base + "api/state", headers={"Host": host}) as r:
                    out[host] = r.status
            return out

        got = s.attack(go)
        assert got == {**{h: 200 for h in good}, **{h: 421 for h in bad}}
    finally:
        s.close()


def test_hosts_of_a_server_bound_to_every_address():
    """Bound to 0.0.0.0, any IP literal at the bound port is this server (a rebinding
    page has a name of its own); names only when listed."""
    g = Guard("t", ["hmi.example"])
    g.bind_to("0.0.0.0:8080")
    assert [g.host_ok(h) for h in ("192.168.1.5:8080", "[fe80::1]:8080", "hmi.example:8080")] == [
        True,
        True,
        True,
    ]
    assert [g.host_ok(h) for h in ("evil.example:8080", "192.168.1.5:80", "192.168.1.5")] == [
        False,
        False,
        False,
    ]


# ---------------------------------------------------------------------- a hostile page


def test_a_page_of_another_origin_cannot_write_save_or_reload(served):
    """Another origin's page POSTs to write, save and reload — as text/plain and as a
    form (no CORS preflight needed for those), and as JSON with the token (it cannot
    have it, but even then): 403 for its Origin. Without an Origin header (a client
    that leaves it out), text/plain and forms are still 415. TEMPC and the list files
    unchanged."""
    before = served.list_bytes()
    form = {"name": COEFF, "axis": "1", "value": "4100"}

    async def go(session):
        out = []
        for path in ("api/write", "api/command/save", "api/command/reload"):
            data = write_body(4100) if path == "api/write" else b"{}"
            for origin in (EVIL, None):
                extra = {"Origin": origin} if origin else {}
                h = served.json_headers() | extra
                if origin:
                    async with session.post(served.base + path, data=data, headers=h) as r:
                        out.append((path, origin, "json", *await answer(r)))
                h = {"Content-Type": "text/plain", TOKEN_HEADER: served.token} | extra
                async with session.post(served.base + path, data=data, headers=h) as r:
                    out.append((path, origin, "text/plain", *await answer(r)))
                h = {TOKEN_HEADER: served.token} | extra
                async with session.post(served.base + path, data=form, headers=h) as r:
                    out.append((path, origin, "form", *await answer(r)))
        return out

    got = served.attack(go)
    assert len(got) == 15
    for path, origin, how, status, body in got:
        if origin:
            assert (status, body["message"]) == (
                403,
                "requests from 'http://evil.example' are not accepted",
            ), (path, how)
        else:
            kind = "text/plain" if how == "text/plain" else "application/x-www-form-urlencoded"
            assert (status, body["message"]) == (
                415,
                f"the body must be application/json, not {kind!r}",
            ), (path, how)
    assert served.coefficient() == LIST_COEFF
    assert served.list_bytes() == before


def test_a_websocket_from_another_origin_is_refused(served):
    async def go(session):
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await session.ws_connect(served.base + "ws", origin=EVIL)
        own = f"http://{served.hmi.address}"
        async with session.ws_connect(served.base + "ws", origin=own) as ws:
            hello = json.loads((await ws.receive(timeout=10)).data)
        return refused.value.status, hello["type"]

    assert served.attack(go) == (403, "hello")


def test_writes_need_the_runs_token(served):
    """No token, a wrong one (also of the right length): 403 with a message; the right
    one: written. The token is drawn per run and never in what a page can read."""
    token = served.token
    assert len(token) == 32 and re.fullmatch(r"[\w-]+", token)

    async def go(session):
        out = []
        for given in ("", "x", "y" * len(token), token[:-1] + ("A" if token[-1] != "A" else "B")):
            async with session.post(
                served.base + "api/write", data=write_body(4100), headers=served.json_headers(given)
            ) as r:
                out.append(await answer(r))
        async with session.post(
            served.base + "api/command/save", data=b"{}", headers=served.json_headers("nope")
        ) as r:
            out.append(await answer(r))
        async with session.get(served.base + "api/state") as r:
            state = await r.text()
        async with session.post(
            served.base + "api/write", data=write_body(4100), headers=served.json_headers()
        ) as r:
            out.append(await answer(r))
        return out, state

    out, state = served.attack(go)
    for status, body in out[:-1]:
        assert status == 403
        assert body["message"].startswith("this needs the token of the URL the server printed")
    assert token not in state
    assert out[-1] == (200, {"ok": True, "name": COEFF, "axis": 1, "value": 4100.0})
    assert served.coefficient() == 4100.0


def test_http_basic_authentication_guards_everything(lists_copy):
    s = Served(lists_copy, HmiOptions(port=0, user="op", password="s3cret"))
    try:

        async def go(session):
            out = {}
            for label, auth in (
                ("none", {}),
                ("wrong", {"Authorization": aiohttp.encode_basic_auth("op", "guess")}),
                ("right", {"Authorization": aiohttp.encode_basic_auth("op", "s3cret")}),
                ("user only", {"Authorization": aiohttp.encode_basic_auth("op", "")}),
            ):
                async with session.get(s.base, headers=auth) as r:
                    out[label] = (r.status, r.headers.get("WWW-Authenticate"))
            return out

        got = s.attack(go)
        refused = (401, 'Basic realm="geo-server", charset="UTF-8"')
        assert got["none"] == got["wrong"] == got["user only"] == refused
        assert got["right"] == (200, None)
    finally:
        s.close()


# ---------------------------------------------------------------------- read-only


def test_read_only_refuses_every_edit_of_one_machine(lists_copy):
    s = Served(lists_copy, HmiOptions(port=0, read_only=True))
    try:
        _read_only_refuses(s, "")
    finally:
        s.close()


def test_read_only_refuses_every_edit_of_a_fleet(lists_copy):
    s = Served(lists_copy, HmiOptions(port=0, read_only=True), fleet=True)
    try:
        for name in s.services:
            _read_only_refuses(s, f"m/{name}/", name)
    finally:
        s.close()


def _read_only_refuses(s: Served, prefix: str, name: str | None = None) -> None:
    before = s.list_bytes()

    async def go(session):
        out = []
        async with session.get(s.base + prefix + "api/state") as r:
            state = json.loads(await r.read())
        for path, data in (
            ("api/write", write_body(4100)),
            ("api/command/save", b"{}"),
            ("api/command/reload", b"{}"),
        ):
            async with session.post(
                s.base + prefix + path, data=data, headers=s.json_headers()
            ) as r:
                out.append(await answer(r))
        return state, out

    state, out = s.attack(go)
    assert state["read_only"] is True  # the page disables its edits
    for status, body in out:
        assert (status, body["code"], body["message"]) == (
            400,
            0x704,
            "this interface is read-only",
        )
    assert s.coefficient(name) == LIST_COEFF
    assert s.list_bytes() == before


@pytest.mark.realtime
@pytest.mark.parametrize("flag", ["--read-only", "--http-read-only"])
def test_the_command_line_makes_the_hmi_read_only(flag):
    args = build_parser().parse_args(["run", flag, "--http", "127.0.0.1:0"])
    assert http_options(args).read_only is True
    args = build_parser().parse_args(["run", "--http", "127.0.0.1:0"])
    assert http_options(args).read_only is False


@contextlib.contextmanager
def http_run(tmp_path, lists_copy, *more: str, env=None):
    """`geo-server run` with the web HMI alone on an ephemeral port: (process, the
    `http: ` line it printed); stopped on leaving."""
    proc = subprocess.Popen(
        [*RUN_HTTP_ONLY, str(lists_copy), "--homed", "--http", "127.0.0.1:0", *more],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        yield proc, next(line for line in proc.stdout if line.startswith("http: "))
    finally:
        proc.terminate()
        proc.wait(15)
        proc.stdout.close()


@pytest.mark.slow
def test_run_read_only_serves_a_read_only_hmi(tmp_path, lists_copy):
    """`geo-server run --read-only --http`: the single-machine HMI refused nothing
    before; now its hello says read_only and a write with the printed token is 0x704."""
    with http_run(tmp_path, lists_copy, "--read-only") as (_proc, line):
        assert line.endswith("(read-only)\n"), line
        url = line.split()[4]
        base, _, token = url.partition("?token=")

        async def go():
            async with aiohttp.ClientSession() as session:
                async with session.get(base + "api/state") as r:
                    state = json.loads(await r.read())
                headers = {"Content-Type": "application/json", TOKEN_HEADER: token}
                async with session.post(
                    base + "api/write", data=write_body(4100), headers=headers
                ) as r:
                    return state["read_only"], await answer(r)

        read_only, (status, body) = asyncio.run(go())
        assert read_only is True
        assert (status, body["code"]) == (400, 0x704)


@pytest.mark.slow
def test_passwords_come_from_the_environment_not_the_process_list(tmp_path, lists_copy):
    """A password on the command line is visible to every user in `ps`; the environment
    (GEO_SERVER_HTTP_PASSWORD) is not: the server asks for it, and it is in no argument."""
    env = {**os.environ, "GEO_SERVER_HTTP_PASSWORD": "s3cret-from-env"}
    with http_run(tmp_path, lists_copy, "--http-user", "operator", env=env) as (proc, line):
        base = line.split()[4].partition("?token=")[0]
        with open(f"/proc/{proc.pid}/cmdline", "rb") as f:
            assert b"s3cret" not in f.read()

        async def go():
            out = []
            for auth in (b"", b"operator:wrong", b"operator:s3cret-from-env"):
                headers = {"Authorization": "Basic " + base64.b64encode(auth).decode()}
                async with (
                    aiohttp.ClientSession() as session,
                    session.get(base + "api/state", headers=headers) as r,
                ):
                    out.append(r.status)
            return out

        assert asyncio.run(go()) == [401, 401, 200]


@pytest.mark.realtime
def test_the_route_and_opcua_passwords_come_from_the_environment_too(monkeypatch):
    monkeypatch.setenv("GEO_SERVER_ADS_ROUTE_PASSWORD", "route-pw")
    monkeypatch.setenv("GEO_SERVER_OPCUA_PASSWORD", "ua-pw")
    monkeypatch.setenv("GEO_SERVER_HTTP_TOKEN", "tok-from-env")
    args = build_parser().parse_args(["run", "--ads-route-user", "eng", "--opcua-user", "ua"])
    assert (args.ads_route_password, args.opcua_password, args.http_token) == (
        "route-pw",
        "ua-pw",
        "tok-from-env",
    )
    # the command line still wins
    args = build_parser().parse_args(["run", "--ads-route-password", "cli-pw"])
    assert args.ads_route_password == "cli-pw"


@pytest.mark.realtime
def test_the_command_line_checks_the_http_options(capsys):
    assert main(["run", "--http", "127.0.0.1:0", "--http-user", "op"]) == 2
    assert "--http-user and --http-password go together" in capsys.readouterr().err
    assert main(["run", "--http", "127.0.0.1:0", "--http-token", "a b"]) == 2
    assert "--http-token" in capsys.readouterr().err
    args = build_parser().parse_args(
        [
            "run",
            "--http",
            "127.0.0.1:0",
            "--http-token",
            "fixed-1",
            "--http-allowed-hosts",
            "a.example,b.example:9",
        ]
    )
    opts = http_options(args)
    assert (opts.token, opts.allowed_hosts) == ("fixed-1", ("a.example", "b.example:9"))


# ---------------------------------------------------------------------- malformed bodies


@pytest.mark.parametrize(
    ("body", "code", "message"),
    [
        (
            b'{"name": "TEMPC::coefficient", "axis": 1, "value": '
            + b"[" * 20000
            + b"]" * 20000
            + b"}",
            0x706,
            "the body is not JSON (maximum recursion depth exceeded",
        ),
        (
            b'{"name": "TEMPC::coefficient", "axis": 1e400, "value": 4100}',
            0x70B,
            '"axis" must be an integer 0 … 65535',
        ),
        (
            b'{"name": "TEMPC::coefficient", "axis": 100000000000000000000, "value": 4100}',
            0x70B,
            '"axis" must be an integer 0 … 65535',
        ),
        (
            b'{"name": "TEMPC::coefficient", "axis": 1, "value": ' + b"9" * 4000 + b"}",
            0x706,
            "the body: a JSON integer of 4000 characters is out of range for every object type",
        ),
        (
            b'{"name": "TEMPC::coefficient", "axis": 1, "value": 1e400}',
            0x706,
            "TEMPC::coefficient: inf is not finite",
        ),
        (
            b'{"name": "TEMPC::coefficient", "axis": 1, "value": "4100"}',
            0x706,
            "TEMPC::coefficient is REAL64: needs a number, got string '4100'",
        ),
        (
            b'{"name": "TEMPC::coefficient", "axis": 1, "value": true}',
            0x706,
            "TEMPC::coefficient is REAL64: needs a number, got boolean True",
        ),
        (b'{"name": 5, "axis": 1, "value": 4100}', 0x70B, '"name" must be a string'),
        (b"[1, 2]", 0x70B, 'expected JSON {"name": …, "axis": …, "value": …}'),
        (b"\xff\xfe{", 0x706, "the body is not JSON"),
    ],
    ids=[
        "deep",
        "axis-1e400",
        "axis-huge",
        "huge-int",
        "1e400",
        "string",
        "true",
        "name",
        "list",
        "bytes",
    ],
)
def test_malformed_bodies_get_400_with_a_message(served, body, code, message):
    """What answered HTTP 500 (deep nesting, `axis 1e400`, a huge integer) or was
    accepted ("4100" and true for a REAL64) is refused as Zenoh refuses it."""

    async def go(session):
        async with session.post(
            served.base + "api/write", data=body, headers=served.json_headers()
        ) as r:
            return await answer(r)

    status, got = served.attack(go)
    assert status == 400 and got["code"] == code and got["ok"] is False
    assert got["message"].startswith(message), got["message"]
    assert served.coefficient() == LIST_COEFF


def test_the_value_rule_is_zenohs():
    """One rule: the web HMI refuses exactly what Zenoh's `_json_value` refuses, with
    the same message (both end in `ObjectDef.coerce_json`)."""
    from geo_server.transports.zenoh.server import _json_value

    obj = load_dictionary().by_name(COEFF)
    for payload in (b'"4100"', b"true", b"9" * 400, b"[" * 5000):
        with pytest.raises(AdsError) as zenoh:
            _json_value(payload, obj)
        assert zenoh.value.code == 0x706


# ---------------------------------------------------------------------- long names


@pytest.fixture
def no_matching(monkeypatch):
    """Record every nearest-name search and name normalisation (the costly part)."""
    calls: list[int] = []

    def close_matches(word, *a, **k):
        calls.append(len(word))
        return []

    real = dictionary_module._normalize_name

    def normalize(name):
        calls.append(len(name))
        return real(name)

    monkeypatch.setattr(dictionary_module.difflib, "get_close_matches", close_matches)
    monkeypatch.setattr(dictionary_module, "_normalize_name", normalize)
    return calls


def test_a_name_longer_than_any_is_refused_before_matching(served, no_matching):
    d = served.service.info.dictionary
    long_name = "TEMPC::" + "c" * 50_000

    async def go(session):
        out = []
        for name in (long_name, "A" * 1_000_000):
            async with session.post(
                served.base + "api/write",
                data=write_body(4100, name),
                headers=served.json_headers(),
            ) as r:
                out.append((r.status, await r.text()))
        return out

    (status, text), (big_status, big_text) = served.attack(go)
    body = json.loads(text)
    assert status == 400 and body["code"] == 0x703
    assert body["message"] == (
        f"unknown object name 'TEMPC::ccccccccccccccccccccccccccccccc…: 50007 characters, "
        f"longer than any object's name (at most {d.max_name_chars})"
    )
    assert len(text) < 300  # the name is not sent back
    # 1 MB is over the body bound: refused on its Content-Length, before a byte of it
    # is read (aiohttp's own bound would read and discard it)
    assert big_status == 413
    assert json.loads(big_text)["message"] == (
        "a body of 1000038 bytes; at most 65536 are accepted"
    )
    assert no_matching == []
    assert served.coefficient() == LIST_COEFF


def test_the_name_bound_is_the_longest_real_name_with_an_axis(no_matching):
    """Every interface resolves names here: a real name with its longest axis suffix is
    still looked up; one character more is refused unmatched."""
    d = load_dictionary()
    longest = max(
        [*(n.replace("::", ":: ") for o in d.objects for n in (o.name, *o.aliases))],
        key=len,
    )
    assert d.max_name_chars >= len(longest) + len("[65535]")
    with pytest.raises(AdsError) as unknown:
        d.by_name("x" * d.max_name_chars)
    assert "did you mean" not in unknown.value.message and no_matching  # matched
    no_matching.clear()
    with pytest.raises(AdsError) as refused:
        d.by_name("x" * (d.max_name_chars + 1))
    assert refused.value.code == 0x703 and "longer than any object's name" in refused.value.message
    assert no_matching == []
    for o in d.objects:
        assert d.by_name(o.name) is o


# ---------------------------------------------------------------------- WebSockets


def test_a_websocket_peer_that_sends_is_closed(served):
    """The page sends nothing: a client sending a 4 MiB frame is closed, so is one
    sending a small message (1008); the server keeps serving pages."""

    async def go(session):
        ends = []
        for data in (b"x" * (4 * 1024 * 1024), b"hello"):
            ws = await session.ws_connect(served.base + "ws", max_msg_size=0)
            assert json.loads((await ws.receive(timeout=10)).data)["type"] == "hello"
            with contextlib.suppress(ConnectionError):
                await ws.send_bytes(data)
            msg = await ws.receive(timeout=10)
            while msg.type == aiohttp.WSMsgType.TEXT:  # pushes sent before the close
                msg = await ws.receive(timeout=10)
            # (the 4 MiB one: the server closes with 1009 while the client still sends,
            # so the client may see the connection reset, 1006, instead of the code)
            ends.append((msg.type != aiohttp.WSMsgType.TEXT, ws.closed, ws.close_code))
            await ws.close()
        async with session.get(served.base + "api/state") as r:
            ends.append(r.status)
        return ends

    big, small, status = served.attack(go)
    assert big[:2] == (True, True) and big[2] in (1009, 1006)
    assert small == (True, True, 1008) and status == 200
    assert served.on_loop(lambda: len(served.hmi.sockets)) == 0


def test_a_frame_over_the_bound_is_refused_at_its_header(served):
    """A raw client announces a 4 MiB frame and sends none of it: the server closes
    with 1009 (message too big) from the header alone, before any payload arrives."""
    port = served.hmi.port
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(
            f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
            "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n".encode()
        )
        reader = s.makefile("rb")
        assert reader.readline().startswith(b"HTTP/1.1 101")
        while reader.readline() not in (b"\r\n", b""):
            pass
        # FIN + binary, masked, 64-bit length 4 MiB, a mask; no payload
        s.sendall(bytes([0x82, 0x80 | 127]) + (4 * 1024 * 1024).to_bytes(8, "big") + b"\0" * 4)
        while True:  # the server's frames: the hello, pushes, then the close
            head = reader.read(2)
            assert len(head) == 2, "closed without a close frame"
            size = head[1] & 0x7F
            if size == 126:
                size = int.from_bytes(reader.read(2), "big")
            elif size == 127:
                size = int.from_bytes(reader.read(8), "big")
            payload = reader.read(size)
            if head[0] & 0x0F == 0x8:
                break
    assert int.from_bytes(payload[:2], "big") == 1009


def test_a_ping_flood_closes_the_socket(served):
    async def go(session):
        ws = await session.ws_connect(served.base + "ws", autoping=False)
        for _ in range(served.hmi.options.ws_ping_burst + 5):
            await ws.ping()
        while True:
            msg = await ws.receive(timeout=10)
            if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                return ws.close_code, msg.extra

    assert served.attack(go) == (1008, "too many pings")


def test_too_many_pages_are_refused(served):
    """At most `max_pages` (3 here) sockets per machine; the next gets 503 with a
    message, and a closed page frees its place."""
    cap = served.hmi.options.max_pages

    async def go(session):
        pages = [await session.ws_connect(served.base + "ws") for _ in range(cap)]
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await session.ws_connect(served.base + "ws")
        async with session.get(
            served.base + "ws",
            headers={
                "Upgrade": "websocket",
                "Connection": "Upgrade",
                "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
                "Sec-WebSocket-Version": "13",
            },
        ) as r:
            message = json.loads(await r.read())["message"]
        await pages.pop().close()
        for _ in range(200):  # until the server has seen the close
            if served.on_loop(lambda: served.hmi._pages) < cap:
                break
            await asyncio.sleep(0.01)
        async with session.ws_connect(served.base + "ws") as again:
            kind = json.loads((await again.receive(timeout=10)).data)["type"]
        for ws in pages:
            await ws.close()
        return refused.value.status, message, kind

    status, message, kind = served.attack(go)
    assert status == 503 and kind == "hello"
    assert message == (
        f"{cap} pages of this machine are open, the most it serves (HmiOptions.max_pages); "
        "close one"
    )


def test_a_raw_request_without_host_is_refused(served):
    """HTTP/1.0 without a Host header: nothing to check it against, refused."""
    with socket.create_connection(("127.0.0.1", served.hmi.port), timeout=10) as s:
        s.sendall(b"GET /api/state HTTP/1.0\r\n\r\n")
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    assert data.startswith(b"HTTP/1.0 421") or data.startswith(b"HTTP/1.1 421"), data[:100]
