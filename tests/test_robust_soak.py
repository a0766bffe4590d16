"""A bounded soak: mixed load on all transports for `SOAK_S` seconds against the real-time
GEO cycle.

The server runs in this process (cycle thread + transports on the loop thread), an NC
program keeps axis X travelling, and the load comes from another process
(`tests/robust/soak_load.py`, as real clients would — not sharing the server's GIL): per
transport a `Checker` (write its own object, read it back, read the cycle count — values
checked) and a `Reader` (Zenoh wildcard get + status, Modbus block read, ADS sum read of
a whole axis), plus an ADS on-change notification and a Zenoh subscription.

It asserts behaviour only: no client error (every request answered, every value read
back as written), no cycle error, notifications and publications delivered, the GEO
cycle not stalled at the end.
Timing figures (rate of nominal, lateness, overruns) are printed for the log; they are
measured properly by `bench/soak.py`, never asserted here: on a loaded 2-core machine
they vary from run to run.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from robust.harness import FullServer

SOAK_S = 10.0
LOAD = Path(__file__).parent / "robust" / "soak_load.py"


@pytest.mark.slow
def test_soak_mixed_load_on_all_transports(loop_thread, lists_copy):
    with FullServer(loop_thread, lists_copy) as srv:
        # something moves all the time: X travels back and forth (NC program over Zenoh)
        with srv.client("zenoh") as c:
            c.nc("N10 G90 G01 X50 F60000\nN20 G01 X0\nN30 $GOTO N10")
        ep = srv.endpoints
        child = subprocess.Popen(
            [
                sys.executable,
                str(LOAD),
                ep.machine_name,
                ep.zenoh_endpoint,
                str(ep.modbus_port),
                str(ep.ads_port),
                str(ep.axes),
                str(SOAK_S),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert child.stdout is not None
            assert json.loads(child.stdout.readline()) == {"started": True}
            cycle0, overruns0 = srv.cycle, srv.machine.overruns
            srv.scheduler.stats.__init__()  # lateness of the soak only
            t0 = time.monotonic()
            out, _ = child.communicate(timeout=SOAK_S + 60)
            elapsed = time.monotonic() - t0
            cycles, overruns = srv.cycle - cycle0, srv.machine.overruns - overruns0
        finally:
            if child.poll() is None:
                child.kill()
                child.communicate(timeout=10)
        assert child.returncode == 0
        load = json.loads(out.strip().splitlines()[-1])
        status = srv.service.status()
        report = {
            "seconds": round(elapsed, 1),
            "cycles": cycles,
            "rate_of_nominal": round(cycles * srv.machine.cycle_s / elapsed, 3),
            "overruns": overruns,
            "lateness_p50_us": round(status["lateness_p50_us"]),
            "lateness_p99_us": round(status["lateness_p99_us"]),
            "lateness_max_us": round(status["lateness_max_us"]),
            **load,
        }
        print("soak:", report)
        assert not load["errors"], report
        assert all(n >= 20 for n in load["requests"].values()), report
        assert load["ads_notifications"] > 0 and load["zenoh_publications"] > 0, report
        assert srv.scheduler.cycle_errors == 0
        assert status["stalled"] is False, report
