"""Transport benchmark (docs/design.md §11): single-object read round trip vs the bare transport.

For each transport the same client library reads one object back to back (closed loop,
one request in flight) first from a trivial server of that transport (`bench/bare.py`)
and then from geo-server (`geo-server run --homed`, GEO cycle in real time at 1 ms), each
server alone in its own process. Rounds alternate bare and geo-server; the samples of all
rounds are pooled. Reported: p50/p99 round trip, requests/s and the ratios geo/bare
(latency) and bare/geo (throughput) — both > 1 mean geo-server is slower.

    python bench/transports.py [--quick] [--rounds N] [--seconds S] [--gap-ms G] [--out FILE]

`--gap-ms 10`: each read after a pause of 0 to 10 ms drawn at random (not timed), so the
exact engine has cycles to catch up on before it answers; requests/s then counts the
pauses too and is not compared.

The object is TEMPC::coefficient of axis 1 (REAL64): Zenoh key
`cnc/local/ads/551/0x120300/0x10043` (raw bytes; also the JSON key
`cnc/local/axis/1/tempc/coefficient`), Modbus FC 3 unit 1 registers 268…271, ADS Read
0x120300/0x10043 (8 bytes) via `pyads.Connection.read`.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Callable
from typing import Any

import numpy as np
from common import (
    BENCH,
    HOST,
    PYTHON,
    ServerProcess,
    address,
    emit,
    free_port,
    free_ports,
    geo_server_argv,
    start_geo,
    summary_us,
    table,
    timed_loop,
    wait_port,
)

#: the object every client reads: TEMPC::coefficient of axis 1 (from the dictionary)
COEFF = address("TEMPC::coefficient", 1)
RAW_KEY, JSON_KEY = COEFF.raw_key, COEFF.named_key
IG, IO = COEFF.index_group, COEFF.index_offset
_netids = itertools.count(2)


# ---------------------------------------------------------------------- clients


def zenoh_reader(port: int, key: str) -> tuple[Callable[[], Any], Callable[[], None]]:
    """(read once, close) with a plain zenoh peer session get."""
    from common import zenoh_session

    session = zenoh_session(f"tcp/{HOST}:{port}")

    def read() -> bytes:
        for reply in session.get(key, timeout=2.0):
            if reply.ok is None:
                raise RuntimeError(reply.err.payload.to_bytes())
            return reply.ok.payload.to_bytes()
        raise TimeoutError(key)

    return read, session.close


def modbus_reader(port: int) -> tuple[Callable[[], Any], Callable[[], None]]:
    """(read once, close) with pymodbus' sync client, FC 3 of 4 registers."""
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(HOST, port=port, timeout=2)
    if not client.connect():
        raise ConnectionError(f"modbus {HOST}:{port}")

    def read() -> list[int]:
        rr = client.read_holding_registers(COEFF.register, count=COEFF.registers, device_id=1)
        if rr.isError():
            raise RuntimeError(rr)
        return rr.registers

    return read, client.close


def ads_reader(port: int) -> tuple[Callable[[], Any], Callable[[], None]]:
    """(read once, close) with `pyads.Connection.read` (a fresh NetId per endpoint)."""
    import pyads

    netid = f"127.0.{next(_netids)}.1.1.1"
    conn = pyads.Connection(netid, 551, f"{HOST}:{port}")
    conn.open()
    conn.set_timeout(2000)

    def read() -> float:
        return conn.read(IG, IO, pyads.PLCTYPE_LREAL)

    return read, conn.close


# ---------------------------------------------------------------------- cases

#: (row label, client library, bare server kind, client factory on the bare server,
#:  client factory on geo-server given its ports)
CASES: list[tuple[str, str, str, Any, Any]] = [
    (
        "Zenoh get, raw ADS key",
        "zenoh session.get",
        "zenoh",
        lambda p: zenoh_reader(p, RAW_KEY),
        lambda ports: zenoh_reader(ports["zenoh"], RAW_KEY),
    ),
    (
        "Zenoh get, JSON key",
        "zenoh session.get",
        "zenoh",
        lambda p: zenoh_reader(p, JSON_KEY),
        lambda ports: zenoh_reader(ports["zenoh"], JSON_KEY),
    ),
    (
        "Modbus FC 3, 4 registers",
        "pymodbus ModbusTcpClient",
        "modbus",
        modbus_reader,
        lambda ports: modbus_reader(ports["modbus"]),
    ),
    (
        "ADS Read 8 bytes (vs asyncio responder)",
        "pyads Connection.read",
        "ads",
        ads_reader,
        lambda ports: ads_reader(ports["ads"]),
    ),
    (
        "ADS Read 8 bytes (vs pyads AdsTestServer)",
        "pyads Connection.read",
        "pyads",
        ads_reader,
        lambda ports: ads_reader(ports["ads"]),
    ),
]


#: pause before each timed read, drawn from 0 to this (ms; `--gap-ms`)
GAP_MS = [0.0]


def measure(factory: Any, arg: Any, n: int, seconds: float) -> tuple[np.ndarray, float]:
    read, close = factory(arg)
    try:
        read()  # first answer proves the server is there
        return timed_loop(read, n, seconds, gap_ms=GAP_MS[0])
    finally:
        close()


