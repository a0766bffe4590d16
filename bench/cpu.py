"""Host CPU of a running geo-server (SPEC §13 baseline): how much of a core one machine costs.

`geo-server run --homed` (1 ms real-time cycle, every interface on) in its own process; the
CPU time (user + system, from /proc/<pid>/stat of the server and its GEO-cycle child) over
a window, as a share of one core:

- **idle**: nothing connected, nothing moving;
- **moving**: every axis of the default machine travelling back and forth (an NC program
  in a `$GOTO` loop).

These are the figures of today's punctual engine (sleep, then spin to the deadline), the
baseline the observation-exact engine is to beat (targets: idle ≤ 1 %, moving ≤ 15 %).

    python bench/cpu.py [--quick] [--seconds S] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from common import ServerProcess, emit, free_ports, geo_server_argv, start_geo, table

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


def measure(extra: list[str], seconds: float, program: Path | None) -> float:
    zport, mport, aport = free_ports(3)
    ports = {"zenoh": zport, "modbus": mport, "ads": aport}
    args = [*extra, "--ads-udp-port", "0"]
    if program is not None:
        args += ["--program", str(program)]
    with ServerProcess(geo_server_argv(1.0, ports, extra=args), "cpu") as server:
        start_geo(server, ports).close()
        time.sleep(1.0)  # start-up over
        c0, t0 = cpu_seconds(server.pid), time.monotonic()
        time.sleep(seconds)
        c1, t1 = cpu_seconds(server.pid), time.monotonic()
    return 100.0 * (c1 - c0) / (t1 - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 s windows")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    seconds = 3.0 if args.quick else args.seconds
    prog = Path(os.environ.get("TMPDIR", "/tmp")) / f"geo-bench-moving-{os.getpid()}.nc"
    prog.write_text(MOVING, encoding="utf-8")
    try:
        rows = [
            ["idle, cycle in its own process", measure([], seconds, None)],
            ["idle, cycle on a thread", measure(["--cycle-in", "thread"], seconds, None)],
            ["all axes moving, cycle in its own process", measure([], seconds, prog)],
        ]
    finally:
        prog.unlink(missing_ok=True)
    md = f"### Host CPU of one default machine, 1 ms cycle ({seconds:g} s windows)\n\n"
    md += table(["case", "% of one core"], rows)
    md += "\nPunctual engine (sleep, then spin to each deadline). Targets of the "
    md += "observation-exact engine (SPEC §13): idle ≤ 1 %, moving ≤ 15 %.\n"
    emit(md, args.out)


if __name__ == "__main__":
    main()
