"""Recorder (docs/recorder.md §8): what recording costs the GEO cycle.

The default machine, every axis moving, stepped `run_cycle()` (published: the recorder
samples what is published). Rounds alternate a cycle without a recorder and a cycle with
one recording 20 values every cycle; medians of each, and the recorder's own per-sample
time (`Recorder._on_cycle` on a fixed snapshot).

    python bench/recorder.py [--cycles N] [--out FILE]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from common import emit, table

from geo_server.listfile.loader import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list
from geo_server.recorder import Recorder, RecordSpec
from geo_server.service import ObjectService

#: 20 values: X's TEMPC and backlash objects, every axis' position and sensor, the cycle
#: count and X's residual error
TWENTY = [
    "TEMPC::*@1",
    "BC::*@1",
    "SIM::command_position",
    "TWIN::sensor_temperature",
    "SIM::cycle_count",
    "TWIN::residual@1",
]
PROGRAM = "N10 G90 G01 X200 Y150 Z-100 C90 F3000\nN20 X-200 Y-150 Z100 C-90\nN30 $GOTO N10\n"


def cycle_times(service: ObjectService, n: int) -> np.ndarray:
    m = service.machine
    out = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        t0 = clock()
        m.run_cycle()  # type: ignore[attr-defined]
        out[i] = (clock() - t0) / 1000
    return out


def run(cycles: int) -> str:
    machine = Machine(load_machine(default_startup_list()), homed=True)
    service = ObjectService(machine)
    machine.start_program(PROGRAM)
    service.step(200)
    spec = RecordSpec(list(TWENTY), samples=cycles * 20 + 10)
    columns = len(Recorder(service, spec).columns)
    off, on = [], []
    for _round in range(20):  # alternate rounds: the same drift for both
        off.append(cycle_times(service, cycles // 20))
        rec = Recorder(service, spec).start()
        on.append(cycle_times(service, cycles // 20))
        rec.stop()
    base, rec_on = np.concatenate(off), np.concatenate(on)
    probe = Recorder(service, RecordSpec(list(TWENTY), samples=100_001))
    snap = service.snapshot
    samples = np.empty(20000)
    for i in range(len(samples)):
        probe._last_cycle = -1
        t0 = time.perf_counter_ns()
        probe._on_cycle(snap)
        samples[i] = (time.perf_counter_ns() - t0) / 1000
        if probe.done:
            probe = Recorder(service, RecordSpec(list(TWENTY), samples=100_001))
    rows = [
        ["cycle, no recorder", f"{np.median(base):.1f}", f"{np.percentile(base, 99):.1f}"],
        [
            f"cycle, recording {columns} values every cycle",
            f"{np.median(rec_on):.1f}",
            f"{np.percentile(rec_on, 99):.1f}",
        ],
        [
            "one sample of the recorder alone",
            f"{np.median(samples):.2f}",
            f"{np.percentile(samples, 99):.2f}",
        ],
    ]
    return (
        f"## Recorder ({cycles} cycles, default machine moving, µs)\n\n"
        + table(["measurement", "p50", "p99"], rows)
        + f"\nAdded per cycle (p50): {np.median(rec_on) - np.median(base):.1f} µs\n"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--cycles", type=int, default=20000)
    p.add_argument("--out")
    args = p.parse_args()
    emit(run(args.cycles), args.out)


if __name__ == "__main__":
    main()
