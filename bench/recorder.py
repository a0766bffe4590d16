"""Recorder (docs/recorder.md §8): what recording costs the GEO cycle, and its memory.

The default machine, every axis moving, stepped `run_cycle()` (published: the recorder
samples what is published). Rounds alternate a cycle without a recorder and a cycle with
one recording 20 values every cycle; medians of each, and the recorder's own per-sample
time (`Recorder._on_cycle` on a fixed snapshot).

`--memory 10000,90000`: for each row count, a fresh process records every object (`*`) to
a CSV file in a stepped machine and reports the resident memory it adds per row while it
records, the peak the stop adds above that (per row), how long the stop takes, and the
file; then, with a trigger that never fires, how much memory the machine's inputs take
while it is awaited (100 writes per cycle).

    python bench/recorder.py [--cycles N] [--memory ROWS,ROWS] [--out FILE]
"""

from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import emit, table

from geo_server import access, jit
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


def cycle_times(m: Machine, n: int) -> np.ndarray:
    out = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        t0 = clock()
        m.run_cycle()
        out[i] = (clock() - t0) / 1000
    return out


def run(cycles: int) -> str:
    machine = Machine(load_machine(default_startup_list()), homed=True)
    service = ObjectService(machine)
    machine.start_program(PROGRAM)
    access.step(service, 200)
    spec = RecordSpec(list(TWENTY), samples=cycles * 20 + 10)
    columns = len(Recorder(service, spec).columns)
    off, on = [], []
    for _round in range(20):  # alternate rounds: the same drift for both
        off.append(cycle_times(machine, cycles // 20))
        rec = Recorder(service, spec).start()
        on.append(cycle_times(machine, cycles // 20))
        rec.stop()
    base, rec_on = np.concatenate(off), np.concatenate(on)
    probe = Recorder(service, RecordSpec(list(TWENTY), samples=100_001))
    snap = service.current(stale_ok=True)
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


def _status(key: str) -> int:
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    return 0


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
        fh.write("5")  # VmHWM := VmRSS (Linux)


def memory_child(rows: int) -> dict[str, float]:
    """One recording of `*` over `rows` cycles to a CSV file (in this process)."""
    service = ObjectService(Machine(load_machine(default_startup_list()), homed=True))
    service.recordings.record_dir = Path(tempfile.mkdtemp(prefix="geo-bench-rec-"))
    access.step(service, 5)
    gc.collect()
    before = _status("VmRSS")
    st = service.recordings.start({"objects": ["*"]}, "star.csv")
    access.step(service, rows)
    gc.collect()
    recording = _status("VmRSS")
    _reset_peak()
    t0 = time.perf_counter()
    done = service.recordings.stop()
    stop_s = time.perf_counter() - t0
    peak = _status("VmHWM")
    return {
        "rows": rows,
        "columns": st["columns"],
        "recording_kib_per_row": (recording - before) / rows / 1024,
        "recording_mib": (recording - before) / 2**20,
        "stop_kib_per_row": (peak - recording) / rows / 1024,
        "stop_mib": (peak - recording) / 2**20,
        "stop_s": stop_s,
        "file_bytes_per_row": Path(done["file"]).stat().st_size / rows,
        "buffer_mib": st.get("buffer_bytes", 0) / 2**20,
    }


def inputs_child(writes: int) -> dict[str, float]:
    """Inputs kept while a trigger is awaited: 100 writes per cycle, queued on the machine
    by name as before (the figures of docs/recorder.md stay comparable)."""
    from geo_server.machine.port import WriteObjects

    machine = Machine(load_machine(default_startup_list()), homed=True)
    service = ObjectService(machine)
    service.recordings.record_dir = Path(tempfile.mkdtemp(prefix="geo-bench-rec-"))
    trigger = {"objects": ["SIM::cycle_count"], "trigger": "SIM::cycle_count < 0"}
    service.recordings.start(trigger, "never.csv")
    gc.collect()
    before = _status("VmRSS")
    t0 = time.perf_counter()
    for _ in range(writes // 100):
        for k in range(100):
            machine.submit(WriteObjects((("TEMPC::offset_0", 1, 40 + k),)))
        access.step(service, 1)
    elapsed = time.perf_counter() - t0
    gc.collect()
    grown = _status("VmRSS") - before
    st = service.status()["recording"]
    service.recordings.stop()
    return {
        "writes": writes,
        "kept": st["inputs"],
        "dropped": st.get("inputs_dropped", 0),
        "grown_mib": grown / 2**20,
        "writes_per_s": writes / elapsed,
        "mib_per_s": grown / 2**20 / elapsed,
    }


def _child(kind: str, n: int) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, __file__, "--child", kind, str(n)],
        capture_output=True,
        text=True,
        check=True,
        timeout=900,
    ).stdout
    result: dict[str, float] = json.loads(out.strip().splitlines()[-1])
    return result


def memory(rows: list[int], writes: int) -> str:
    lines = []
    for n in rows:
        r = _child("memory", n)
        lines.append(
            [
                f"{n} rows of {r['columns']:.0f} values",
                f"{r['recording_kib_per_row']:.3f} ({r['recording_mib']:.1f} MiB)",
                f"{r['stop_kib_per_row']:.3f} ({r['stop_mib']:.1f} MiB)",
                f"{r['stop_s']:.2f}",
                f"{r['file_bytes_per_row']:.0f}",
            ]
        )
    i = _child("inputs", writes)
    return (
        "\n## Recorder memory (`*` to CSV, stepped; RSS)\n\n"
        + table(
            [
                "recording",
                "KiB/row while recording",
                "KiB/row at the stop (peak)",
                "stop s",
                "file B/row",
            ],
            lines,
        )
        + f"\nInputs while a trigger is awaited: {i['writes']:.0f} writes "
        f"({i['writes_per_s']:.0f}/s): {i['kept']:.0f} kept, {i['dropped']:.0f} dropped, "
        f"+{i['grown_mib']:.1f} MiB ({i['mib_per_s']:.2f} MiB/s)\n"
    )


def main() -> None:
    jit.load()  # the cycle's machine code before anything is timed (geo_server/jit.py)
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--cycles", type=int, default=20000)
    p.add_argument("--memory", help="row counts of the memory part, e.g. 10000,90000")
    p.add_argument("--input-writes", type=int, default=100_000)
    p.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    p.add_argument("--out")
    args = p.parse_args()
    if args.child:
        kind, n = args.child[0], int(args.child[1])
        print(json.dumps(memory_child(n) if kind == "memory" else inputs_child(n)))
        return
    text = run(args.cycles) if args.cycles else ""
    if args.memory:
        text += memory([int(x) for x in args.memory.split(",")], args.input_writes)
    emit(text, args.out)


if __name__ == "__main__":
    main()
