"""Synthetic machines and motion for the kernel benchmark and the randomized tests.

`full_machine` builds n axes with every compensation configured at the manuals' table
sizes (docs/design.md §11: LSEC 1500 points, cross 1001, plane 101×101, crosstalk mode 3 with 15
points, friction 20 points); `random_machine` varies sizes, modes and flags;
`Motion` produces smooth moving profiles with reversals.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from geo_server.listfile.loader import load_machine
from geo_server.model import (
    AxisConfig,
    AxisParams,
    CompList,
    CrossComp,
    CrosstalkComp,
    FrictComp,
    LsecComp,
    MachineConfig,
    PlaneComp,
)
from geo_server.paths import data_dir
from geo_server.volcomp.paramfile import Block, write_isg_csv


def _axis(i: int, n: int, rng: np.random.Generator, full: bool) -> AxisConfig:
    nr = i + 1
    m1, m2, m3 = (i + 1) % n + 1, (i + 2) % n + 1, (i + 3) % n + 1
    rotary = (not full) and rng.random() < 0.2
    p = AxisParams(
        log_nr=nr,
        name=f"A{nr}",
        kind="R" if rotary else "T",
        modulo=rotary,
        modulo_period=3_600_000.0,
        lose=int(rng.integers(-500, 500)) or 100,
        anwahl_losekomp=int(rng.integers(1, 3)) if full else int(rng.integers(0, 3)),
        n_backlash_cyc=int(rng.integers(0, 21)),
        temp_comp=True,
        temp_comp_position_0=int(rng.integers(-1000, 1000)),
        temp_comp_offset_0=int(rng.integers(-100, 100)),
        temp_comp_coefficient=float(rng.uniform(-50, 50)),
        temp_comp_n_cycles=int(rng.integers(0, 21)),
        crosscomp=True,
        crosscomp2=True,
        ssfk=True,
        frict_comp=True,
        crosstalk=True,
    )
    if not full:
        p.temp_comp_manual_activation = bool(rng.random() < 0.2)
    # cross: 1001 points over ±500 mm
    nc = 1001 if full else int(rng.integers(1, 40))
    sp = np.linspace(-5_000_000, 5_000_000, nc) if nc > 1 else np.array([0.0])
    if rotary or (not full and rng.random() < 0.3):
        sp = np.linspace(0, 3_600_000, max(nc, 2))
    cross = CrossComp(
        master_ax_nr=m1,
        setpoint=np.round(sp),
        correction=np.round(rng.normal(0, 50, len(sp))),
        n_cycles=int(rng.integers(0, 21)),
    )
    # plane: 101 x 101 grid, 10 mm interval
    l1, l2 = (101, 101) if full else (int(rng.integers(1, 8)), int(rng.integers(1, 8)))
    plane = PlaneComp(
        master1_ax_nr=m1,
        master2_ax_nr=m2,
        start_position_master1=-5_000_000.0 if full else float(rng.integers(-200000, 0)),
        start_position_master2=-5_000_000.0 if full else float(rng.integers(-200000, 0)),
        interval1=100_000.0 if full else float(rng.integers(10000, 100000)),
        interval2=100_000.0 if full else float(rng.integers(10000, 100000)),
        table=np.round(rng.normal(0, 30, (l2, l1))),
        n_cycles=int(rng.integers(0, 21)),
    )
    # LSEC: 1500 non-equidistant points
    nl = 1500 if full else int(rng.integers(1, 60))
    if rotary:
        lsp = np.linspace(0, 3_600_000, max(nl, 2))
    else:
        lsp = np.sort(rng.uniform(-6_000_000, 6_000_000, nl)).round()
        lsp = np.unique(lsp)
    pos = np.round(rng.normal(0, 40, len(lsp)))
    neg = np.round(pos + rng.normal(0, 20, len(lsp)))
    if rotary:
        neg[-1], pos[-1] = neg[0], pos[0]
    lsec = LsecComp(
        setpoint=lsp,
        pos=pos,
        neg=neg,
        bilateral=full or bool(rng.random() < 0.7),
        modulo=rotary,
        set_pos_without_comp=(not full) and bool(rng.random() < 0.3),
    )
    # friction: 20 points over 0..300 mm/s (µm/s in the table)
    nf = 20 if full else int(rng.integers(1, 20))
    vin = np.sort(np.unique(np.round(rng.uniform(0, 300_000, nf))))
    if full:
        vin[0] = 0.0
    frict = FrictComp(
        vin=vin,
        out=np.round(rng.uniform(0, 4000, len(vin))),
        position_delay=int(rng.integers(0, 31)),
        reversal_lookahead=int(rng.integers(0, 5)),
        scaling_factor=int(rng.integers(1, 2000)),
        delay_cycles=int(rng.integers(0, 10)),
    )
    # crosstalk: mode 3 with 15 test points over the adaptation axes
    mode = 3 if full else int(rng.integers(1, 4))
    dialect = "new" if full or rng.random() < 0.8 else "old"
    npts = 15 if full else int(rng.integers(1, 16))
    if mode == 3 and not full and rng.random() < 0.3:
        g = np.array([(x, y) for y in (0, 1500, 3000) for x in (0, 1500, 3000)], dtype=float)
        ax1, ax2 = g[:, 0] * 1000, g[:, 1] * 1000
        npts = 9
    else:
        ax1 = np.round(rng.uniform(-4_000_000, 4_000_000, npts))
        ax2 = np.round(rng.uniform(-4_000_000, 4_000_000, npts))
    xt = CrosstalkComp(
        dialect=dialect,
        master_dyn_ax_nr=m1,
        mode=mode,
        master_pos1_ax_nr=m2,
        master_pos2_ax_nr=m3,
        n_cycles=int(rng.integers(0, 21)),
        acceleration=float(rng.integers(100, 5000)),
        deceleration=-float(rng.integers(100, 5000)),
        velocity_dependent=bool(rng.random() < 0.5),
        ax_1=ax1,
        ax_2=ax2,
        corrections=np.round(rng.normal(0, 40, (npts, 4))),
        acc_table=np.sort(rng.uniform(-5000, 5000, 5)),
        corr_table=np.round(rng.normal(0, 40, 5)),
    )
    comp = CompList(
        path="", achs_nr=nr, cross=cross, plane=plane, lsec=lsec, frict=frict, crosstalk=xt
    )
    if not full:  # leave some compensations unconfigured
        for name in ("cross", "plane", "lsec", "frict", "crosstalk"):
            if rng.random() < 0.15:
                setattr(comp, name, None)
    return AxisConfig(params=p, comp=comp)


def full_machine(n: int, seed: int = 1) -> MachineConfig:
    """n axes, every compensation at manual table sizes (docs/design.md §11)."""
    rng = np.random.default_rng(seed)
    return MachineConfig(Path("<bench>"), {i + 1: _axis(i, n, rng, True) for i in range(n)})


def random_machine(n: int, seed: int) -> MachineConfig:
    """n axes with random small tables, modes and flags (randomized equality tests)."""
    rng = np.random.default_rng(seed)
    return MachineConfig(Path("<random>"), {i + 1: _axis(i, n, rng, False) for i in range(n)})


class Motion:
    """Random smooth motion: per axis a velocity that drifts and reverses (units/s)."""

    def __init__(self, n: int, seed: int = 0, dt: float = 0.001) -> None:
        self.rng = np.random.default_rng(seed)
        self.dt = dt
        self.pos = self.rng.uniform(-4_000_000, 4_000_000, n)
        self.vel = np.zeros(n)
        self.acc = np.zeros(n)
        self.homed = np.zeros(n, dtype=bool)
        self.reversal = np.full(n, -1, dtype=np.int64)
        self._goal = self.rng.uniform(-1_000_000, 1_000_000, n)

    def step(self) -> None:
        rng, n = self.rng, len(self.pos)
        switch = rng.random(n) < 0.01
        self._goal[switch] = rng.uniform(-1_000_000, 1_000_000, switch.sum())
        stop = rng.random(n) < 0.005
        self._goal[stop] = 0.0
        new_vel = self.vel + np.clip(self._goal - self.vel, -50_000, 50_000)
        self.acc = (new_vel - self.vel) / self.dt
        self.vel = new_vel
        self.pos = self.pos + self.vel * self.dt
        self.homed |= rng.random(n) < 0.01
        # cycles until a reversal if the goal has the opposite sign
        rev = np.where(self._goal * self.vel < 0, np.ceil(np.abs(self.vel) / 50_000), -1).astype(
            np.int64
        )
        self.reversal = rev


_GRID = np.arange(-600.0, 601.0, 50.0)


def _smooth(rng: np.random.Generator, scale: float) -> np.ndarray:
    return scale * np.sin(_GRID / 250.0 + rng.uniform(0, 6))


def volumetric_machine(folder: Path) -> MachineConfig:
    """The default machine with two compensations (docs/volumetric.md §4):

    - ID0, chain YXZ, switched on by object (`manual_activation 1`), ramp of 12 cycles,
      `negate Y`: the 18 component errors of X, Y, Z (a few µm and µrad) and the three
      squareness errors, plus a positioning error of X of 1 µm/mm, so that its X
      correction (about −10 increments per mm of X) passes X's `s_limit` of 150
      increments beyond X ≈ 15 mm, which the program reaches (X20);
    - ID1, chain CYXZ (C on the workpiece side, `alternative_model 1`), on as soon as
      the axes are referenced, ramp of 5 cycles: errors of C over its travel (spliced)
      and a 2-D table of EZZ over X and Y."""
    lists = folder / "lists"
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    rng = np.random.default_rng(11)
    blocks = []
    for axis in "XYZ":
        cols = [_smooth(rng, 3e-3 if d in "XYZ" else 2e-5) for d in "XYZABC"]
        if axis == "X":
            cols[0] = cols[0] + 1e-3 * _GRID
        rows = tuple((float(g), *(float(c[i]) for c in cols)) for i, g in enumerate(_GRID))
        blocks.append(Block((axis,), tuple(f"E{d}{axis}" for d in "XYZABC"), rows))
    blocks.append(Block((), ("C0Y", "B0Z", "A0Z", "N0Z"), ((2e-5, -1e-5, 3e-5, -1.0),)))
    (lists / "vc0.csv").write_text(write_isg_csv(blocks), encoding="utf-8")
    gc = np.arange(0.0, 360.0, 30.0)
    c_rows = tuple(
        (float(c), 2e-3 * np.cos(np.radians(c)), 1e-5 * np.sin(np.radians(c))) for c in gc
    )
    xy = [(float(x), float(y)) for x in (-100.0, 0.0, 100.0) for y in (-100.0, 100.0)]
    z_rows = tuple((x, y, 1e-3 * np.sin(x / 70.0) * np.cos(y / 90.0)) for x, y in xy)
    c_blocks = [
        Block(("C",), ("EXC", "ECC"), c_rows),
        Block(("X", "Y"), ("EZZ",), z_rows),
        Block((), ("PZC", "X0C", "C0C", "N0Z"), ((-50.0, 2e-3, 1e-5, -1.0),)),
    ]
    (lists / "vc1.csv").write_text(write_isg_csv(c_blocks), encoding="utf-8")
    (lists / "vc0.lis").write_text(
        "X 1\nY 2\nZ 3\nchain YXZ\nfilter_steps 12\nmanual_activation 1\nnegate Y\n"
        "file[0] vc0.csv\nfile_format[0] ISG_CSV\n",
        encoding="utf-8",
    )
    (lists / "vc1.lis").write_text(
        "X 1\nY 2\nZ 3\nC 4\nchain CYXZ\nworkpiece_axes 1\nalternative_model 1\n"
        "enable_splicing 1\nfilter_steps 5\nfile[0] vc1.csv\nfile_format[0] ISG_CSV\n",
        encoding="utf-8",
    )
    with (lists / "hochlauf.lis").open("a", encoding="utf-8") as fh:
        for i in (0, 1):
            fh.write(f"vol_comp[{i}].max_records 2000\nvol_comp[{i}].file_name vc{i}.lis\n")
    for i, limit in ((1, 150), (2, 10_000), (3, 10_000)):
        with (lists / f"achsmd{i}.lis").open("a", encoding="utf-8") as fh:
            fh.write(f"lr_param.vol_comp.s_limit {limit}\n")
    cfg = load_machine(lists / "hochlauf.lis")
    assert [c.available for c in cfg.volumetric] == [True, True], [
        c.problem for c in cfg.volumetric
    ]
    return cfg


def updates_read(m: object, timeout: float = 30.0) -> None:
    """Wait until every `#VOLCOMP [.. UPDATE]` machine `m` has under way has read its
    files (a worker thread reads them; the next cycle applies what it read). Stepping
    until a program ends counts cycles, and no count of cycles bounds a thread's wall
    time: a busy host let 3000 cycles run out while the worker read (the test thread
    owns the stepped machine, so it may look at what is loading)."""
    from geo_server.machine.machine import Machine

    assert isinstance(m, Machine)
    for _ident, _since, fut in list(m._volc_loading):
        fut.result(timeout=timeout)


def with_params(cfg: MachineConfig, axis: int, **changes: object) -> MachineConfig:
    """`cfg` with axis `axis`'s parameters changed (a loaded configuration is sealed:
    geo_server.model.Sealed; the copy is not, as a test's own machine needs)."""
    from dataclasses import replace

    from geo_server.model import with_axis_params

    return with_axis_params(cfg, {axis: replace(cfg.axes[axis].params, **changes)})
