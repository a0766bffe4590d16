"""Steady stretches in one pass (docs/design.md §13.2): cost per cycle of a moving machine.

The default machine with every axis moving (an NC program of long G01 moves), its cycles
computed one by one (`Machine.run_cycle(publish=False)`) and as passes of n cycles
(`Machine.run_batch(n)`): median µs per cycle and per pass, with the caches warm (passes
back to back) and cold (each pass right after an 8 ms sleep, as the exact engine wakes).

    python bench/batch.py [--passes N] [--out FILE]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from common import emit, table

from geo_server import jit
from geo_server.listfile.loader import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list

PROGRAM = "N10 G90 G01 X200 Y150 Z-100 C90 F600\nN20 X-200 Y-150 Z100 C-90\nN30 $GOTO N10\n"
SIZES = (1, 2, 4, 8, 16, 32, 64)


def moving_machine() -> Machine:
    m = Machine(load_machine(default_startup_list()), homed=True)
    m.start_program(PROGRAM)
    m.step(50)
    return m


def one_pass(m: Machine, n: int) -> tuple[int, int]:
    """(ns, cycles) of one pass of n cycles (n = 1: a single cycle); a pass the stretch
    does not allow (a move ends) runs as single cycles and is not counted."""
    t0 = time.perf_counter_ns()
    if n == 1:
        m.run_cycle(publish=False)
        return time.perf_counter_ns() - t0, 1
    got = m.run_batch(n)
    if got != n:
        for _ in range(n - got):
            m.run_cycle(publish=False)
        return 0, 0
    return time.perf_counter_ns() - t0, n


def measure(n: int, passes: int, sleep: float) -> float:
    m = moving_machine()
    per_pass = []
    while len(per_pass) < passes:
        if sleep:
            time.sleep(sleep)
        ns, cycles = one_pass(m, n)
        if cycles:
            per_pass.append(ns / 1000)
    return float(np.median(per_pass))


def main() -> None:
    jit.load()  # the cycle's machine code before anything is timed (geo_server/jit.py)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=300)
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    rows = []
    for n in SIZES:
        warm = measure(n, args.passes, 0.0)
        cold = measure(n, max(args.passes // 3, 5), 0.008)
        rows.append(
            [
                "single cycle" if n == 1 else f"pass of {n}",
                f"{warm:.0f}",
                f"{warm / n:.1f}",
                f"{cold:.0f}",
                f"{cold / n:.1f}",
            ]
        )
    md = "### A moving default machine: cycle by cycle and in one pass (median µs)\n\n"
    md += table(
        ["cycles", "warm, per pass", "warm, per cycle", "cold, per pass", "cold, per cycle"], rows
    )
    md += (
        "\n*Cold*: each pass right after an 8 ms sleep (the exact engine wakes every 16 "
        "cycles of a moving machine nobody asks). Bit-identical results: tests/test_batch.py.\n"
    )
    emit(md, args.out)


if __name__ == "__main__":
    main()
