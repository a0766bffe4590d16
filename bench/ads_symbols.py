"""ADS symbol access benchmark (docs/design.md §9): a read by handle vs a read by address.

One geo-server (`geo-server run --homed`, 1 ms real-time cycle, its own process); one
pyads connection reads TEMPC::coefficient of axis 1 back to back (closed loop), either as
`Read(0x120300, 0x10043)` or as `Read(0xF005, handle)` with the handle of
`GEO.X.TEMPC.coefficient` (0xF003). Rounds alternate the two; samples of all rounds are
pooled. Reported: p50 / p99 round trip and the ratio handle / address (target ≤ 1.1).

    python bench/ads_symbols.py [--quick] [--rounds N] [--seconds S] [--out FILE]
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np
from common import (
    HOST,
    ServerProcess,
    address,
    emit,
    free_ports,
    geo_server_argv,
    start_geo,
    summary_us,
    table,
    timed_loop,
)

#: TEMPC::coefficient of axis 1 (from the dictionary)
COEFF = address("TEMPC::coefficient")

IG, IO = COEFF.index_group, COEFF.index_offset
NAME = "GEO.X.TEMPC.coefficient"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 rounds of 0.5 s")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--seconds", type=float, default=2.0, help="per round and kind")
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    rounds, seconds = (2, 0.5) if args.quick else (args.rounds, args.seconds)

    import pyads

    zport, mport, aport = free_ports(3)
    ports = {"zenoh": zport, "modbus": mport, "ads": aport}
    server = ServerProcess(geo_server_argv(1.0, ports, extra=["--ads-udp-port", "0"]), "geo")
    samples: dict[str, list[np.ndarray]] = {"address": [], "handle": []}
    rates: dict[str, list[float]] = {"address": [], "handle": []}
    try:
        start_geo(server, ports).close()
        conn = pyads.Connection("10.77.0.1.1.1", 551, f"{HOST}:{aport}")
        conn.open()
        try:
            handle = conn.get_handle(NAME)
            calls = {
                "address": lambda: conn.read(IG, IO, pyads.PLCTYPE_LREAL),
                "handle": lambda: conn.read(0xF005, handle, pyads.PLCTYPE_LREAL),
            }
            assert calls["address"]() == calls["handle"]()
            for _, kind in itertools.product(range(rounds), ("address", "handle")):
                rtt, rate = timed_loop(calls[kind], 200_000, seconds)
                samples[kind].append(rtt)
                rates[kind].append(rate)
            conn.release_handle(handle)
        finally:
            conn.close()
    finally:
        server.stop()
    rows = []
    stats = {k: summary_us(np.concatenate(v)) for k, v in samples.items()}
    for kind in ("address", "handle"):
        s = stats[kind]
        rows.append([f"read by {kind}", s["p50"], s["p99"], float(np.median(rates[kind])), s["n"]])
    ratio50 = stats["handle"]["p50"] / stats["address"]["p50"]
    ratio99 = stats["handle"]["p99"] / stats["address"]["p99"]
    md = "### ADS symbol access (pyads, one connection, closed loop)\n\n"
    md += table(["request", "p50 µs", "p99 µs", "req/s", "samples"], rows)
    md += f"\nhandle / address: p50 {ratio50:.3f}×, p99 {ratio99:.3f}× (target ≤ 1.1)\n"
    emit(md, args.out)


if __name__ == "__main__":
    main()
