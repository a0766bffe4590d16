"""Kernel benchmark (docs/design.md §11): cost per GEO cycle with all compensations active.

Machines of 1, 8, 32 and 128 axes, every axis with backlash, temperature, cross (1001
points), plane (101×101), LSEC (1500 points, bilateral), friction (20 points) and
crosstalk mode 3 (15 test points); all axes homed and moving with reversals. Prints the
median and p99 µs per cycle of `Kernel` and `ReferenceKernel` as a Markdown table.

    python bench/kernel.py [--cycles N] [--axes 1,8,32,128] [--ref-cycles N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from geo_server import jit
from geo_server.kernel import Kernel

# the synthetic machines and the reference kernel (the test oracle) are test support
# (tests/support/machines.py, tests/support/reference.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.machines import Motion, full_machine
from support.reference import ReferenceKernel


def run(kernel_cls: type, n: int, cycles: int) -> tuple[float, float]:
    cfg = full_machine(n)
    k = kernel_cls(cfg)
    m = Motion(n, seed=2)
    m.homed[:] = True
    # precompute the motion so that only the kernel is timed
    frames = []
    for _ in range(cycles + 50):
        m.step()
        frames.append((m.pos.copy(), m.vel.copy(), m.acc.copy(), m.reversal.copy()))
    homed = np.ones(n, dtype=bool)
    times = np.empty(cycles)
    for i, (p, v, a, r) in enumerate(frames):
        t0 = time.perf_counter_ns()
        k.step(p, v, a, homed, r)
        t1 = time.perf_counter_ns()
        if i >= 50:  # warm-up
            times[i - 50] = (t1 - t0) / 1000.0
    assert k.effective.all(), "every compensation should be effective in the benchmark"
    return float(np.median(times)), float(np.percentile(times, 99))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=2000)
    ap.add_argument("--ref-cycles", type=int, default=None, help="cycles for the reference")
    ap.add_argument("--axes", default="1,8,32,128")
    args = ap.parse_args()
    ref_cycles = args.ref_cycles or args.cycles
    # the compiled laws (geo_server/jit.py): without this, `Kernel.step` runs them
    # interpreted, about a thousand times slower (what the composition root avoids)
    jit.load()
    print("| axes | Kernel median µs | Kernel p99 µs | Reference median µs | Reference p99 µs |")
    print("|---:|---:|---:|---:|---:|")
    for n in (int(x) for x in args.axes.split(",")):
        fm, fp = run(Kernel, n, args.cycles)
        rm, rp = run(ReferenceKernel, n, ref_cycles)
        print(f"| {n} | {fm:.1f} | {fp:.1f} | {rm:.1f} | {rp:.1f} |", flush=True)


if __name__ == "__main__":
    main()
