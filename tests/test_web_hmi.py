"""The web HMI (docs/web.md) in a real headless browser: Debian's Chromium driven by
Playwright, against a real-time machine (exact engine) served in this process; and its
JSON without a browser."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import re
import shutil
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import aiohttp
import pytest
from conftest import RUN_HTTP_ONLY

from geo_server import access
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import data_dir, default_startup_list
from geo_server.service import ObjectService
from geo_server.web import CHROMIUM, CHROMIUM_ARGS
from geo_server.web.server import HmiOptions, HmiServer, parse_http
from geo_server.web.tables import tables
from geo_server.web.views import LiveView

WAIT_MS = 15_000
ACCEL_POS = "accelerating, + direction"


class Served:
    """A real-time machine with the web HMI on an ephemeral port of 127.0.0.1."""

    def __init__(self, startup: Path, options: HmiOptions | None = None) -> None:
        self.machine = Machine(load_machine(startup), homed=True)
        self.scheduler = Scheduler(self.machine, mode="realtime", engine="exact")
        self.service = ObjectService(self.machine, self.scheduler)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.hmi = HmiServer(self.service, options or HmiOptions(port=0, machine="bench"))
        self.run(self.hmi.start())
        self.scheduler.start()
        self.url = f"http://{self.hmi.address}/"
        #: the page's URL as `geo-server run` prints it: with the run's write token
        self.page_url = self.hmi.url
        self.lists = startup.parent

    def run(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(15)

    def get(self, path: str):
        with urllib.request.urlopen(self.url + path.lstrip("/"), timeout=10) as r:
            return json.loads(r.read())

    def post(self, path: str, body: dict) -> tuple[int, dict]:
        req = urllib.request.Request(
            self.url + path.lstrip("/"),
            json.dumps(body).encode(),
            {"Content-Type": "application/json", "X-Geo-Token": self.hmi.options.token},
        )
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    def close(self) -> None:
        self.run(self.hmi.close())
        self.scheduler.stop()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()


def copy_lists(tmp_path: Path, *, twin: bool = True) -> Path:
    """The default machine's lists in tmp_path: save writes here, never into the
    repository's lists."""
    lists = tmp_path / "lists"
    ignore = ["examples", "tools"] + ([] if twin else ["twin.toml"])
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns(*ignore))
    return lists / "hochlauf.lis"


