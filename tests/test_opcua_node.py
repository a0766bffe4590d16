"""An OPC UA client nobody here wrote: node-opcua's, from the npm registry
(tests/node/package-lock.json), reads the address space with units and range, and reads
and writes TEMPC::coefficient (README *OPC UA*).

`.ci/run` installs Node.js and the package; elsewhere the test is skipped unless
GEO_SERVER_REQUIRE_NODE=1 (as in CI) makes a missing client a failure.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import run_in

from geo_server import access
from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService
from geo_server.transports.opcua.server import OpcUaInterface, OpcUaOptions

NODE_DIR = Path(__file__).parent / "node"
NODE = shutil.which("node")
INSTALLED = (NODE_DIR / "node_modules" / "node-opcua-client").is_dir()
REQUIRED = os.environ.get("GEO_SERVER_REQUIRE_NODE") == "1"

pytestmark = pytest.mark.skipif(
    not REQUIRED and (NODE is None or not INSTALLED),
    reason="node or tests/node/node_modules/node-opcua-client missing (npm ci --prefix tests/node)",
)


@pytest.mark.realtime
@pytest.mark.slow
def test_node_opcua_reads_and_writes_the_coefficient(loop_thread, machine) -> None:
    assert NODE is not None and INSTALLED, "GEO_SERVER_REQUIRE_NODE=1 but no node-opcua-client"
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    sched.start()
    iface = OpcUaInterface({"local": service}, OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0"))
    run_in(loop_thread, iface.start(), timeout=60)
    try:
        r = subprocess.run(
            [NODE, str(NODE_DIR / "opcua_client_check.js"), iface.endpoint, "12.5"],
            capture_output=True,
            text=True,
            timeout=90,
            cwd=NODE_DIR,
        )
        assert r.returncode == 0, r.stderr
        # node-opcua writes its own notes to stdout as well: the result has a marker
        result = [line for line in r.stdout.splitlines() if line.startswith("RESULT ")]
        assert result, r.stdout + r.stderr
        out = json.loads(result[-1].removeprefix("RESULT "))
    finally:
        run_in(loop_thread, iface.close())
        sched.stop()
    assert out["ns"] >= 1
    assert out["browse"] == [
        "activated",
        "actual_offset",
        "coefficient",
        "f_is_active",
        "offset_0",
        "position_0",
    ]
    assert out["units"] == "µm/m"
    assert out["range"] == [-10000, 10000]
    assert out["before"] == 4000
    assert out["write"] == "Good"
    assert out["writeOutOfRange"] == "BadOutOfRange"
    assert out["after"] == 12.5
    assert access.read_name(service, "TEMPC::coefficient", 1) == 12.5
