"""A scenario run by tests/test_jit.py twice: with the cycle's machine code and, in a
subprocess with `NUMBA_DISABLE_JIT=1`, with the laws interpreted (`python jit_run.py OUT`
writes the states to OUT, an .npz file).

The default machine, the volumetric machine of tests/support/machines.py (two
compensations, one with a rotary workpiece axis and the alternative model, ramps, an
s_limit stop) and two random machines (modulo axes, friction delays, crosstalk modes,
LSEC, manual activation) run an NC program with moves, reversals and a dwell, a
TEMPC write during the motion (a sin² ramp), a reload, and the twin's thermal updates
and sensor samples: every array the cycle writes is kept after every 50th cycle.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from geo_server.listfile.loader import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.port import Reload, WriteObjects
from geo_server.model import MachineConfig
from geo_server.paths import default_startup_list

sys.path.insert(0, str(Path(__file__).parent.parent))
from support.machines import random_machine, volumetric_machine

CYCLES = 900


def _program(names: list[str]) -> str:
    there = " ".join(f"{x}{20 + 7 * i}" for i, x in enumerate(names))
    back = " ".join(f"{x}{-15 - 5 * i}" for i, x in enumerate(names))
    return f"N10 G90 G01 {there} F3000\nN20 {back}\nN30 G04 X0.02\nN40 G00 {there}\nM30\n"


def _state(m: Machine) -> list[np.ndarray]:
    k, mo, tw = m.kernel, m.motion, m.twin
    return [k.F7, k.B7, k.I7, k.F1, k.B1, k.G, k.ring, mo.F, mo.I, mo.B, tw.A, tw.N, tw.S,
            tw.C, tw.O, m._output, m._drive_act, m.volc.S, m.volc.offset,
            m.snapshot.values]  # fmt: skip


def _machines(folder: Path) -> list[MachineConfig]:
    cfgs = [load_machine(default_startup_list()), volumetric_machine(folder)]
    for n, seed in ((3, 4), (5, 2)):
        cfg = random_machine(n, seed)
        for a, letter in zip(sorted(cfg.axes), "XYZUV", strict=False):
            cfg.axes[a].params.name = letter
        cfgs.append(cfg)
    return cfgs


def run(folder: Path) -> dict[str, np.ndarray]:
    """The states; `folder` for the volumetric machine's lists."""
    out: dict[str, np.ndarray] = {}
    for j, cfg in enumerate(_machines(folder)):
        m = Machine(cfg, homed=True)
        m.set_epoch(0)
        m.start_program(_program(sorted(m.names, key=m.names.__getitem__)))
        for c in range(CYCLES):
            if c == 300:
                m.submit(WriteObjects((("TEMPC::offset_0", m.axes[0], -250),)))
            if c == 600:
                m.submit(Reload(cfg))
            m.run_cycle(publish=c % 50 == 49)
            if c % 50 == 49:
                for i, a in enumerate(_state(m)):
                    out[f"m{j}c{c}s{i}"] = np.array(a)
    return out


if __name__ == "__main__":
    out = Path(sys.argv[1])
    np.savez(out, **run(out.parent / "interpreted"))
