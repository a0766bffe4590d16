"""The volumetric loop on the twin (docs/volumetric.md §8): a machine with the 21
rigid-body errors → its volumetric error across the work volume → a measurement written as
an ISG CSV correction file → `#VOLCOMP [ID0 UPDATE]`, `#VOLCOMP ON [ID0]` → the residual
error is down to the interpolation floor.

A three-axis machine without axis compensations, so the residual is the volumetric error
alone. Stepped mode: every position is set, one cycle run, `TWIN::residual` read.
"""

from __future__ import annotations

import itertools
import math
import time
from pathlib import Path

import numpy as np
import pytest

from geo_server.dictionary import load_dictionary
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.twin.file import load_twin
from geo_server.twin.volumetric import measure_rigid_body, write_correction

D = load_dictionary()
TRAVEL = {"X": (-400.0, 400.0), "Y": (-300.0, 300.0), "Z": (-200.0, 0.0)}
KNOTS = 10.0  # mm between the points of the twin's curves


def curve(lo: float, hi: float, amplitude: float, period: float, phase: float) -> str:
    """A smooth error (µm or µrad) sampled every KNOTS mm: the twin's 'true' curve."""
    xs = np.arange(lo - 50, hi + 50 + 1e-9, KNOTS)
    ys = amplitude * np.sin(2 * math.pi * xs / period + phase) + amplitude * xs / (hi - lo)
    return (
        f"{{ positions = [{', '.join(f'{x:g}' for x in xs)}], "
        f"errors = [{', '.join(f'{y:.6f}' for y in ys)}] }}"
    )


def make_machine(folder: Path) -> Path:
    """hochlauf.lis with X, Y, Z (s_limit 1 mm) and vol_comp[0] (its list is written
    later, by the measurement), twin.toml with the rigid-body errors only."""
    folder.mkdir(parents=True, exist_ok=True)
    stup = ["zahl_mds 3"]
    for i, a in enumerate("XYZ"):
        stup += [f"achs_mds_log_ax_nr[{i}] {i + 1}", f"achs_mds[{i}] ax{a}.lis"]
        (folder / f"ax{a}.lis").write_text(
            f"kopf.achs_nr {i + 1}\nkopf.log_achs_name {a}\nkenngr.achs_typ 1\n"
            "lr_param.vol_comp.s_limit 10000\n",
            encoding="utf-8",
        )
    stup += ["vol_comp[0].max_records 1000", "vol_comp[0].file_name volcomp_twin.lis"]
    (folder / "hochlauf.lis").write_text("\n".join(stup) + "\n", encoding="utf-8")
    errors = []
    amp = {"X": 8.0, "Y": 4.0, "Z": 4.0, "A": 12.0, "B": 12.0, "C": 12.0}
    for k, (axis, d) in enumerate(itertools.product("XYZ", "XYZABC")):
        lo, hi = TRAVEL[axis]
        errors.append(f"E{d}{axis} = {curve(lo, hi, amp[d], 700.0 + 37 * k, 0.3 * k)}")
    (folder / "twin.toml").write_text(
        '[rigid_body]\nchain = "YXZ"\ntool = [0.0, 0.0, -120.0]\n'
        "squareness = { C0Y = 25.0, B0Z = -18.0, A0Z = 12.0 }\n\n"
        "[rigid_body.errors]\n" + "\n".join(errors) + "\n",
        encoding="utf-8",
    )
    return folder / "hochlauf.lis"


def volumetric_errors(m: Machine) -> np.ndarray:
    """|residual| (µm) at the 5×5×5 points of the work volume."""
    out = []
    for p in itertools.product(*(np.linspace(*TRAVEL[a], 5) for a in "XYZ")):
        for slot, v in enumerate(p):
            m.motion.set_position(slot, v * 10_000)
        for _ in range(2):
            snap = m.run_cycle()
        r = [snap.value(D.by_name("TWIN::residual"), a) for a in (1, 2, 3)]
        out.append(math.hypot(*r) / 10.0)  # increments → µm
    return np.array(out)


@pytest.mark.parametrize(("step", "floor_um"), [(KNOTS, 0.15), (100.0, 1.5)])
def test_measure_correct_and_the_residual_is_the_interpolation_floor(
    tmp_path: Path, step: float, floor_um: float
) -> None:
    """With the measurement on the twin's own knots (10 mm) the residual is what the
    increments round (< 0.15 µm); on a 100 mm grid it is the chord error of the curves
    (h²/8·|f''|: 0.56 µm for these), against 25 µm before."""
    stup = make_machine(tmp_path / "m")
    cfg = load_machine(stup)
    assert not cfg.volumetric[0].available  # no list yet: measured below
    m = Machine(cfg, cycle_s=0.001, homed=True)
    before = volumetric_errors(m)
    assert before.max() > 20.0
    rb = load_twin(tmp_path / "m" / "twin.toml", ["X", "Y", "Z"]).rigid_body
    assert rb is not None
    blocks = measure_rigid_body(rb, TRAVEL, step)
    write_correction(stup.parent, blocks, rb, {"X": 1, "Y": 2, "Z": 3})
    # (ramped in: a NO_MOVE would hold the drives until the axes move, and the points
    # below are set, not travelled to)
    m.start_program("#VOLCOMP [ID0 UPDATE]\n#VOLCOMP ON [ID0]\n", mdi=True)
    # the UPDATE reads the files in a worker thread (the cycle never waits for a disk):
    # cycles run until it is done, however long a loaded host takes
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        m.run_cycle()
        if m.snapshot.value(D.by_name("VOLC::active"), 0):
            break
        time.sleep(0.001)
    assert m.snapshot.value(D.by_name("VOLC::active"), 0) == 1
    for _ in range(1000):  # (the program waits for the ramp of filter_steps cycles)
        if m.player is None or not m.player.running:
            break
        m.run_cycle()
    assert m.volc.at_rest and not m.volc.held.any()
    after = volumetric_errors(m)
    assert after.max() < floor_um
    print(
        f"step {step} mm: before max {before.max():.1f} µm rms {np.sqrt((before**2).mean()):.1f}"
        f" µm, after max {after.max():.2f} µm rms {np.sqrt((after**2).mean()):.2f} µm"
    )
