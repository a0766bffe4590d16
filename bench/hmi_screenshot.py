"""The README's screenshot of the web HMI (docs/img/hmi.png), made the way a user sees it.

The default machine in real time (exact engine) with its twin warming up fast
(`--time-scale`), every axis moving back and forth, a spindle heat source on and an
edited TEMPC coefficient; after `--seconds` of trends, headless Chromium (Debian's,
driven by Playwright) photographs the page.

    python bench/hmi_screenshot.py [--out docs/img/hmi.png] [--seconds 20]
"""

from __future__ import annotations

import argparse
import asyncio
import threading
import time

from geo_server import access, jit
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.web import CHROMIUM, CHROMIUM_ARGS
from geo_server.web.server import HmiOptions, HmiServer

PROGRAM = (
    "N10 G90 G01 X120 Y-60 Z40 C90 F6000\n"
    "N20 X-150 Y80 Z-30 C270\n"
    "N30 X40 Y10 Z0 C0\n"
    "N40 $GOTO N10\n"
)


def main() -> None:
    jit.load()  # the cycle's machine code before anything is timed (geo_server/jit.py)
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", default="docs/img/hmi.png")
    p.add_argument("--seconds", type=float, default=20.0)
    args = p.parse_args()
    machine = Machine(load_machine(default_startup_list()), homed=True, time_scale=300.0)
    sched = Scheduler(machine, mode="realtime", engine="exact")
    service = ObjectService(machine, sched)
    loop = asyncio.new_event_loop()
    threading.Thread(target=loop.run_forever, daemon=True).start()
    hmi = HmiServer(service, HmiOptions(port=0, machine="local"))
    asyncio.run_coroutine_threadsafe(hmi.start(), loop).result(10)
    sched.start()
    access.write_name(service, "TWIN::spindle_on", 0, True)
    access.write_name(service, "TEMPC::coefficient", 2, 45.0)
    machine.start_program(PROGRAM)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_ARGS))
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        page.goto(hmi.url)  # with the run's token, as printed
        time.sleep(args.seconds)
        page.screenshot(path=args.out, full_page=True)
        browser.close()
    asyncio.run_coroutine_threadsafe(hmi.close(), loop).result(10)
    sched.stop()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
