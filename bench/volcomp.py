"""Volumetric compensation (docs/volumetric.md §9): what it adds to a GEO cycle.

A correction file of manual size — the 18 component errors of X, Y, Z every 10 mm over
±280 mm (the grid of the Etalon example, 004 p.33: 57 points, 1026 records) and the three
squareness errors — on the default machine (YXZ chain, 120 mm tool). Medians of:

- one correction at one position (the compiled law, `volcomp.law.correction`, called
  from Python) and per position in a batch of 64 (the same law in a compiled loop),
  against the plain reference;
- the default machine's cycle (`run_cycle(publish=False)`, every axis moving) with the
  compensation off and on: the difference is what one channel pays per cycle.

    python bench/volcomp.py [--cycles N] [--out FILE]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from common import emit, table

from geo_server.listfile.loader import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import data_dir
from geo_server.volcomp import reference
from geo_server.volcomp.evaluator import Evaluator
from geo_server.volcomp.model import build_model
from geo_server.volcomp.paramfile import Block, write_isg_csv
from geo_server.volcomp.tables import ParamTable

PROGRAM = "N10 G90 G01 X200 Y150 Z-100 C90 F600\nN20 X-200 Y-150 Z100 C-90\nN30 $GOTO N10\n"
GRID = np.arange(-280.0, 280.0 + 1e-9, 10.0)


def correction_file() -> str:
    rng = np.random.default_rng(1)
    blocks = []
    for axis in "XYZ":
        cols = []
        for d in "XYZABC":
            scale = 5e-3 if d in "XYZ" else 3e-5
            ph = rng.uniform(0, 6)
            cols.append(scale * np.sin(GRID / 250.0 + ph))
        rows = tuple((float(g), *(float(c[i]) for c in cols)) for i, g in enumerate(GRID))
        blocks.append(Block((axis,), tuple(f"E{d}{axis}" for d in "XYZABC"), rows))
    blocks.append(Block((), ("C0Y", "B0Z", "A0Z", "N0Z"), ((2e-5, -1e-5, 3e-5, -1.0),)))
    return write_isg_csv(blocks)


def machine(folder: Path, on: bool) -> Machine:
    lists = folder / ("on" if on else "off")
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    if on:
        (lists / "vc.csv").write_text(correction_file(), encoding="utf-8")
        (lists / "vc.lis").write_text(
            "X 1\nY 2\nZ 3\nchain YXZ\nfile[0] vc.csv\nfile_format[0] ISG_CSV\n",
            encoding="utf-8",
        )
        with (lists / "hochlauf.lis").open("a", encoding="utf-8") as fh:
            fh.write("vol_comp[0].max_records 2000\nvol_comp[0].file_name vc.lis\n")
        for i in (1, 2, 3):
            with (lists / f"achsmd{i}.lis").open("a", encoding="utf-8") as fh:
                fh.write("lr_param.vol_comp.s_limit 100000\n")
    m = Machine(load_machine(lists / "hochlauf.lis"), homed=True)
    m.start_program(PROGRAM)
    m.step(50)
    if on:
        m.volc.tool_length = 120.0
        assert m.volc.busy
    return m


def cycle_us(m: Machine, cycles: int) -> float:
    out = []
    for _ in range(cycles):
        t0 = time.perf_counter_ns()
        m.run_cycle(publish=False)
        out.append((time.perf_counter_ns() - t0) / 1000)
    return float(np.median(out))


def timed(fn, n: int) -> float:
    out = []
    for _ in range(n):
        t0 = time.perf_counter_ns()
        fn()
        out.append((time.perf_counter_ns() - t0) / 1000)
    return float(np.median(out))


def main() -> None:
    from geo_server import jit

    jit.load()  # the cycle's machine code before anything is timed (geo_server/jit.py)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=5000)
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        off = machine(Path(tmp), False)
        on = machine(Path(tmp), True)
        st = on.volc.states[0]
        ev = st.evaluator
        assert ev is not None
        model = ev.model
        tip = model.tool_point(120.0)
        q1 = np.array([[35.0, -120.0, -40.0]])
        q64 = np.random.default_rng(2).uniform(-250, 250, size=(64, 3))
        one = timed(lambda: ev.correction(q1, tip), args.cycles)
        batch = timed(lambda: ev.correction(q64, tip), max(args.cycles // 20, 20)) / 64
        # the same tables with a rotary table C (chain CYXZ, workpiece side): Rodrigues,
        # the workpiece inverse, a Jacobian per position
        tables = dict(model.tables)
        gc = np.linspace(0.0, 360.0, 73)
        tables["EXC"] = ParamTable("EXC", ("C",), (gc,), 2e-3 * np.cos(np.radians(gc)))
        tables["ECC"] = ParamTable("ECC", ("C",), (gc,), 2e-5 * np.sin(np.radians(gc)))
        rot = Evaluator(build_model("CYXZ", 1, tables))
        rot_one = timed(
            lambda: rot.correction_one([123.0, 35.0, -120.0, -40.0], (0.0, 0.0, -120.0)),
            args.cycles,
        )
        ref = timed(
            lambda: reference.correction(model, {"Y": 35.0, "X": -120.0, "Z": -40.0}, 120.0),
            max(args.cycles // 50, 10),
        )
        base, with_vc = [], []
        for _ in range(5):  # interleaved, so drifts of the host hit both alike
            base.append(cycle_us(off, args.cycles // 5))
            with_vc.append(cycle_us(on, args.cycles // 5))
        b, w = float(np.median(base)), float(np.median(with_vc))
    rows = [
        ["one correction, one position (compiled, called from Python)", f"{one:.1f}"],
        ["one correction, per position in a batch of 64 (compiled loop)", f"{batch:.1f}"],
        ["one correction, plain reference", f"{ref:.0f}"],
        ["one correction, one position, chain CYXZ (rotary table)", f"{rot_one:.1f}"],
        ["default machine cycle, moving, compensation off", f"{b:.1f}"],
        ["default machine cycle, moving, compensation on", f"{w:.1f}"],
        ["added per cycle", f"{w - b:.1f}"],
    ]
    md = (
        f"### Volumetric compensation: 21 parameters, {len(GRID)} points per axis "
        f"({18 * len(GRID)} records), median µs\n\n"
    )
    md += table(["what", "µs"], rows)
    emit(md, args.out)


if __name__ == "__main__":
    main()
