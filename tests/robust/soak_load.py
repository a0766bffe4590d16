"""Load generator of tests/test_robust_soak.py, in its own process (as real clients are:
the server's GIL is not shared with the load).

    python soak_load.py <machine> <zenoh endpoint> <modbus port> <ads port> <axes> <seconds>

Runs a `Checker` and a `Reader` per transport, an ADS on-change notification and a Zenoh
subscription, for <seconds>; prints one JSON line: requests per load, errors, samples.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: conftest, robust

from robust.harness import Checker, Endpoints, Reader


def main() -> None:
    machine, zenoh_ep, mport, aport, axes, seconds = sys.argv[1:7]
    ep = Endpoints(machine, zenoh_ep, int(mport), int(aport), int(axes))
    notes: list[int] = []
    published: list[bytes] = []
    ads_sub = ep.client("ads")
    ads_sub.subscribe("TEMPC::actual_offset", 1, lambda v, _t: notes.append(v))
    z_sub = ep.client("zenoh")
    z_sub.subscribe(f"cnc/{machine}/axis/4/tempc/*", lambda _k, v: published.append(v))
    load = [Checker(ep, via, pause=0.001).start() for via in ("zenoh", "modbus", "ads")]
    load += [Reader(ep, via).start() for via in ("zenoh", "modbus", "ads")]
    print(json.dumps({"started": True}), flush=True)
    time.sleep(float(seconds))
    for x in load:
        x.stop()
    ads_sub.close()
    z_sub.close()
    print(
        json.dumps(
            {
                "requests": {
                    f"{type(x).__name__.lower()}-{x.via}": getattr(x, "rounds", None)
                    or getattr(x, "requests", 0)
                    for x in load
                },
                "errors": {
                    f"{type(x).__name__.lower()}-{x.via}": x.errors[:5] for x in load if x.errors
                },
                "ads_notifications": len(notes),
                "zenoh_publications": len(published),
            }
        ),
        flush=True,
    )


if __name__ == "__main__":
    main()