def bare_round(samples: dict, n: int, seconds: float) -> None:
    """One round against every bare server (one at a time, each in its own process)."""
    for label, _lib, kind, bare_factory, _geo in CASES:
        port = free_port()
        argv = [PYTHON, str(BENCH / "bare.py"), kind, "--port", str(port)]
        with ServerProcess(argv, f"bare-{kind}") as srv:
            wait_port(port, 20.0, srv.proc)
            rtt, rps = measure(bare_factory, port, n, seconds)
        samples[label]["bare"].append((rtt, rps))
        print(f"  bare  {label}: p50 {np.median(rtt):.0f} µs, {rps:.0f} req/s", flush=True)


def geo_round(
    samples: dict, n: int, seconds: float, cycle_ms: float, cycle_in: str, engine: str
) -> dict[str, Any]:
    """One round against one geo-server (real-time cycle) for every case."""
    zp, mp, ap = free_ports(3)
    ports = {"zenoh": zp, "modbus": mp, "ads": ap}
    argv = geo_server_argv(cycle_ms, ports, extra=["--cycle-in", cycle_in], engine=engine)
    with ServerProcess(argv, f"geo-server-{cycle_in}") as srv:
        session = start_geo(srv, ports)
        try:
            for label, _lib, _kind, _bare, geo_factory in CASES:
                rtt, rps = measure(lambda p, f=geo_factory: f(p), ports, n, seconds)
                samples[label][cycle_in].append((rtt, rps))
                print(
                    f"  geo ({cycle_in})  {label}: p50 {np.median(rtt):.0f} µs, {rps:.0f} req/s",
                    flush=True,
                )
            from common import get_status

            return get_status(session)
        finally:
            session.close()


def run(args: argparse.Namespace) -> str:
    modes = args.cycle_in
    samples: dict[str, dict[str, list]] = {
        c[0]: {"bare": [], **{m: [] for m in modes}} for c in CASES
    }
    status: dict[str, dict[str, Any]] = {}

    def geo_rounds() -> None:
        for m in modes:
            status[m] = geo_round(
                samples, args.requests, args.seconds, args.cycle_ms, m, args.engine
            )

    for r in range(args.rounds):
        print(f"round {r + 1}/{args.rounds}", flush=True)
        if r % 2 == 0:
            bare_round(samples, args.requests, args.seconds)
            geo_rounds()
        else:
            geo_rounds()
            bare_round(samples, args.requests, args.seconds)
    rows = []
    for (label, lib, _kind, _b, _g), mode in [(c, m) for c in CASES for m in modes]:
        b = samples[label]["bare"]
        g = samples[label][mode]
        bs = summary_us(np.concatenate([x[0] for x in b]))
        gs = summary_us(np.concatenate([x[0] for x in g]))
        brps = float(np.median([x[1] for x in b]))
        grps = float(np.median([x[1] for x in g]))
        rows.append(
            [
                label,
                f"{lib}, cycle {mode}",
                bs["p50"],
                bs["p99"],
                brps,
                gs["p50"],
                gs["p99"],
                grps,
                f"{gs['p50'] / bs['p50']:.2f}×",
                f"{gs['p99'] / bs['p99']:.2f}×",
                f"{brps / grps:.2f}×",
            ]
        )
    md = (
        f"### Transports: single-object read vs the bare transport "
        f"(geo-server cycle {args.cycle_ms} ms real time, {args.engine} engine)\n\n"
        f"{args.rounds} rounds × up to {args.requests} sequential reads or {args.seconds} s "
        "per case and server, pooled"
        + (
            f", each read after a pause of 0–{args.gap_ms:g} ms drawn at random (req/s "
            "counts the pauses)"
            if args.gap_ms
            else ""
        )
        + "; round trip in µs; ratio > 1 = geo-server slower "
        "(target ≤ 1.15×; ADS: no slower than pyads' AdsTestServer). *cycle thread*: the "
        "GEO cycle on a thread of the server (`--cycle-in thread`, the exact engine's "
        "default); *cycle process*: `--cycle-in process` (the punctual engine's default)."
        "\n\n"
    )
    md += table(
        [
            "read",
            "client",
            "bare p50",
            "bare p99",
            "bare req/s",
            "geo p50",
            "geo p99",
            "geo req/s",
            "p50 ratio",
            "p99 ratio",
            "req/s ratio",
        ],
        rows,
        align="llrrrrrrrrr",
    )
    for mode, st in status.items():
        md += (
            f"\ngeo-server (cycle {mode}) during the last round: lateness p50 "
            f"{st['lateness_p50_us']:.0f} µs, p99 {st['lateness_p99_us']:.0f} µs, max "
            f"{st['lateness_max_us']:.0f} µs, overruns {st['overruns']}.\n"
        )
    return md


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 round of ≤ 1 s per case")
    ap.add_argument("--rounds", type=int, default=None, help="rounds (default 2; quick 1)")
    ap.add_argument("--seconds", type=float, default=None, help="per case (default 4; quick 1)")
    ap.add_argument("--requests", type=int, default=20_000, help="max reads per case")
    ap.add_argument("--cycle-ms", type=float, default=1.0)
    ap.add_argument("--cycle-in", default="thread,process", help="thread, process or both")
    ap.add_argument(
        "--engine", choices=("exact", "punctual"), default="exact", help="default: exact"
    )
    ap.add_argument(
        "--gap-ms", type=float, default=0.0, help="pause 0..G ms at random before each read"
    )
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    GAP_MS[0] = args.gap_ms
    args.rounds = args.rounds or (1 if args.quick else 2)
    args.cycle_in = [x for x in args.cycle_in.split(",") if x]
    args.seconds = args.seconds or (1.0 if args.quick else 4.0)
    emit(run(args), args.out)


if __name__ == "__main__":
    main()