@pytest.fixture
def served(tmp_path):
    s = Served(copy_lists(tmp_path))
    yield s
    s.close()


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        if os.environ.get("GEO_SERVER_REQUIRE_BROWSER") == "1":
            pytest.fail(f"{CHROMIUM} is missing (apt-get install chromium)")
        pytest.skip(f"{CHROMIUM} is missing (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_ARGS))
        yield b
        b.close()


def open_page(browser, served):
    """The page of `served`, once every axis shows a live value."""
    pg = browser.new_page(viewport={"width": 1400, "height": 1000})
    pg.errors = []
    pg.on("pageerror", lambda e: pg.errors.append(str(e)))
    pg.goto(served.page_url)
    last = served.service.info.axes[-1]
    pg.wait_for_selector(
        f"#axis-{last} .v[data-f='command_position']:not(:text('–'))", timeout=WAIT_MS
    )
    pg.wait_for_function("() => state.tablePlots.length > 0", timeout=WAIT_MS)
    return pg


@pytest.fixture
def page(browser, served):
    pg = open_page(browser, served)
    yield pg
    pg.close()
    assert pg.errors == []  # no script error in the page


def cell(pg, axis: int, field: str):
    return pg.locator(f"#axis-{axis} .v[data-f='{field}']")


def tempc_input(pg, axis: int, name: str):
    return pg.locator(f"input[data-name='{name}'][data-axis='{axis}']")


# ---------------------------------------------------------------------- in the browser


@pytest.mark.slow
def test_the_page_shows_every_axis_live(page, served):
    from playwright.sync_api import expect

    names = [page.locator(f"#axis-{a} h2 span").inner_text() for a in (1, 2, 3, 4)]
    assert names == ["X", "Y", "Z", "C"]
    expect(cell(page, 1, "command_position")).to_have_text("0.0000 mm")
    expect(cell(page, 4, "command_position")).to_have_text("0.0000 °")
    # the twin's sensor starts at its ambient temperature (lists/twin.toml: 20 °C)
    expect(cell(page, 4, "sensor_temperature")).to_have_text("20.00 °C")
    # lists/achsmd1.lis: temp_comp_coefficient 4000 µm/m, offset_0 40 (0.1 µm) = 4.0 µm
    expect(tempc_input(page, 1, "TEMPC::coefficient")).to_have_value("4000")
    expect(tempc_input(page, 1, "TEMPC::offset_0")).to_have_value("40")
    expect(page.locator("#axis-1 .hint[data-hint='offset_0']")).to_have_text("= 4.0 µm")
    # the raw unit of an offset: 0.1 µm on linear X, 0.0001° on rotary C (design.md §3.1)
    label = "#axis-{} .tempc label:has-text('offset_0') small"
    expect(page.locator(label.format(1))).to_have_text("[0.1 µm]")
    expect(page.locator(label.format(4))).to_have_text("[0.0001°]")
    # a rotary axis' 4 decimals fit their column (C's leadscrew value, -0.0007 °, used to
    # run into its unit)
    expect(page.locator("#axis-4 tr[data-comp='LSEC'] .act")).not_to_have_text("–")
    overflowing = page.eval_on_selector_all(
        ".comps td.num", "cells => cells.filter(c => c.scrollWidth > c.clientWidth).length"
    )
    assert overflowing == 0
    # X at 0 mm: 4.0 µm + 4000·10⁻⁶·(0 − 0.01 mm) = 3.96 µm → TEMPC::actual_offset 4.0 µm
    row = page.locator("#axis-1 tr[data-comp='TEMP']")
    expect(row.locator(".act")).to_have_text("4.0")
    # X: temperature compensation selected and effective (homed, 000 p.22)
    expect(row.locator(".sel")).to_have_class("dot sel on")
    expect(row.locator(".eff")).to_have_class("dot eff on")
    # every configured table drawn: LSEC of X, Y, C; X friction; Z cross, plane, mode 3
    expect(page.locator(".table-card")).to_have_count(7)
    expect(page.locator(".table-card canvas.heat")).to_have_count(2)
    expect(page.locator("#trends .trend")).to_have_count(3)
    expect(page.locator("#status")).to_contain_text("exact engine")


@pytest.mark.slow
def test_a_value_changes_when_the_axis_moves(page, served, tmp_path):
    from playwright.sync_api import expect

    served.service.nc.run("G90 G01 X10 Y-5 F6000")  # 10 mm at 100 mm/s
    expect(cell(page, 1, "command_position")).to_have_text("10.0000 mm", timeout=WAIT_MS)
    expect(cell(page, 2, "command_position")).to_have_text("-5.0000 mm", timeout=WAIT_MS)
    # the tables' marker follows: the cross table of Z over X and the plane over X/Y
    cross = page.locator(".table-card[data-kind='cross'] .caption")
    expect(cross).to_contain_text("X 10.0000 mm", timeout=WAIT_MS)
    plane = page.locator(".table-card[data-kind='plane'] .caption")
    expect(plane).to_contain_text("X 10.0000 mm · Y -5.0000 mm", timeout=WAIT_MS)
    page.screenshot(path=str(tmp_path / "moved.png"), full_page=True)
    assert (tmp_path / "moved.png").stat().st_size > 50_000


@pytest.mark.slow
def test_a_tempc_edit_reaches_the_server(page, served):
    from playwright.sync_api import expect

    box = tempc_input(page, 1, "TEMPC::coefficient")
    box.fill("4321.5")
    box.press("Enter")
    expect(page.locator("#tempc-msg-1")).to_have_text("TEMPC::coefficient := 4321.5")
    assert access.read_name(served.service, "TEMPC::coefficient", 1) == 4321.5
    off = tempc_input(page, 3, "TEMPC::offset_0")
    off.fill("-25")
    off.press("Enter")
    expect(page.locator("#tempc-msg-3")).to_have_text("TEMPC::offset_0 := -25")
    assert access.read_name(served.service, "TEMPC::offset_0", 3) == -25
    expect(page.locator("#axis-3 .hint[data-hint='offset_0']")).to_have_text("= -2.5 µm")
    # a flag: the checkbox switches the temperature compensation of C on
    tempc_input(page, 4, "TEMPC::activated").check()
    expect(page.locator("#tempc-msg-4")).to_have_text("TEMPC::activated := true")
    assert access.read_name(served.service, "TEMPC::activated", 4) is True


@pytest.mark.slow
def test_an_out_of_range_edit_shows_the_servers_error(page, served):
    from playwright.sync_api import expect

    box = tempc_input(page, 1, "TEMPC::coefficient")
    box.fill("20000")
    box.press("Enter")
    # the object's range, −10000 … 10000 µm/m (000 p.21), as every interface says it
    # (the JSON number as sent, as Zenoh says it: the same rule, `coerce_json`)
    expect(page.locator("#tempc-msg-1")).to_have_text(
        "ADS 0x706: TEMPC::coefficient: 20000 outside the range -10000 … 10000 [µm/m]"
    )
    expect(page.locator("#tempc-msg-1")).to_have_class("msg error")
    assert access.read_name(served.service, "TEMPC::coefficient", 1) == 4000.0
    box.fill("abc")
    box.press("Enter")
    expect(page.locator("#tempc-msg-1")).to_have_text("TEMPC::coefficient: 'abc' is not a number")
    assert access.read_name(served.service, "TEMPC::coefficient", 1) == 4000.0


@pytest.mark.slow
def test_save_and_reload_buttons(page, served):
    from playwright.sync_api import expect

    box = tempc_input(page, 2, "TEMPC::coefficient")
    box.fill("33.5")
    box.press("Enter")
    expect(page.locator("#tempc-msg-2")).to_have_text("TEMPC::coefficient := 33.5")
    page.click("#save")
    expect(page.locator("#command-result")).to_have_text(f"saved: {served.lists / 'achsmd2.lis'}")
    assert "lr_param.temp_comp_coefficient 33.5" in (served.lists / "achsmd2.lis").read_text()
    # an edited table reaches the page by the button: X's LSEC error at -490 mm 1.5 → 2.5 µm
    x_lsec = "state.tables.find((t) => t.kind === 'lsec' && t.axis === 1).series.error[1]"
    assert page.evaluate(x_lsec) == 1.5
    kw1 = served.lists / "achskw1.lis"
    kw1.write_text(kw1.read_text().replace("table[1].pos 15 ", "table[1].pos 25 "))
    page.click("#reload")
    expect(page.locator("#command-result")).to_have_text("reloaded (8 files)")
    page.wait_for_function(f"() => {x_lsec} === 2.5", timeout=WAIT_MS)
    # … and by a reload from another interface (the page is told to fetch the tables)
    kw1.write_text(kw1.read_text().replace("table[1].pos 25 ", "table[1].pos -5 "))
    assert served.service.commands.run("reload").ok
    page.wait_for_function(f"() => {x_lsec} === -0.5", timeout=WAIT_MS)
    # the saved coefficient came back with the lists
    expect(tempc_input(page, 2, "TEMPC::coefficient")).to_have_value("33.5")


@pytest.mark.slow
def test_new_errors_and_faults_show_up(page, served):
    from playwright.sync_api import expect

    served.service.report("coolant pressure low (from the test)", error_id=4711)
    first = page.locator("#errors tbody tr").first
    expect(first).to_contain_text("coolant pressure low (from the test)", timeout=WAIT_MS)
    expect(first.locator("td").nth(1)).to_have_text("error")
    expect(first.locator("td").nth(2)).to_have_text("4711")
    served.service.faults.inject("ads:error=0x707,count=2")
    expect(page.locator("#faults")).to_have_text(
        "Injected faults: #1 ads:error=0x707,count=2 (0 hits)", timeout=WAIT_MS
    )


@pytest.mark.slow
def test_a_machine_without_twin(browser, tmp_path):
    """No twin.toml: no twin rows, one trend, and the page still works."""
    from playwright.sync_api import expect

    served = Served(copy_lists(tmp_path, twin=False))
    try:
        pg = open_page(browser, served)
        expect(pg.locator("#trends .trend")).to_have_count(1)
        expect(cell(pg, 1, "sensor_temperature")).to_have_count(0)
        # TEMPC 4.0 µm + LSEC 0.9 µm (lists/achskw1.lis: table[50].pos -9 at 0 mm; the
        # cycle applies −Δs)
        expect(cell(pg, 1, "total_offset")).to_have_text("4.9 µm")
        pg.close()
        assert pg.errors == []
    finally:
        served.close()


# ---------------------------------------------------------------------- without a browser


def test_tables_in_engineering_units():
    cfg = load_machine(default_startup_list())
    by = {(t["axis"], t["kind"]): t for t in tables(cfg, (1, 2, 3, 4))}
    assert sorted(by) == [
        (1, "frict"),
        (1, "lsec"),
        (2, "lsec"),
        (3, "cross"),
        (3, "crosstalk"),
        (3, "plane"),
        (4, "lsec"),
    ]
    x = by[(1, "lsec")]
    # lists/achskw1.lis: kw_startpos -5000000, interval 100000, table[1].pos 15 (0.1 µm)
    assert x["x"][:2] == [-500.0, -490.0] and x["series"]["error"][:2] == [0.0, 1.5]
    assert (x["x_name"], x["x_unit"], x["y_label"]) == ("X", "mm", "measured error [µm]")
    y = by[(2, "lsec")]  # lists/achskw2.lis: bilateral, setpoints -200000, -199306, …
    assert list(y["series"]) == ["+ direction", "− direction"] and y["x"][:2] == [-20.0, -19.9306]
    # lists/achskw1.lis: friction table[1] 50 µm/s → 2600
    fr = by[(1, "frict")]
    assert (fr["x"][1], fr["series"]["additive current"][1], fr["x_unit"]) == (0.05, 2600.0, "mm/s")
    # lists/achskw3.lis: cross table[1] at -485 mm: 3 (0.1 µm); plane start -500 mm,
    # interval 50 mm, table[0][0] 15, [0][1] 12
    cross = by[(3, "cross")]
    assert (cross["x_axis"], cross["x"][1], cross["series"]["correction"][1]) == (1, -485.0, 0.3)
    plane = by[(3, "plane")]
    assert plane["x"][:2] == [-500.0, -450.0]
    assert plane["layers"]["correction"][0][:2] == [1.5, 1.2]
    # mode 3: position[0] at X -500, Y -400 mm, accelerate_dir_pos 35, …_neg -37; the
    # sampled surface passes through its test points
    ct = by[(3, "crosstalk")]
    assert (ct["points"]["x"][0], ct["points"]["y"][0]) == (-500.0, -400.0)
    assert ct["points"]["layers"][ACCEL_POS][0] == 3.5
    assert ct["points"]["layers"]["accelerating, − direction"][0] == -3.7
    assert (ct["x"][0], ct["y"][0], ct["layers"][ACCEL_POS][0][0]) == (-500.0, -400.0, 3.5)
    assert len(ct["x"]) == 48 and len(ct["layers"][ACCEL_POS]) == 36
    c = by[(4, "lsec")]
    assert (c["x_unit"], c["y_label"]) == ("°", "measured error [°]")


def test_tables_endpoint(served):
    got = served.get("/api/tables")
    assert got == json.loads(json.dumps(tables(served.machine.cfg, served.service.info.axes)))
    assert [t["title"] for t in got] == [
        "X leadscrew error (LSEC)",
        "X friction compensation (FRICT)",
        "Y leadscrew error (LSEC)",
        "Z cross compensation over X (CROSSC)",
        "Z plane compensation over X/Y (CC2)",
        "Z crosstalk mode 3 over X/Y",
        "C leadscrew error (LSEC)",
    ]


def test_live_payload_of_a_stepped_machine():
    m = Machine(load_machine(default_startup_list()), homed=True)
    service = ObjectService(m)
    service.nc.run("G91 G01 X1 F6000")
    access.step(service, 500)
    view = LiveView(service.info.dictionary, m.cfg, service.info.axes)
    live = view.push(service.current(stale_ok=True), 1.5)
    x = live["axes"]["1"]
    assert live["cycle"] == 500 and x["command_position"] == 1.0  # mm
    assert x["tempc"]["coefficient"] == 4000.0 and x["comps"]["TEMP"][:2] == [True, True]
    assert x["tempc_shown"] == {"offset_0": "4.0 µm", "position_0": "0.01 mm"}
    assert x["comps"]["PLANE"][1] is None  # the manual has no effective flag for it
    # X's node at 20 °C, its sensor read with 0.02 K noise (lists/twin.toml; 5 σ)
    assert x["sensor_temperature"] == pytest.approx(20.0, abs=0.1)
    assert view.trend_fields == ("total_offset", "residual", "sensor_temperature")
    assert len(view.trend_point(live)) == 12
    # the sample taken while no page is open: the same numbers without the push
    assert view.trend_sample(service.current(stale_ok=True)) == view.trend_point(live)
    assert view.trend_sample(service.current(stale_ok=True))[2] == x["sensor_temperature"]


def test_live_payload_without_twin(tmp_path):
    m = Machine(load_machine(copy_lists(tmp_path, twin=False)), homed=True)
    service = ObjectService(m)
    access.step(service, 20)
    view = LiveView(service.info.dictionary, m.cfg, service.info.axes)
    live = view.push(service.current(stale_ok=True), 0.0)
    x = live["axes"]["1"]
    assert not view.has_twin and "residual" not in x and "sensor_temperature" not in x
    # total offsets at rest: X 4.0 (TEMPC) + 0.9 (LSEC) µm, Y -9.8 µm (LSEC), Z -2.0
    # (TEMPC) + 8.3 (cross) - 2.0 (plane) µm, C -0.0007° (LSEC, 7 increments)
    assert view.trend_fields == ("total_offset",)
    assert view.trend_point(live) == [4.9, -9.8, 4.3, -0.0007]
    assert view.trend_sample(service.current(stale_ok=True)) == [4.9, -9.8, 4.3, -0.0007]


@pytest.mark.slow
def test_nobody_watching_costs_one_sample_a_second(tmp_path):
    """No socket: a trend sample every `idle_period`, nothing pushed; a page opened
    later gets those samples, then a push every `period`."""
    opts = HmiOptions(port=0, period=0.02, idle_period=0.2)
    served = Served(copy_lists(tmp_path), opts)
    try:
        t0 = time.monotonic()
        time.sleep(1.0)
        samples, elapsed = served.hmi.samples, time.monotonic() - t0
        # one per idle period (the first at start), never one per period: a host that
        # oversleeps only stretches the window, which the bound follows
        assert 2 <= samples <= elapsed / opts.idle_period + 2 and served.hmi.pushes == 0

        async def watch() -> tuple[dict, list[dict]]:
            async with (
                aiohttp.ClientSession() as s,
                s.ws_connect(f"ws://{served.hmi.address}/ws") as ws,
            ):
                hello = json.loads((await ws.receive()).data)
                got = [json.loads((await ws.receive()).data) for _ in range(10)]
                return hello, got

        hello, got = served.run(watch())
        assert len(hello["trends"]["t"]) >= 3 and len(hello["trends"]["series"]) == 12
        live = [m for m in got if m["type"] == "live"]
        assert len(live) >= 9
        # pushed at the page's period (0.02 s), not the idle one (0.2 s): the pushes' own
        # time stamps, whatever the client's delays
        gaps = sorted(b["t"] - a["t"] for a, b in itertools.pairwise(live))
        assert gaps[len(gaps) // 2] < opts.idle_period / 2, gaps
        assert served.hmi.pushes >= 9
    finally:
        served.close()


def test_a_stalled_cycle_is_pushed_as_such(served, monkeypatch):
    def stalled():
        raise AdsError(AdsErrorCode.DEVICE_NOTREADY, "the GEO cycle is stalled")

    monkeypatch.setattr(served.service, "current", stalled)
    got = json.loads(served.hmi.sample())
    assert got == {"type": "stalled", "code": 0x707, "message": "the GEO cycle is stalled"}


def test_write_endpoint_refuses_what_is_not_a_tempc_parameter(served):
    status, body = served.post("/api/write", {"name": "SIM::feed", "axis": 1, "value": 5})
    assert status == 400 and body["code"] == 0x704
    assert body["message"] == "SIM::feed is not a writable TEMPC parameter"
    status, body = served.post("/api/write", {"name": "TEMPC::nope", "axis": 1, "value": 5})
    assert status == 400 and body["code"] == 0x703
    status, body = served.post("/api/write", {"axis": 1})
    assert status == 400 and body["code"] == 0x70B
    status, body = served.post("/api/write", {"name": "TEMPC::coefficient", "axis": 9, "value": 1})
    assert status == 400 and body["message"] == "axis 9 is not configured"
    status, body = served.post("/api/command/explode", {})
    assert status == 400 and body["code"] == 0x701
    status, body = served.post("/api/write", {"name": "TEMPC::coefficient", "axis": 1, "value": 7})
    assert (status, body["ok"], body["value"]) == (200, True, 7.0)


def test_a_read_only_server_refuses_edits_and_commands(tmp_path):
    """`geo-server run --read-only --http`: the page may look, not touch (0x704)."""
    s = Served(copy_lists(tmp_path), HmiOptions(port=0, read_only=True))
    try:
        assert s.get("/api/state")["read_only"] is True
        status, body = s.post("/api/write", {"name": "TEMPC::coefficient", "axis": 1, "value": 7})
        assert (status, body["code"]) == (400, 0x704)
        assert body["message"] == "this interface is read-only"
        status, body = s.post("/api/command/save", {})
        assert (status, body["code"]) == (400, 0x704)
        assert access.read_name(s.service, "TEMPC::coefficient", 1) == 4000.0  # lists/achsmd1.lis
    finally:
        s.close()


def banner(proc: subprocess.Popen) -> tuple[str, str]:
    """The page's URL in `geo-server run`'s `http:` line (with its `?token=…`), and the
    line ("" and "" when the server ended without one)."""
    for line in proc.stdout:
        if line.startswith("http: web HMI on "):
            return line.split()[4], line
    return "", ""


@pytest.mark.realtime
@pytest.mark.slow
def test_run_with_the_http_port_taken_fails_cleanly(tmp_path):
    """`geo-server run --http` on a port in use: exit 2 and one clear line."""
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    port = blocker.getsockname()[1]
    try:
        r = subprocess.run(
            [*RUN_HTTP_ONLY, "--cycles", "50", "--http", f"127.0.0.1:{port}"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        blocker.close()
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.strip() == (
        f"error: http interface did not start: 127.0.0.1:{port} is taken (another "
        "geo-server?); choose another --http HOST:PORT or stop the other server"
    )


@pytest.mark.realtime
@pytest.mark.slow
def test_run_serves_the_page_on_an_ephemeral_port(tmp_path):
    """`--http 127.0.0.1:0`: the banner names the port the page is served on."""
    proc = subprocess.Popen(
        [*RUN_HTTP_ONLY, "--homed", "--http", "127.0.0.1:0"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        url, line = banner(proc)
        assert line.endswith("(edits need the token in this URL)\n")
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+/\?token=[\w-]{32}", url), url
        with urllib.request.urlopen(url, timeout=10) as r:
            assert b"<title>geo-server HMI</title>" in r.read()
    finally:
        proc.terminate()
        proc.wait(15)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("127.0.0.1:8080", ("127.0.0.1", 8080)),
        ("8080", ("127.0.0.1", 8080)),
        ("[::1]:0", ("::1", 0)),
        ("0.0.0.0:80", ("0.0.0.0", 80)),
    ],
)
def test_parse_http(text, expected):
    assert parse_http(text) == expected


def test_parse_http_refuses_nonsense():
    with pytest.raises(ValueError, match="expected HOST:PORT"):
        parse_http("localhost:http")
    with pytest.raises(ValueError, match="expected HOST:PORT"):
        parse_http("1.2.3.4:70000")


@pytest.mark.realtime
@pytest.mark.slow
def test_a_fleet_page_reaches_every_machine_by_name(browser, tmp_path):
    """`geo-server run --fleet FILE --http`: `/` lists the machines (docs/web.md §3), a
    name opens that machine's page at /m/<name>/, and an edit there reaches that machine
    and no other (a fresh page of each shows its own server value)."""
    from playwright.sync_api import expect

    fleet = tmp_path / "fleet.toml"
    fleet.write_text(
        '[[machine]]\nname = "mill-a"\n\n[[machine]]\nname = "lathe-b"\nnetid = "127.0.0.1.9.1"\n',
        encoding="utf-8",
    )
    with open(tmp_path / "err.txt", "wb") as err:  # (a pipe nobody reads could fill up)
        proc = subprocess.Popen(
            [*RUN_HTTP_ONLY, "--fleet", str(fleet), "--homed", "--http", "127.0.0.1:0"],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
    pg = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page_url, _ = banner(proc)
        assert page_url.startswith("http://127.0.0.1:"), (tmp_path / "err.txt").read_text()
        url, _, token = page_url.partition("?token=")
        with urllib.request.urlopen(url + "api/fleet", timeout=10) as r:
            st = json.loads(r.read())
        assert st["count"] == 2 and [m["name"] for m in st["machines"]] == ["mill-a", "lathe-b"]
        assert [m["netid"] for m in st["machines"]] == ["127.0.0.1.1.1", "127.0.0.1.9.1"]
        with pytest.raises(urllib.error.HTTPError) as nope:
            urllib.request.urlopen(url + "m/drill-c/", timeout=10)
        assert nope.value.code == 404
        assert nope.value.read().decode() == (
            "no machine 'drill-c' in this fleet (machines: mill-a, lathe-b)"
        )
        post = urllib.request.Request(
            url + "m/drill-c/api/write",
            b"{}",
            {"Content-Type": "application/json", "X-Geo-Token": token},
            method="POST",
        )
        with pytest.raises(urllib.error.HTTPError) as nope:
            urllib.request.urlopen(post, timeout=10)
        assert nope.value.code == 404

        pg.goto(page_url)  # the token is kept for the machines' pages
        rows = pg.locator("#machines tbody tr")
        expect(rows).to_have_count(2, timeout=WAIT_MS)
        expect(rows.nth(1).locator("td").nth(5)).to_have_text("127.0.0.1.9.1")
        # (overruns and stalls are figures of a real-time server: their shape only)
        status = re.compile(r"^2 machines · overruns \d+ · stalled \d+$")
        expect(pg.locator("#status")).to_have_text(status)
        pg.locator("a", has_text="lathe-b").click()
        pg.wait_for_url(url + "m/lathe-b/")
        expect(pg.locator("#machine")).to_contain_text("lathe-b")
        expect(pg.locator("#fleet-link")).to_be_visible()
        box = tempc_input(pg, 1, "TEMPC::coefficient")
        expect(box).to_have_value("4000", timeout=WAIT_MS)
        box.fill("4321.5")
        box.press("Enter")
        expect(pg.locator("#tempc-msg-1")).to_have_text("TEMPC::coefficient := 4321.5")
        # the other machine keeps the list's 4000 µm/m; this one serves 4321.5 to a new page
        for name, value in (("mill-a", "4000"), ("lathe-b", "4321.5")):
            pg.goto(url + f"m/{name}")  # (no slash: redirected to the page)
            expect(pg.locator("#machine")).to_contain_text(name, timeout=WAIT_MS)
            expect(tempc_input(pg, 1, "TEMPC::coefficient")).to_have_value(value, timeout=WAIT_MS)
        pg.locator("#fleet-link").click()
        expect(pg.locator("#machines tbody tr")).to_have_count(2, timeout=WAIT_MS)
    finally:
        pg.close()
        proc.terminate()
        proc.wait(15)
        proc.stdout.close()
    assert errors == []
