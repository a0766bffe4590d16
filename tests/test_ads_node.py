"""An ADS client nobody here wrote, in its default settings: Node.js `ads-client` (npm,
version 2) against geo-server (docs/design.md §9 "real tooling").

Its `connect()` registers an AMS port at the router (AMS/TCP 0x1000), reads the system
state on AMS port 10000, subscribes to the ADS state (0xF100) and the symbol version
(0xF008), reads the device info, the upload info (0xF00F) and the symbol version; then
this test reads by address and by symbol, writes by symbol and subscribes. `.ci/run`
installs Node.js (Debian) and the package (npm registry, tests/node/package-lock.json);
elsewhere the test is skipped unless GEO_SERVER_REQUIRE_NODE=1 (as in CI) makes a missing
client a failure.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import run_in
from test_ads_server import start_server

from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService

NODE_DIR = Path(__file__).parent / "node"
NODE = shutil.which("node")
INSTALLED = (NODE_DIR / "node_modules" / "ads-client").is_dir()
REQUIRED = os.environ.get("GEO_SERVER_REQUIRE_NODE") == "1"

pytestmark = pytest.mark.skipif(
    not REQUIRED and (NODE is None or not INSTALLED),
    reason="node or tests/node/node_modules/ads-client missing (npm ci --prefix tests/node)",
)


@pytest.mark.realtime
def test_ads_client_connects_with_default_settings(loop_thread, machine) -> None:
    assert NODE is not None and INSTALLED, "GEO_SERVER_REQUIRE_NODE=1 but no ads-client"
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    sched.start()
    srv = start_server(loop_thread, service)
    try:
        r = subprocess.run(
            [NODE, str(NODE_DIR / "ads_client_check.js"), str(srv.port)],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=NODE_DIR,
        )
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout.strip().splitlines()[-1])
    finally:
        run_in(loop_thread, srv.close())
        sched.stop()
    conn = out["connection"]
    assert conn["connected"] is True and conn["localAmsNetId"] == "127.0.0.1.1.1"
    assert conn["localAdsPort"] >= 32768  # a port of its own from the router
    info = out["uploadInfo"]
    # the GEO task's port: the COM task's objects (port 553) have no symbols there
    geo = [o for o in machine.dictionary.objects if o.group != "com"]
    axis_objects = sum(1 for o in geo if o.scope == "axis")
    machine_objects = len(geo) - axis_objects
    assert info["version"] == 2
    assert info["symbolCount"] == 4 * axis_objects + machine_objects  # X, Y, Z, C
    assert info["dataTypeCount"] == 6
    assert out["symbolVersion"] == 1
    # readTcSystemExtendedState (index group 0xF0 on port 10000): RUN, never restarted
    assert out["extendedState"] == {"adsState": "Run", "restartIndex": 0}
    assert out["readRaw"] == 4000.0  # TEMPC::coefficient of X, 000 p.24
    assert out["readValue"] == 4000.0
    assert out["readBool"] is True
    assert out["readString"] == "1=X 2=Y 3=Z 4=C"
    assert out["afterWrite"] == 77
    assert out["handle"] == {"size": 8, "dataType": "LREAL"}
    assert out["readByHandle"] == 12.5
    assert out["multi"] == ["DINT", 0x710]
    assert out["badWrite"] == 0x706  # the same range check as by address
    # issue 45 #10: the text pyads reads too (tests/test_ads_tooling.py), in ASCII
    assert out["lastError"] == (
        "TEMPC::coefficient: write refused: TEMPC::coefficient: 20000.0 outside the range "
        "-10000 ... 10000 [um/m] (ADS 0x706)"
    )
    assert out["unknown"] == 0x710
    samples = out["samples"]
    # every 10 ms = 10 cycles, each sample its own cycle's count (none skipped)
    assert len(samples) == 3 and samples[1] - samples[0] == samples[2] - samples[1] == 10
    assert srv.stats.router_commands >= 1
