"""The web HMI (docs/web.md) in a real headless browser: Debian's Chromium driven by
Playwright, against a real-time machine (exact engine) served in this process."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import threading
import urllib.request
from pathlib import Path

import pytest

from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import data_dir, default_startup_list
from geo_server.service import ObjectService
from geo_server.web import CHROMIUM, CHROMIUM_ARGS
from geo_server.web.server import HmiOptions, HmiServer, parse_http
from geo_server.web.views import LiveView, tables

WAIT_MS = 15_000


class Served:
    """A real-time machine with the web HMI on an ephemeral port of 127.0.0.1."""

    def __init__(self, startup: Path) -> None:
        self.machine = Machine(load_machine(startup), homed=True)
        self.scheduler = Scheduler(self.machine, mode="realtime", engine="exact")
        self.service = ObjectService(self.machine, self.scheduler)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.hmi = HmiServer(self.service, HmiOptions(port=0, machine="bench"))
        self._run(self.hmi.start())
        self.scheduler.start()
        self.url = f"http://{self.hmi.address}/"

    def _run(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(15)

    def post(self, path: str, body: dict) -> tuple[int, dict]:
        req = urllib.request.Request(
            self.url + path.lstrip("/"),
            json.dumps(body).encode(),
            {"Content-Type": "application/json"},
        )
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    def close(self) -> None:
        self._run(self.hmi.close())
        self.scheduler.stop()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()


@pytest.fixture
def served(tmp_path):
    lists = tmp_path / "lists"  # save writes here, never into the repository's lists
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    s = Served(lists / "hochlauf.lis")
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


@pytest.fixture
def page(browser, served):
    pg = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(served.url)
    pg.wait_for_selector("#axis-4 .v[data-f='command_position']:not(:text('–'))", timeout=WAIT_MS)
    yield pg
    pg.close()
    assert errors == []  # no script error in the page


def cell(pg, axis: int, field: str):
    return pg.locator(f"#axis-{axis} .v[data-f='{field}']")


def tempc_input(pg, axis: int, name: str):
    return pg.locator(f"input[data-name='{name}'][data-axis='{axis}']")


# ---------------------------------------------------------------------- in the browser


def test_the_page_shows_every_axis_live(page, served):
    from playwright.sync_api import expect

    names = [page.locator(f"#axis-{a} h2 span").inner_text() for a in (1, 2, 3, 4)]
    assert names == ["X", "Y", "Z", "C"]
    expect(cell(page, 1, "command_position")).to_have_text("0.0000 mm")
    expect(cell(page, 4, "command_position")).to_have_text("0.0000 °")
    # lists/achsmd1.lis: temp_comp_coefficient 4000 µm/m, shown in the editor
    expect(tempc_input(page, 1, "TEMPC::coefficient")).to_have_value("4000")
    # X: temperature compensation selected and effective (homed, 000 p.22)
    row = page.locator("#axis-1 tr[data-comp='TEMP']")
    expect(row.locator(".sel")).to_have_class("dot sel on")
    expect(row.locator(".eff")).to_have_class("dot eff on")
    # every configured table drawn: 4 LSEC, friction, cross, plane, crosstalk mode 3
    expect(page.locator(".table-card")).to_have_count(7)
    expect(page.locator("#status")).to_contain_text("exact")


def test_a_value_changes_when_the_axis_moves(page, served, tmp_path):
    from playwright.sync_api import expect

    served.service.run_nc("G90 G01 X10 Y-5 F6000")  # 10 mm at 100 mm/s
    expect(cell(page, 1, "command_position")).to_have_text("10.0000 mm", timeout=WAIT_MS)
    expect(cell(page, 2, "command_position")).to_have_text("-5.0000 mm", timeout=WAIT_MS)
    page.screenshot(path=str(tmp_path / "moved.png"), full_page=True)
    assert (tmp_path / "moved.png").stat().st_size > 50_000


def test_a_tempc_edit_reaches_the_server(page, served):
    from playwright.sync_api import expect

    box = tempc_input(page, 1, "TEMPC::coefficient")
    box.fill("4321.5")
    box.press("Enter")
    expect(page.locator("#tempc-msg-1")).to_have_text("TEMPC::coefficient := 4321.5")
    assert served.service.read_name("TEMPC::coefficient", 1) == 4321.5
    off = tempc_input(page, 3, "TEMPC::offset_0")
    off.fill("-25")
    off.press("Enter")
    expect(page.locator("#tempc-msg-3")).to_have_text("TEMPC::offset_0 := -25")
    assert served.service.read_name("TEMPC::offset_0", 3) == -25


def test_an_out_of_range_edit_shows_the_servers_error(page, served):
    from playwright.sync_api import expect

    box = tempc_input(page, 1, "TEMPC::coefficient")
    box.fill("20000")
    box.press("Enter")
    # the object's range, −10000 … 10000 µm/m (000 p.21), as every interface says it
    expect(page.locator("#tempc-msg-1")).to_have_text(
        "ADS 0x706: TEMPC::coefficient: 20000.0 outside the range -10000 … 10000 [µm/m]"
    )
    expect(page.locator("#tempc-msg-1")).to_have_class("msg error")
    assert served.service.read_name("TEMPC::coefficient", 1) == 4000.0
    box.fill("abc")
    box.press("Enter")
    expect(page.locator("#tempc-msg-1")).to_have_text("TEMPC::coefficient: 'abc' is not a number")


def test_save_and_reload_buttons(page, served):
    from playwright.sync_api import expect

    box = tempc_input(page, 2, "TEMPC::coefficient")
    box.fill("33.5")
    box.press("Enter")
    expect(page.locator("#tempc-msg-2")).to_have_text("TEMPC::coefficient := 33.5")
    page.click("#save")
    lists = served.machine.cfg.startup_path.parent
    expect(page.locator("#command-result")).to_have_text(f"saved: {lists / 'achsmd2.lis'}")
    assert "lr_param.temp_comp_coefficient 33.5" in (lists / "achsmd2.lis").read_text("utf-8")
    page.click("#reload")
    expect(page.locator("#command-result")).to_contain_text("reloaded (")


def test_new_errors_and_faults_show_up(page, served):
    from playwright.sync_api import expect

    served.service.report("coolant pressure low (from the test)")
    expect(page.locator("#errors tbody tr").first).to_contain_text(
        "coolant pressure low (from the test)", timeout=WAIT_MS
    )
    served.service.inject_fault("ads:error=0x707,count=2")
    expect(page.locator("#faults")).to_have_text(
        "Injected faults: #1 ads:error=0x707,count=2 (0 hits)", timeout=WAIT_MS
    )


# ---------------------------------------------------------------------- without a browser


def test_tables_in_engineering_units():
    cfg = load_machine(default_startup_list())
    by = {(t["axis"], t["kind"]): t for t in tables(cfg, (1, 2, 3, 4))}
    assert sorted(by) == [
        (1, "frict"),
        (1, "lsec"),
        (2, "lsec"),
        (3, "cross"),
        (3, "plane"),
        (3, "scatter"),
        (4, "lsec"),
    ]
    x = by[(1, "lsec")]
    # lists/achskw1.lis: kw_startpos -5000000, interval 100000, table[1].pos 15 (0.1 µm)
    assert x["x"][:2] == [-500.0, -490.0] and x["series"]["positive"][:2] == [0.0, 1.5]
    assert (x["x_unit"], x["y_unit"]) == ("mm", "µm")
    plane = by[(3, "plane")]
    # lists/achskw3.lis: start -5000000, interval 500000, table[0][0] 15, [0][1] 12
    assert plane["x"][:2] == [-500.0, -450.0] and plane["z"][0][:2] == [1.5, 1.2]
    assert by[(4, "lsec")]["x_unit"] == "°"


def test_live_payload_of_a_stepped_machine():
    m = Machine(load_machine(default_startup_list()), homed=True)
    service = ObjectService(m)
    service.run_nc("G91 G01 X1 F6000")
    service.step(500)
    view = LiveView(service.dictionary, m.cfg, service.axes)
    live = view.push(service.snapshot, 1.5)
    x = live["axes"]["1"]
    assert live["cycle"] == 500 and x["command_position"] == 1.0  # mm
    assert x["tempc"]["coefficient"] == 4000.0 and x["comps"]["TEMP"][:2] == [True, True]
    assert x["comps"]["PLANE"][1] is None  # the manual has no effective flag for it
    assert len(view.trend_point(live)) == 12


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
