"""Host CPU of a running geo-server (SPEC §13 baseline): how much of a core one machine costs.

`geo-server run --homed` (1 ms real-time cycle, every interface on) in its own process; the
CPU time (user + system, from /proc/<pid>/stat of the server and its GEO-cycle child) over
a window, as a share of one core:

- **idle**: nothing connected, nothing moving;
- **moving**: every axis of the default machine travelling back and forth (an NC program
  in a `$GOTO` loop).

Each case with both engines in the same run: the observation-exact engine (the default:
computes late, in batches, skips the cycles of a machine at rest; targets idle ≤ 1 %,
moving ≤ 15 %) and the punctual one (sleep, then spin to each deadline).

And a fleet of default machines at rest in one process (exact engine, every interface
on, nobody connected), without and with the web HMI (`--http`, no page open: one trend
sample a second per machine).

    python bench/cpu.py [--quick] [--seconds S] [--fleet N] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from common import (
    HOST,
    ServerProcess,
    emit,
    free_ports,
    geo_server_argv,
    start_geo,
    table,
    wait_port,
)
from engine import free_range, settle

TICKS = os.sysconf("SC_CLK_TCK")
#: every axis of the default machine back and forth, forever (X Y Z linear, C rotary)
MOVING = "N10 G90 G01 X200 Y150 Z-100 C90 F6000\nN20 X-200 Y-150 Z100 C-90\nN30 $GOTO N10\n"


def cpu_seconds(pid: int) -> float:
    """User + system CPU of `pid` and its children that are still running."""
    total = 0.0
    for p in [pid, *children(pid)]:
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / TICKS  # utime, stime
    return total


def children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(x) for x in text.split()]


def measure(extra: list[str], seconds: float, program: Path | None, engine: str) -> float:
    zport, mport, aport = free_ports(3)
    ports = {"zenoh": zport, "modbus": mport, "ads": aport}
    args = [*extra, "--ads-udp-port", "0"]
    if program is not None:
        args += ["--program", str(program)]
    argv = geo_server_argv(1.0, ports, extra=args, engine=engine)
    with ServerProcess(argv, "cpu") as server:
        start_geo(server, ports).close()
        time.sleep(1.0)  # start-up over
        c0, t0 = cpu_seconds(server.pid), time.monotonic()
        time.sleep(seconds)
        c1, t1 = cpu_seconds(server.pid), time.monotonic()
    return 100.0 * (c1 - c0) / (t1 - t0)


def measure_fleet(size: int, seconds: float, http: bool) -> float:
    """CPU of `--fleet-size size` at rest (exact engine), % of one core."""
    zport, aport, hport = free_ports(3)
    mbase = free_range(size)
    ports = {"zenoh": zport, "modbus": mbase, "ads": aport}
    extra = ["--fleet-size", str(size), "--ads-udp-port", "0"]
    if http:
        extra += ["--http", f"{HOST}:{hport}"]
    argv = geo_server_argv(1.0, ports, extra=extra, engine="exact")
    with ServerProcess(argv, f"cpu-fleet-{size}") as server:
        for p in (zport, aport, mbase + size - 1, *([hport] if http else [])):
            wait_port(p, 60.0, server.proc)
        settle(server.pid)
        time.sleep(1.0)
        c0, t0 = cpu_seconds(server.pid), time.monotonic()
        time.sleep(seconds)
        c1, t1 = cpu_seconds(server.pid), time.monotonic()
    return 100.0 * (c1 - c0) / (t1 - t0)


#: (the default place of the cycle differs: a thread for the exact engine, a process for
#: the punctual one; each case names it, so both engines run it in the same place)
CASES = (
    ("idle, cycle in its own process", ["--cycle-in", "process"], False),
    ("idle, cycle on a thread", ["--cycle-in", "thread"], False),
    ("all axes moving, cycle in its own process", ["--cycle-in", "process"], True),
    ("all axes moving, cycle on a thread", ["--cycle-in", "thread"], True),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 s windows")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--fleet", type=int, default=50, help="machines of the fleet (0: none)")
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    seconds = 3.0 if args.quick else args.seconds
    prog = Path(os.environ.get("TMPDIR", "/tmp")) / f"geo-bench-moving-{os.getpid()}.nc"
    prog.write_text(MOVING, encoding="utf-8")
    try:
        rows = [
            [
                name,
                measure(extra, seconds, prog if moving else None, "exact"),
                measure(extra, seconds, prog if moving else None, "punctual"),
            ]
            for name, extra, moving in CASES
        ]
    finally:
        prog.unlink(missing_ok=True)
    md = f"### Host CPU of one default machine, 1 ms cycle ({seconds:g} s windows)\n\n"
    md += table(["case", "exact engine, % of one core", "punctual engine, % of one core"], rows)
    md += "\nTargets of the observation-exact engine (SPEC §13): idle ≤ 1 %, moving ≤ 15 %.\n"
    if args.fleet:
        n = args.fleet
        plain, web = measure_fleet(n, seconds, False), measure_fleet(n, seconds, True)
        md += f"\n### A fleet of {n} default machines at rest, exact engine ({seconds:g} s)\n\n"
        md += table(
            ["case", "% of one core", "per machine"],
            [
                ["every interface, nobody connected", plain, plain / n],
                ["and the web HMI (--http), no page open", web, web / n],
            ],
        )
    emit(md, args.out)


if __name__ == "__main__":
    main()
