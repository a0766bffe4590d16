"""Soak: a bounded run of mixed load on every transport against one real-time server.

The default machine (`bench/server.py`, i.e. `geo-server run --homed`, 1 ms real time)
serves `bench/load.py --mix soak` for a fixed time: reads on all three transports, writes
of TEMPC parameters on each (Zenoh `coefficient`, Modbus `offset_0`, ADS `position_0`),
ADS sum reads, an NC line every 2 s over Zenoh (X moves ±50 mm), an ADS on-change
notification on X's `SIM::command_position` and a Zenoh subscription on
`cnc/local/axis/1/**`. Reported: lateness over the whole soak, overruns, cycle errors,
per-operation counts, errors and round trips, notifications/publications received, the
server's RSS over time and how it stops.

    python bench/soak.py [--quick] [--seconds S] [--out FILE]
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import (
    ServerProcess,
    bench_server_argv,
    emit,
    free_ports,
    get_status,
    rss_kib,
    start_geo,
    table,
)
from scheduler import LoadProcess, window


def soak(seconds: float, cycle_ms: float) -> dict[str, Any]:
    zp, mp, ap = free_ports(3)
    ports = {"zenoh": zp, "modbus": mp, "ads": ap}
    expected = int((seconds + 90) / (cycle_ms / 1000))
    rss: list[tuple[float, int]] = []
    with tempfile.TemporaryDirectory(prefix="bench-soak-") as tmp:
        dump = Path(tmp) / "stats.npz"
        argv = bench_server_argv(cycle_ms, ports, stats_size=expected, dump=dump)
        with ServerProcess(argv, "soak") as srv:
            session = start_geo(srv, ports, min_cycles=500)
            try:
                gen = LoadProcess(ports, seconds, mix="soak")
                try:
                    gen.start()
                    st0 = get_status(session)
                    t0 = time.monotonic()
                    rss.append((0.0, rss_kib(srv.pid)["VmRSS"]))
                    done = threading.Event()
                    waiter = threading.Thread(
                        target=lambda: (gen.proc.wait(seconds + 60), done.set()), daemon=True
                    )
                    waiter.start()
                    step = max(seconds / 12, 1.0)
                    while not done.wait(step):  # at most ~12 + samples: bounded
                        rss.append((time.monotonic() - t0, rss_kib(srv.pid)["VmRSS"]))
                    st1 = get_status(session)
                    rss.append((time.monotonic() - t0, rss_kib(srv.pid)["VmRSS"]))
                finally:
                    load = gen.result()
                errors_seen = _errors(session)
            finally:
                session.close()
            code = srv.stop(timeout=15)
            stop_s = srv.stop_seconds
            log_lines = srv.log_text().splitlines()
        data = np.load(dump)
        w = window(data, st0["cycle"], st1["cycle"], cycle_ms)
        cycle_errors = int(data["cycle_errors"])
    return {
        "seconds": seconds,
        **w,
        "overruns": st1["overruns"] - st0["overruns"],
        "cycle_errors": cycle_errors,
        "load": load,
        "rss": rss,
        "exit_code": code,
        "stop_s": stop_s,
        "server_errors": errors_seen,
        "server_log": _log_problems(log_lines),
    }


def _log_problems(lines: list[str], keep: int = 12) -> list[str]:
    """The server log's error lines and the last line of each traceback (bounded)."""
    out: list[str] = []
    for i, line in enumerate(lines):
        if "Traceback" in line:
            j = i + 1
            while j < len(lines) and lines[j].startswith((" ", "\t")):
                j += 1
            if j < len(lines):
                out.append("  -> " + lines[j])
        elif "ERROR" in line or "failed" in line:
            out.append(line)
    uniq = list(dict.fromkeys(out))
    return uniq[:keep]


def _errors(session: Any) -> int:
    """How many entries the server's `cnc/local/errors` list holds (≤ 100)."""
    import json

    for reply in session.get("cnc/local/errors", timeout=2.0):
        if reply.ok is not None:
            return len(json.loads(reply.ok.payload.to_bytes()))
    return -1


def run(args: argparse.Namespace) -> str:
    r = soak(args.seconds, args.cycle_ms)
    load = r["load"]
    md = (
        f"### Soak: {r['seconds']:g} s of mixed load on all transports "
        f"(default machine, {args.cycle_ms:g} ms real time)\n\n"
    )
    md += table(
        [
            "cycles",
            "lateness p50",
            "p99",
            "max",
            "> 100 µs",
            "overruns",
            "cycles skipped",
            "max gap",
            "cycle p50",
            "cycle p99",
            "cycle errors",
        ],
        [
            [
                r["cycles"],
                r["p50"],
                r["p99"],
                r["max"],
                f"{r['late_100']:.1f} %",
                r["overruns"],
                r["missed"],
                r["max_gap"],
                r["cycle_p50"],
                r["cycle_p99"],
                r["cycle_errors"],
            ]
        ],
        align="rrrrrrrrrrr",
    )
    rows = [
        [
            name,
            o["ok"],
            o["errors"],
            ", ".join(f"{k} {v}" for k, v in o["error_kinds"].items()),
            o["ok"] / r["seconds"],
            o["p50_us"],
            o["p99_us"],
            o["max_us"],
        ]
        for name, o in load["ops"].items()
    ]
    md += "\n" + table(
        ["operation", "ok", "errors", "error kinds", "per s", "p50 µs", "p99 µs", "max µs"],
        rows,
        align="lrrlrrrr",
    )
    examples = [
        f"- {name}: {kind}: `{msg}`"
        for name, o in load["ops"].items()
        for kind, msg in o.get("error_examples", {}).items()
    ]
    if examples:
        md += "\nFirst error of each kind:\n\n" + "\n".join(examples) + "\n"
    if r["server_log"]:
        md += "\nServer log (errors, distinct):\n\n```\n" + "\n".join(r["server_log"]) + "\n```\n"
    rec = load.get("received", {})
    rss = r["rss"]
    md += (
        f"\nReceived: {rec.get('ads_note', 0)} ADS notifications "
        f"({rec.get('ads_note', 0) / r['seconds']:.0f}/s), {rec.get('zenoh_pub', 0)} Zenoh "
        f"publications on `cnc/local/axis/1/**`. Load setup errors: "
        f"{load.get('setup_errors') or 'none'}; stuck client threads: "
        f"{load.get('stuck_threads') or 'none'}. Server RSS: "
        f"{rss[0][1] / 1024:.1f} MiB at the start, {rss[-1][1] / 1024:.1f} MiB at the end "
        f"(samples: {', '.join(f'{t:.0f} s {k / 1024:.1f}' for t, k in rss)}). "
        f"Server errors list: {r['server_errors']} entries. Stopped by SIGTERM in "
        f"{r['stop_s'] or 0:.2f} s, exit code {r['exit_code']}.\n"
    )
    return md


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20 s")
    ap.add_argument("--seconds", type=float, default=None, help="default 120; quick 20")
    ap.add_argument("--cycle-ms", type=float, default=1.0)
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    args.seconds = args.seconds or (20.0 if args.quick else 120.0)
    emit(run(args), args.out)


if __name__ == "__main__":
    main()
