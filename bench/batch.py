"""Steady stretches in one pass (docs/design.md §13.2): cost per cycle of a moving machine.

The default machine with every axis moving (an NC program of long G01 moves), its cycles
computed one by one (`Machine.run_cycle(publish=False)`) and as passes of n cycles
(`Machine.run_batch(n)`): median µs per cycle and per pass, with the caches warm (passes
back to back) and cold (each pass right after an 8 ms sleep, as the exact engine wakes).
A pass the machine refuses (`run_batch` returns 0: a code that cannot pass while a
volumetric compensation acts, or a program block starting) runs as n single cycles —
what the engine does then — and is counted; a pass cut short by a move's end is not.

`--volumetric`: the machine carries the volumetric compensation of bench/volcomp.py
acting (21 parameters on tables of manual size, chain YXZ, a 120 mm tool).
`--against TREE`: the same measurements with the geo_server of TREE (a checkout, e.g.
`git archive COMMIT | tar -x -C TREE`) side by side, each in its own process, the two
alternating for `--rounds` rounds; the table gives the range of the rounds' medians.

    python bench/batch.py [--passes N] [--volumetric] [--against TREE --rounds R] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import BENCH, ROOT, emit, table

from geo_server.listfile.loader import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list

PROGRAM = "N10 G90 G01 X200 Y150 Z-100 C90 F600\nN20 X-200 Y-150 Z100 C-90\nN30 $GOTO N10\n"
SIZES = (1, 2, 4, 8, 16, 32, 64)


def moving_machine(volumetric: bool = False) -> Machine:
    if volumetric:
        from volcomp import machine as volc_machine  # bench/volcomp.py

        return volc_machine(Path(tempfile.mkdtemp(prefix="bench-batch-")), True)
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
        if got:
            return 0, 0
    return time.perf_counter_ns() - t0, n


def measure(n: int, passes: int, sleep: float, volumetric: bool = False) -> float:
    m = moving_machine(volumetric)
    per_pass = []
    while len(per_pass) < passes:
        if sleep:
            time.sleep(sleep)
        ns, cycles = one_pass(m, n)
        if cycles:
            per_pass.append(ns / 1000)
    return float(np.median(per_pass))


def medians(passes: int, volumetric: bool) -> dict[str, list[float]]:
    """Per pass size: [warm, cold] median µs per pass."""
    out = {}
    for n in SIZES:
        warm = measure(n, passes, 0.0, volumetric)
        cold = measure(n, max(passes // 3, 5), 0.008, volumetric)
        out[str(n)] = [warm, cold]
    return out


def load_compiled() -> None:
    """The cycle's machine code before anything is timed (geo_server/jit.py); a tree
    from before the compiler (`--against`) has nothing to load."""
    try:
        from geo_server import jit
    except ImportError:
        return
    jit.load()


def _run(tree: str, passes: int, volumetric: bool) -> dict[str, list[float]]:
    """`medians` in a process of its own with the geo_server of `tree`."""
    env = dict(os.environ, PYTHONPATH=tree)
    argv = [sys.executable, str(BENCH / "batch.py"), "--json", "--passes", str(passes)]
    if volumetric:
        argv.append("--volumetric")
    out = subprocess.run(argv, env=env, check=True, capture_output=True, text=True, cwd=tree)
    return json.loads(out.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def _span(values: list[float], per: int) -> str:
    lo, hi = min(values) / per, max(values) / per
    digits = 0 if hi >= 100 else 1
    return (
        f"{lo:.{digits}f}"
        if f"{lo:.{digits}f}" == f"{hi:.{digits}f}"
        else (f"{lo:.{digits}f}–{hi:.{digits}f}")
    )


def against(tree: str, rounds: int, passes: int, volumetric: bool) -> str:
    """Markdown: this checkout and `tree` alternating, the rounds' medians per cycle."""
    runs: dict[str, list[dict[str, list[float]]]] = {"before": [], "after": []}
    for r in range(rounds):
        order = [("before", tree), ("after", str(ROOT))]
        for name, where in order if r % 2 == 0 else order[::-1]:
            runs[name].append(_run(where, passes, volumetric))
    rows = []
    for n in SIZES:
        row = ["single cycle" if n == 1 else f"pass of {n}"]
        for k in (0, 1):
            row.append(_span([m[str(n)][k] for m in runs["before"]], n))
            row.append(_span([m[str(n)][k] for m in runs["after"]], n))
        rows.append(row)
    what = "with a volumetric compensation acting" if volumetric else "moving"
    md = (
        f"### The default machine {what}: µs per cycle, before ({tree}) and after "
        f"(this checkout), {rounds} alternating rounds\n\n"
    )
    md += table(["cycles", "warm, before", "warm, after", "cold, before", "cold, after"], rows)
    return md


def main() -> None:
    load_compiled()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=300)
    ap.add_argument("--volumetric", action="store_true", help="a volumetric compensation acts")
    ap.add_argument("--against", metavar="TREE", help="compare with TREE's geo_server")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    if args.json:
        print(json.dumps(medians(args.passes, args.volumetric)))
        return
    if args.against:
        emit(against(args.against, args.rounds, args.passes, args.volumetric), args.out)
        return
    rows = []
    for n, (warm, cold) in medians(args.passes, args.volumetric).items():
        k = int(n)
        rows.append(
            [
                "single cycle" if k == 1 else f"pass of {k}",
                f"{warm:.0f}",
                f"{warm / k:.1f}",
                f"{cold:.0f}",
                f"{cold / k:.1f}",
            ]
        )
    what = "with a volumetric compensation acting" if args.volumetric else ""
    md = f"### A moving default machine {what}: cycle by cycle and in one pass (median µs)\n\n"
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
