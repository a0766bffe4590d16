"""Memory benchmark (docs/design.md §11): resident size of a running geo-server.

Starts the server in a subprocess (the default machine with `geo-server run --homed`;
N fully configured axes with `bench/server.py --demo-axes N`, i.e.
`support.machines.full_machine(N)`), lets it run a few hundred real-time 1 ms
cycles, and reads VmRSS (and the peak VmHWM) from /proc/<pid>/status; then drives 2 s
of read load on all three transports and reads them again. A bare interpreter that
only imports what the server imports is the baseline.

    python bench/memory.py [--quick] [--axes 32] [--out FILE]
"""

from __future__ import annotations

import argparse
import time

from common import (
    PYTHON,
    ServerProcess,
    bench_server_argv,
    emit,
    free_ports,
    geo_server_argv,
    get_status,
    rss_kib,
    start_geo,
    table,
)
from scheduler import LoadProcess

IMPORTS = (
    "import numpy, zenoh, geo_server.cli, geo_server.service, "
    "geo_server.transports.zenoh.server, geo_server.transports.modbus.server, "
    "geo_server.transports.ads.server, "
    "geo_server.listfile, geo_server.kernel, time; print('ready', flush=True); time.sleep(60)"
)


def baseline() -> dict[str, int]:
    """RSS of an interpreter that has imported the server's modules and nothing else."""
    with ServerProcess([PYTHON, "-c", IMPORTS], "imports") as p:
        end = time.monotonic() + 30
        while "ready" not in p.log_text() and time.monotonic() < end:
            time.sleep(0.05)
        return rss_kib(p.pid)


def total_rss(pids: list[int]) -> dict[str, int]:
    """VmRSS / VmHWM summed over the server and its GEO-cycle process (pages they share,
    such as the interpreter's, count twice: an upper bound)."""
    out = {"VmRSS": 0, "VmHWM": 0}
    for pid in pids:
        for key, value in rss_kib(pid).items():
            out[key] += value
    return out


def server_rss(argv_for: object, cycles: int, load_s: float) -> dict[str, object]:
    """RSS after `cycles` cycles, and after `load_s` seconds of read load."""
    zp, mp, ap = free_ports(3)
    ports = {"zenoh": zp, "modbus": mp, "ads": ap}
    with ServerProcess(argv_for(ports), "memory") as srv:  # type: ignore[operator]
        session = start_geo(srv, ports, min_cycles=cycles)
        try:
            st = get_status(session)
            pids = [srv.pid] + ([st["cycle_pid"]] if st.get("cycle_pid") else [])
            idle = total_rss(pids)
            gen = LoadProcess(ports, load_s)
            try:
                gen.start()
            finally:
                load = gen.result()
            loaded = total_rss(pids)
            requests = sum(o["ok"] for o in load["ops"].values())
        finally:
            session.close()
    return {"idle": idle, "loaded": loaded, "cycles": st["cycle"], "requests": requests}


def run(args: argparse.Namespace) -> str:
    rows = []
    base = baseline()
    rows.append(["Python + server imports (no machine)", "–", "–", base["VmRSS"] / 1024, "–", "–"])
    cases = [
        ("default machine (4 axes, `geo-server run --homed`)", lambda p: geo_server_argv(1.0, p)),
        *(
            (
                f"`full_machine({n})` ({n} fully configured axes)",
                lambda p, n=n: bench_server_argv(1.0, p, demo_axes=n),
            )
            for n in args.axes
        ),
    ]
    for label, argv_for in cases:
        r = server_rss(argv_for, args.cycles, args.load_seconds)
        idle, loaded = r["idle"], r["loaded"]
        print(f"  {label}: {idle['VmRSS'] / 1024:.1f} MiB idle", flush=True)
        rows.append(
            [
                label,
                r["cycles"],
                r["requests"],
                idle["VmRSS"] / 1024,
                loaded["VmRSS"] / 1024,
                loaded["VmHWM"] / 1024,
            ]
        )
    md = (
        "### Memory: resident size of the server (MiB, /proc/<pid>/status)\n\n"
        "Server process plus its GEO-cycle process (`--cycle-in process`, the default), "
        "summed. "
        f"RSS after ≥ {args.cycles} real-time 1 ms cycles with Zenoh, Modbus and ADS up "
        f"(idle), then after {args.load_seconds:g} s of read load on all three (loaded); "
        "peak = VmHWM.\n\n"
    )
    md += table(
        ["server", "cycles", "load requests", "RSS idle", "RSS loaded", "peak"],
        rows,
        align="lrrrrr",
    )
    return md


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer cycles, shorter load")
    ap.add_argument("--axes", default="32", help="demo machines to measure (default 32)")
    ap.add_argument("--cycles", type=int, default=None, help="cycles before (default 500)")
    ap.add_argument("--load-seconds", type=float, default=None, help="default 2; quick 1")
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    args.axes = [int(x) for x in args.axes.split(",") if x]
    args.cycles = args.cycles or (300 if args.quick else 500)
    args.load_seconds = args.load_seconds or (1.0 if args.quick else 2.0)
    emit(run(args), args.out)


if __name__ == "__main__":
    main()
