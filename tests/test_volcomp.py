"""Volumetric compensation (004, docs/volumetric.md): configuration, model, cycle, objects.

Expected corrections are worked out by hand here from the rigid-body model of
docs/volumetric.md §2 (one error at a time), never by the code under test; the vectorised
kernel is held against the plain reference with many errors at once.
"""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from support.machines import updates_read

from geo_server.dictionary import load_dictionary
from geo_server.listfile import load_machine
from geo_server.listfile.schema import ListKind
from geo_server.listfile.syntax import parse_list
from geo_server.listfile.values import Reporter, read_values
from geo_server.machine.machine import Machine
from geo_server.paths import data_dir
from geo_server.service import ObjectService
from geo_server.volcomp import reference as R
from geo_server.volcomp.config import read_volc_list
from geo_server.volcomp.evaluator import Evaluator
from geo_server.volcomp.model import build_model
from geo_server.volcomp.tables import ParamTable

D = load_dictionary()
EXAMPLES = data_dir("lists") / "examples" / "volumetric"


def table(name: str, arg: str | None = None, points=(), values=()) -> ParamTable:
    if arg is None:
        return ParamTable(name, (), (), np.array(float(values)))
    return ParamTable(name, (arg,), (np.array(points, float),), np.array(values, float))


def model(chain: str = "YXZ", *tables: ParamTable, wp: int = 0):
    return build_model(chain, wp, {t.name: t for t in tables})


# ---------------------------------------------------------------------- examples load


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.lis")), ids=lambda p: p.name)
def test_every_example_list_reads_without_a_warning(path: Path) -> None:
    """Each example of 004 is read as the list it comes from (start-up, axis or VOLC):
    every entry known, every value valid."""
    text = path.read_text(encoding="utf-8")
    kind = (
        ListKind.STUP
        if "vol_comp[" in text
        else ListKind.AXIS
        if "lr_param" in text
        else ListKind.VOLC
    )
    diags: list = []
    values = read_values(parse_list(path), kind, Reporter(diags))
    assert [d.describe() for d in diags] == []
    assert values.data


@pytest.mark.parametrize(
    ("name", "chain", "axes", "files"),
    [
        ("004_p36_vol_comp_0_xyz.lis", "YXZ", {"X": 1, "Y": 2, "Z": 3}, 1),
        ("004_p37_vol_comp_0_yxz.lis", "YXZ", {"X": 1, "Y": 2, "Z": 3}, 1),
        ("004_p37_vol_comp_1_cyxz.lis", "CYXZ", {"X": 1, "Y": 2, "Z": 3, "C": 5}, 1),
        ("004_p23_volcomp1.lis", "XYZ", {"X": 1, "Y": 2, "Z": 3}, 1),
    ],
)
def test_the_manuals_configurations_check(name, chain, axes, files) -> None:
    cfg = read_volc_list(EXAMPLES / name, Reporter([]))
    assert (cfg.chain, cfg.axes, len(cfg.files)) == (chain, axes, files)


def test_p23_configuration_values() -> None:
    cfg = read_volc_list(EXAMPLES / "004_p23_volcomp1.lis", Reporter([]))
    assert cfg.filter_steps == 20 and cfg.interpolation == "GRID"
    assert not (cfg.enable_splicing or cfg.manual_activation or cfg.alternative_model)
    assert cfg.files == ((r"C:\vc\volcomp1.csv", "ISG_CSV", 12),)


# ---------------------------------------------------------------------- a machine


def add_volc(
    startup: Path,
    volc: str,
    files: dict[str, str],
    ident: int = 0,
    max_records: int = 1000,
    s_limit: int | None = 10000,
) -> None:
    folder = startup.parent
    (folder / f"volc{ident}.lis").write_text(volc, encoding="utf-8")
    for name, text in files.items():
        (folder / name).write_text(text, encoding="utf-8")
    with startup.open("a", encoding="utf-8") as fh:
        fh.write(f"vol_comp[{ident}].max_records {max_records}\n")
        fh.write(f"vol_comp[{ident}].file_name volc{ident}.lis\n")
    if s_limit is not None:
        for i in (1, 2, 3):
            with (folder / f"achsmd{i}.lis").open("a", encoding="utf-8") as fh:
                fh.write(f"lr_param.vol_comp.s_limit {s_limit}\n")


def add_second_volc(startup: Path, volc: str) -> None:
    """A second volumetric compensation (ID 1) from the VOLC list text `volc`, beside
    the one `add_volc` configured."""
    (startup.parent / "volc1.lis").write_text(volc, encoding="utf-8")
    with startup.open("a", encoding="utf-8") as fh:
        fh.write("vol_comp[1].max_records 10\nvol_comp[1].file_name volc1.lis\n")


def value(m: Machine, name: str, axis: int = 0):
    return m.snapshot.value(D.by_name(name), axis)


def p23_machine(lists_copy: Path) -> Machine:
    """The p.23 example (C:\\vc\\volcomp1.lis and .csv) on the default machine."""
    folder = lists_copy.parent
    shutil.copy(EXAMPLES / "004_p23_volcomp1.csv", folder / "volcomp1.csv")
    volc = (EXAMPLES / "004_p23_volcomp1.lis").read_text(encoding="utf-8")
    add_volc(lists_copy, volc, {})
    return Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)


def test_p23_example_corrects_by_hand(lists_copy: Path) -> None:
    """004 p.23: EXX = EYY = 0.0002·y (mm, y in mm) on a grid over Y (X = Z = 0). At
    y = 20 mm: Y solves y + Δy + 0.0002(y + Δy) = y → Δy = −0.0002·20/1.0002 =
    −0.0039992 mm; X solves x + Δx + EXX(y + Δy) = x → Δx = −0.0002·(20 + Δy) =
    −0.0039992 mm; both −39.992 increments → −40. filter_steps 20: it ramps in over 20
    cycles after the automatic activation."""
    m = p23_machine(lists_copy)
    assert value(m, "VOLC::available") == 1
    m.motion.set_position(1, 20 * 10_000)
    m.run_cycle()
    assert value(m, "VOLC::active") == 1
    first = value(m, "VOLC::correction", 2)
    assert first == round(-39.992 / 20)  # one step of the ramp of 20
    for _ in range(25):
        m.run_cycle()
    assert [value(m, "VOLC::correction", a) for a in (1, 2, 3)] == [-40, -40, 0]
    out = value(m, "SIM::output_position", 2)
    assert out == pytest.approx(20 * 10_000 + value(m, "SIM::total_offset", 2) - 39.992, abs=1)


def test_p23_grid_holds_its_edges(lists_copy: Path) -> None:
    """Beyond the last record (y = 40 mm, 0.008 mm) the values are held: Δy at 60 mm is
    −0.008/1.0 … solved at y + Δy = 59.99 → EYY = 0.008 → Δy = −0.008 mm = −80."""
    m = p23_machine(lists_copy)
    m.motion.set_position(1, 60 * 10_000)
    for _ in range(30):
        m.run_cycle()
    assert value(m, "VOLC::correction", 2) == -80
    assert value(m, "VOLC::correction", 1) == -80


# ---------------------------------------------------------------------- hand cases


@pytest.mark.parametrize("x", [-300.0, 0.0, 125.0, 480.0])
def test_pure_x_positioning_error(x: float) -> None:
    """EXX(x) = k·x: the tool is at x + k·x, so Δx solves x + Δ + k(x + Δ) = x:
    Δ = −k·x/(1 + k); nothing moves in Y and Z."""
    k = 2e-5
    mdl = model("YXZ", table("EXX", "X", (-500, 500), (-500 * k, 500 * k)))
    want = -k * x / (1 + k)
    got = R.correction(mdl, {"X": x, "Y": 10.0, "Z": -5.0})
    assert got == pytest.approx({"X": want, "Y": 0.0, "Z": 0.0}, abs=1e-12)
    # the kernel's two Newton steps leave (k·x)·k ≈ 1e-12 mm (docs/volumetric.md §2)
    fast = Evaluator(mdl).correction(np.array([[10.0, x, -5.0]]), np.zeros(3))[0]
    assert fast == pytest.approx([want, 0.0, 0.0], abs=1e-10)


@pytest.mark.parametrize(("x", "y", "z"), [(0.0, 0.0, 0.0), (100.0, 250.0, -40.0)])
def test_pure_squareness(x: float, y: float, z: float) -> None:
    """C0Y tilts Y's travel: moving Y by y moves the tool by −C0Y·y in X. B0Z: +B0Z·z
    in X; A0Z: −A0Z·z in Y. So Δy = +A0Z·z, and X must undo what Y's tilt does at the
    corrected Y: Δx = C0Y·(y + Δy) − B0Z·z (exact: the model is linear here)."""
    c0y, b0z, a0z = 50e-6, -30e-6, 20e-6
    mdl = model("YXZ", table("C0Y", values=c0y), table("B0Z", values=b0z), table("A0Z", values=a0z))
    got = R.correction(mdl, {"X": x, "Y": y, "Z": z})
    dx = c0y * (y + a0z * z) - b0z * z
    assert got["X"] == pytest.approx(dx, abs=1e-12)
    assert got["Y"] == pytest.approx(a0z * z, abs=1e-12)
    assert got["Z"] == pytest.approx(0.0, abs=1e-12)
    fast = Evaluator(mdl).correction(np.array([[y, x, z]]), np.zeros(3))[0]
    assert fast == pytest.approx([dx, a0z * z, 0.0], abs=1e-12)


@pytest.mark.parametrize(("z", "length"), [(0.0, 0.0), (0.0, 150.0), (-80.0, 150.0)])
def test_pure_roll_with_a_tool_offset(z: float, length: float) -> None:
    """EAX = a (roll of the X carriage about X): the carriage carries Z and the tool
    (N0 = (0, 0, −1), length L): the tip relative to it is v = (0, 0, z − L), turned by
    Ω(a, 0, 0): v + a·e_x × v = v + (0, −a(z − L), 0). Y is first in the chain and
    carries no error, so Δy = a·(z − L), Δx = Δz = 0 (exactly)."""
    a = 40e-6
    mdl = model("YXZ", table("EAX", "X", (-500, 500), (a, a)), table("N0Z", values=-1.0))
    got = R.correction(mdl, {"X": 30.0, "Y": 0.0, "Z": z}, length)
    assert got == pytest.approx({"X": 0.0, "Y": a * (z - length), "Z": 0.0}, abs=1e-12)
    tip = mdl.tool_point(length)
    fast = Evaluator(mdl).correction(np.array([[0.0, 30.0, z]]), tip)[0]
    assert fast == pytest.approx([0.0, a * (z - length), 0.0], abs=1e-12)


@pytest.mark.slow
def test_rotary_axis_on_the_workpiece_side_is_ideal_without_errors() -> None:
    """CYXZ, workpiece_axes 1: the table turns by −θ (s = −1), so the tool at (x, y, z)
    is at Rot_z(θ)·(x, y, z) in the workpiece frame; θ = 90°: (−y, x, z)."""
    mdl = model("CYXZ", wp=1)
    p = R.forward(mdl, {"C": 90.0, "X": 10.0, "Y": 20.0, "Z": 5.0})
    assert p == pytest.approx([-20.0, 10.0, 5.0], abs=1e-12)
    fast = Evaluator(mdl).forward(np.array([[90.0, 20.0, 10.0, 5.0]]), np.zeros(3))[0]
    assert fast == pytest.approx([-20.0, 10.0, 5.0], abs=1e-12)


def test_rotary_axis_position_shift() -> None:
    """X0C = d shifts the table (workpiece side) by d in X after the ideal rotation, so
    the tool is at Rot_z(θ)·(p − (d, 0, 0)) relative to it; the linear axes correct it
    by moving +d in X (in the machine frame): Δx = d, Δy = 0 at any θ."""
    d = 0.01
    mdl = model("CYXZ", table("X0C", values=d), wp=1)
    for theta in (0.0, 30.0, 90.0):
        got = R.correction(mdl, {"C": theta, "X": 50.0, "Y": -20.0, "Z": 0.0})
        assert got == pytest.approx({"X": d, "Y": 0.0, "Z": 0.0}, abs=1e-12)
        fast = Evaluator(mdl).correction(np.array([[theta, -20.0, 50.0, 0.0]]), np.zeros(3))
        assert fast[0] == pytest.approx([d, 0.0, 0.0], abs=1e-12)


def smooth_model(seed: int, chain: str = "YXZ", wp: int = 0) -> object:
    """All 18 component errors as smooth curves (a few µm, tens of µrad) and the three
    squareness errors: a realistic machine."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-500.0, 500.0, 21)
    tabs = []
    for a in "XYZ":
        for c, scale in (("EX", 5e-3), ("EY", 3e-3), ("EZ", 3e-3)):
            ph = rng.uniform(0, 6)
            tabs.append(table(f"{c}{a}", a, g, scale * np.sin(g / 300.0 + ph)))
        for c in ("EA", "EB", "EC"):
            ph = rng.uniform(0, 6)
            tabs.append(table(f"{c}{a}", a, g, 3e-5 * np.sin(g / 400.0 + ph)))
    tabs += [table("C0Y", values=2e-5), table("B0Z", values=-1e-5), table("A0Z", values=3e-5)]
    tabs.append(table("N0Z", values=-1.0))
    if "C" in chain:
        gc = np.linspace(0.0, 360.0, 37)
        tabs += [table("EXC", "C", gc, 2e-3 * np.cos(np.radians(gc))), table("PZC", values=-50.0)]
        tabs += [table("ECC", "C", gc, 2e-5 * np.sin(np.radians(gc)))]
    return model(chain, *tabs, wp=wp)


@pytest.mark.parametrize(("chain", "wp"), [("YXZ", 0), ("XYZ", 1), ("CYXZ", 1), ("YXZC", 0)])
def test_kernel_matches_the_reference(chain: str, wp: int) -> None:
    """The vectorised kernel (one position: Python floats; a batch: numpy) against the
    plain reference, 40 positions across the volume, a 120 mm tool: within 1e-9 mm."""
    mdl = smooth_model(3, chain, wp)
    ev = Evaluator(mdl)  # type: ignore[arg-type]
    rng = np.random.default_rng(7)
    q = rng.uniform(-480, 480, size=(40, len(chain)))
    if "C" in chain:
        q[:, chain.index("C")] = rng.uniform(0, 360, size=40)
    tip = mdl.tool_point(120.0)  # type: ignore[attr-defined]
    batch = ev.correction(q, tip)
    for i, row in enumerate(q):
        ref = R.correction(mdl, dict(zip(chain, row, strict=True)), 120.0)  # type: ignore[arg-type]
        want = [ref["X"], ref["Y"], ref["Z"]]
        assert batch[i] == pytest.approx(want, abs=1e-9)
        assert ev.correction(row[None, :], tip)[0] == pytest.approx(want, abs=1e-9)


def test_correction_puts_the_imperfect_tool_on_the_ideal_one() -> None:
    mdl = smooth_model(5)
    q = {"X": 123.0, "Y": -321.0, "Z": 45.0}
    d = R.correction(mdl, q, 80.0)  # type: ignore[arg-type]
    moved = {a: q[a] + d[a] for a in q}
    assert R.forward(mdl, moved, 80.0) == pytest.approx(  # type: ignore[arg-type]
        R.forward(mdl, q, 80.0, errors=False),
        abs=1e-12,  # type: ignore[arg-type]
    )
    assert math.dist(R.forward(mdl, q, 80.0), R.forward(mdl, q, 80.0, errors=False)) > 0.005  # type: ignore[arg-type]


# ---------------------------------------------------------------------- switching, NC, ADS


def smooth_files(folder: Path) -> str:
    """A pure X positioning error EXX = 2e-5·x (ISG CSV) and its VOLC list text."""
    (folder / "exx.csv").write_text("X EXX\n-1000 -0.02\n1000 0.02\n", encoding="utf-8")
    return (
        "X 1\nY 2\nZ 3\nchain YXZ\nfilter_steps 4\nmanual_activation 1\n"
        "file[0] exx.csv\nfile_format[0] ISG_CSV\n"
    )


def test_nc_volcomp_on_ramps_weights_and_off(lists_copy: Path) -> None:
    """#VOLCOMP ON [ID0 CFACT_X=0.5] at x = 100 mm: Δx = −2e-5·100/1.00002 mm =
    −19.9996 increments, weighted 0.5 → −9.9998, ramped over filter_steps 4 cycles
    (a quarter per cycle); OFF ramps it out; NO_MOVE switches at once (004 p.21-22)."""
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.run_cycle()
    assert value(m, "VOLC::active") == 0  # manual_activation 1: waits for #VOLCOMP
    m.start_program("N10 #VOLCOMP ON [ID=0 CFACT_X=0.5]\nM30\n", mdi=True)
    seen = []
    for _ in range(8):
        m.run_cycle()
        seen.append(m.volc.offset[0])
    full = -2e-5 * 100 / 1.00002 * 10_000 * 0.5
    ramp = [v for v in seen if v != 0.0]
    assert ramp[:4] == pytest.approx([full / 4, full / 2, 3 * full / 4, full], abs=1e-6)
    assert value(m, "VOLC::correction", 1) == -10 and value(m, "VOLC::active") == 1
    m.start_program("#VOLCOMP OFF [ID0 NO_MOVE]\n", mdi=True)
    m.run_cycle()
    m.run_cycle()
    assert value(m, "VOLC::active") == 0 and m.volc.offset[0] == 0.0
    m.start_program("#VOLCOMP ON ALL\n", mdi=True)
    for _ in range(6):
        m.run_cycle()
    assert m.volc.offset[0] == pytest.approx(full * 2, abs=1e-6)  # CFACT is not modal


def held_around_a_move(m: Machine, line: str, cycles: int) -> tuple[list[int], list[int]]:
    """`VOLC::held` of X over `cycles` cycles after starting the MDI `line`: the values
    before X's first moving cycle and those from it on."""
    m.start_program(line + "\n", mdi=True)
    held, moving = [], []
    for _ in range(cycles):
        m.run_cycle()
        held.append(value(m, "VOLC::held", 1))
        moving.append(value(m, "SIM::velocity", 1) != 0)
    first = moving.index(True)
    return held[:first], held[first:]


def test_no_move_holds_the_drive_until_the_axis_moves(lists_copy: Path) -> None:
    """004 p.21: with NO_MOVE "the axes do not move when compensation is activated/
    deactivated", as the axis compensations' NO_MOVE, whose offset "is only executed at
    the next axis motion programmed" (000 p.94). At x = 100 mm the correction is −20
    increments (−19.9996): #VOLCOMP ON [ID0 NO_MOVE] switches it on at once, the drive
    keeps what it got (VOLC::held +20, the output unchanged) until X moves; from the
    motion's first cycle the +20 ramps out over filter_steps 4 (15, 10, 5, 0). OFF
    NO_MOVE at rest likewise holds −20."""
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    for _ in range(30):
        m.run_cycle()
    before = value(m, "SIM::output_position", 1)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    for _ in range(5):
        m.run_cycle()
        assert value(m, "VOLC::correction", 1) == -20 or value(m, "VOLC::active") == 0
        assert value(m, "SIM::output_position", 1) == before
    assert value(m, "VOLC::held", 1) == 20
    before_motion, from_motion = held_around_a_move(m, "G91 G01 X-0.01 F60", 8)
    assert set(before_motion) <= {20} and from_motion[:4] == [15, 10, 5, 0]
    for _ in range(50):
        m.run_cycle()
    before = value(m, "SIM::output_position", 1)
    m.start_program("#VOLCOMP OFF [ID0 NO_MOVE]\n", mdi=True)
    for _ in range(5):
        m.run_cycle()
    assert value(m, "VOLC::correction", 1) == 0 and value(m, "VOLC::held", 1) == -20
    assert value(m, "SIM::output_position", 1) == before


def test_a_second_hold_keeps_the_first_ones_ramp(lists_copy: Path) -> None:
    """Two compensations, each −20 increments on X at x = 100 mm (EXX = 2e-5·x), the
    first with filter_steps 4, the second with 2, both switched on with NO_MOVE: the
    drive keeps what it got when the first held it (VOLC::held +40) and, from the first
    moving cycle, ramps the 40 out over the first hold's 4 cycles (30, 20, 10, 0): an
    axis already held keeps what it holds, its ramp included."""
    folder = lists_copy.parent
    add_volc(lists_copy, smooth_files(folder), {})
    second = smooth_files(folder).replace("filter_steps 4", "filter_steps 2")
    add_second_volc(lists_copy, second)
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    for _ in range(30):
        m.run_cycle()
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n#VOLCOMP ON [ID1 NO_MOVE]\n", mdi=True)
    for _ in range(5):
        m.run_cycle()
    assert value(m, "VOLC::held", 1) == 40
    before_motion, from_motion = held_around_a_move(m, "G91 G01 X-0.01 F60", 8)
    assert set(before_motion) <= {40} and from_motion[:4] == [30, 20, 10, 0]


def test_s_limit_missing_refuses_activation(lists_copy: Path) -> None:
    add_volc(lists_copy, smooth_files(lists_copy.parent), {}, s_limit=None)
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.start_program("#VOLCOMP ON [ID0]\n", mdi=True)
    m.run_cycle()
    m.run_cycle()
    assert value(m, "VOLC::active") == 0
    last = value(m, "SIM::last_error")
    assert "s_limit" in last and "P-AXIS-00525" in last


def test_s_limit_exceeded_switches_off(lists_copy: Path) -> None:
    """s_limit 15 increments (1.5 µm): at x = 100 mm the correction is 20 increments."""
    add_volc(lists_copy, smooth_files(lists_copy.parent), {}, s_limit=15)
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    for _ in range(3):
        m.run_cycle()
    assert value(m, "VOLC::active") == 0 and m.volc.offset[0] == 0.0
    assert "exceeds lr_param.vol_comp.s_limit 15" in value(m, "SIM::last_error")


@pytest.mark.parametrize(
    ("volc", "message"),
    [
        ("X 1\nY 2\nZ 3\nchain YXQ\n", "unknown axis letter 'Q'"),
        ("X 1\nY 2\nchain YX\n", "exactly the 3 linear axes"),
        ("X 1\nY 2\nZ 9\nchain YXZ\n", "axis 9 is not an axis of the machine"),
        ("X 1\nY 2\nZ 3\ninterpolation SPLINE\n", "not one of GRID, SCATTER"),
        ("X 1\nY 2\nZ 3\nfile[0] nowhere.csv\nfile_format[0] ISG_CSV\n", "nowhere.csv not found"),
        ("X 1\nY 2\nZ 3\nfile[0] exx.csv\n", "file[0] without file_format[0]"),
    ],
)
def test_bad_configuration_is_an_error_with_file_and_line(lists_copy, volc, message) -> None:
    add_volc(lists_copy, volc, {})
    cfg = load_machine(lists_copy)
    (comp,) = cfg.volumetric
    assert not comp.available and message in comp.problem
    errors = [d for d in cfg.diagnostics if d.error_id == 990525]
    assert errors and message in errors[0].message and errors[0].file


def test_more_records_than_max_records(lists_copy: Path) -> None:
    add_volc(lists_copy, smooth_files(lists_copy.parent), {}, max_records=1)
    (comp,) = load_machine(lists_copy).volumetric
    assert "2 records in the correction files, more than vol_comp[0].max_records 1" in comp.problem


def within_cycles(
    m: Machine, done: Callable[[], bool], cycles: int = 1000, seconds: float = 30.0
) -> bool:
    """Poll `done` until it holds, or machine `m` (in real time) has run `cycles` more
    cycles and `seconds` have passed: a bound in the machine's own time, not in reads — a
    cycle thread starved by a busy host lets any number of reads run out before a 4-cycle
    ramp (filter_steps) has ended — and in wall time for an UPDATE, whose files a worker
    reads first (docs/volumetric.md §7)."""
    end, late = m.cycle + cycles, time.monotonic() + seconds
    while not done():
        if m.cycle >= end and time.monotonic() >= late:
            return False
        time.sleep(0.001)  # (the cycle thread needs the interpreter lock to advance)
    return True


@pytest.mark.realtime
def test_com_objects_over_ads_port_553(lists_copy: Path, loop_thread) -> None:
    """004 p.19, p.22-23 through pyads on AMS port 553: enable (0x291), disable (0x292),
    and an update: the ID to 0x27D, then the VOLC list's path to 0x27C (the second
    write triggers it, docs/volumetric.md §7); the read-back objects on port 551."""
    import pyads
    from conftest import run_in

    from geo_server.client.ads_client import AdsClient, close_port_first
    from geo_server.machine.scheduler import Scheduler
    from geo_server.transports.ads.server import AdsOptions, AdsServer

    folder = lists_copy.parent
    add_volc(lists_copy, smooth_files(folder), {})
    (folder / "twice.csv").write_text("X EXX\n-1000 -0.04\n1000 0.04\n", encoding="utf-8")
    (folder / "other.lis").write_text(
        smooth_files(folder).replace("exx.csv", "twice.csv"), encoding="utf-8"
    )
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    sched = Scheduler(m, mode="realtime")
    service = ObjectService(m, sched)
    sched.start()
    srv = AdsServer(service, AdsOptions(port=0))
    run_in(loop_thread, srv.start())
    com = pyads.Connection("127.0.0.9.1.1", 553, srv.address)
    geo = pyads.Connection("127.0.0.9.1.1", 551, srv.address)
    com.open()
    geo.open()
    # the manual's addresses of the COM objects (004 p.19) are typed here on purpose: the
    # test holds the dictionary to them; the emulator's read-back objects come from it
    corr, active, vfile = (D.by_name(n) for n in ("VOLC::correction", "VOLC::active", "VOLC::file"))
    sim = corr.index_group
    try:
        com.write(0x120100, 0x291, 0, pyads.PLCTYPE_UINT)  # enable ID 0

        def correction() -> int:
            return int(geo.read(sim, corr.index_offset(1), pyads.PLCTYPE_DINT))

        assert within_cycles(m, lambda: correction() == -20), correction()
        assert geo.read(sim, active.index_offset(0), pyads.PLCTYPE_UINT) == 1
        com.write(0x120100, 0x292, 0, pyads.PLCTYPE_UINT)  # disable ID 0
        com.write(0x120100, 0x27D, 0, pyads.PLCTYPE_UINT)
        com.write(0x120100, 0x27C, str(folder / "other.lis"), pyads.PLCTYPE_STRING)
        assert geo.read(sim, vfile.index_offset(0), pyads.PLCTYPE_STRING) == str(
            folder / "other.lis"
        )
        com.write(0x120100, 0x291, 0, pyads.PLCTYPE_UINT)
        # twice the error: −4e-5·100/1.00004 mm = −39.998 increments
        assert within_cycles(m, lambda: correction() == -40), correction()
        with pytest.raises(pyads.ADSError) as exc:  # write-only (004 p.19)
            com.read(0x120100, 0x291, pyads.PLCTYPE_UINT)
        assert exc.value.err_code == 0x704
        with pytest.raises(pyads.ADSError) as exc:  # ID 3 is not configured
            com.write(0x120100, 0x291, 3, pyads.PLCTYPE_UINT)
        assert exc.value.err_code == 0x706
        with pytest.raises(pyads.ADSError) as exc:  # a list that is not there
            com.write(0x120100, 0x27C, "missing.lis", pyads.PLCTYPE_STRING)
        assert exc.value.err_code == 0x70D  # syntax error in the lists (design.md §9)
        with pytest.raises(pyads.ADSError) as exc:  # the COM group is not the GEO task's
            geo.write(0x120100, 0x291, 0, pyads.PLCTYPE_UINT)
        assert exc.value.err_code == 0x702
        # geo-client's ADS client opens the COM task's port for these objects by name
        host, port = srv.address.rsplit(":", 1)
        with AdsClient(host, int(port), netid="127.0.0.10.1.1") as client:
            client.write("cnc_vol_comp_disable_index_w", 0, 0)
            # ramped out over filter_steps (4 cycles)
            assert within_cycles(m, lambda: client.read("VOLC::active") == 0)
            client.write("cnc_vol_comp_enable_index_w", 0, 0)
            assert client.read("VOLC::active") == 1
    finally:
        close_port_first(com)
        close_port_first(geo)
        run_in(loop_thread, srv.close())
        sched.stop()


# ---------------------------------------------------------------------- review findings


def test_a_second_automatic_compensation_starts_while_one_acts(lists_copy: Path) -> None:
    """manual_activation 0 for both; C is referenced late: ID1 (chain CYXZ) starts in
    the first cycle in which every axis of its chain is referenced, ID0 (YXZ) acting."""
    folder = lists_copy.parent
    auto = smooth_files(folder).replace("manual_activation 1", "manual_activation 0")
    add_volc(lists_copy, auto, {})
    cyxz = auto.replace("chain YXZ", "C 4\nchain CYXZ\nworkpiece_axes 1")
    add_second_volc(lists_copy, cyxz)
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.homed[3] = False
    m.run_cycle()
    assert value(m, "VOLC::active") == 1  # C not referenced: ID0 only
    m.motion.home(3)
    m.run_cycle()
    assert value(m, "VOLC::active") == 3


def test_referencing_is_a_precondition_and_losing_it_switches_off(lists_copy: Path) -> None:
    """004 p.20: each axis must be referenced; p.24: an axis error removes the values
    without movement."""
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=False)
    m.start_program("#VOLCOMP ON [ID0]\n", mdi=True)
    m.run_cycle()
    m.run_cycle()
    assert value(m, "VOLC::active") == 0
    assert "must be referenced" in value(m, "SIM::last_error")
    for s in range(3):
        m.motion.home(s)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    m.run_cycle()
    m.run_cycle()
    assert value(m, "VOLC::active") == 1
    m.motion.homed[0] = False
    m.run_cycle()
    assert value(m, "VOLC::active") == 0 and m.volc.offset[0] == 0.0
    assert "lost its reference" in value(m, "SIM::last_error")


def test_s_limit_bounds_the_sum_on_an_axis(lists_copy: Path) -> None:
    """Two compensations of −20 increments each on X, s_limit 30: each alone is within
    it, the axis would get −40 (004 p.14: the value for this axis)."""
    folder = lists_copy.parent
    add_volc(lists_copy, smooth_files(folder), {}, s_limit=30)
    add_second_volc(lists_copy, smooth_files(folder))
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n#VOLCOMP ON [ID1 NO_MOVE]\n", mdi=True)
    for _ in range(5):
        m.run_cycle()
    assert abs(value(m, "VOLC::correction", 1)) <= 30
    assert "exceeds lr_param.vol_comp.s_limit 30" in value(m, "SIM::last_error")


def test_an_update_interrupted_by_reset_is_dropped(lists_copy: Path) -> None:
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.start_program("#VOLCOMP [ID0 UPDATE]\n", mdi=True)
    m.run_cycle()
    m.run_cycle()
    m.reset()
    assert m._volc_loading == []
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    for _ in range(5):
        m.run_cycle()
    assert value(m, "VOLC::active") == 1 and value(m, "VOLC::correction", 1) == -20


def test_a_broken_update_keeps_the_compensation(lists_copy: Path) -> None:
    """Like the CNC object (docs/volumetric.md §7): the old compensation stays, the
    program stops with the error."""
    folder = lists_copy.parent
    add_volc(lists_copy, smooth_files(folder), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    for _ in range(3):
        m.run_cycle()
    (folder / "exx.csv").write_text("X EXX\n0 nan\n", encoding="utf-8")
    m.start_program("#VOLCOMP [ID0 UPDATE]\n", mdi=True)
    for _ in range(3000):
        updates_read(m)
        m.run_cycle()
        if m.player is not None and not m.player.running:
            break
    assert value(m, "VOLC::available") == 1 and value(m, "VOLC::correction", 1) == -20
    assert "UPDATE] failed, compensation unchanged" in value(m, "SIM::last_error")


def test_reload_keeps_what_is_switched_on_and_the_tool_length(lists_copy: Path) -> None:
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.volc.tool_length = 150.0
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    for _ in range(3):
        m.run_cycle()
    m.reload(load_machine(lists_copy))
    m.run_cycle()
    assert value(m, "VOLC::active") == 1 and value(m, "VOLC::correction", 1) == -20
    assert value(m, "VOLC::tool_length") == 150.0


def test_mixed_splicing_on_one_axis_matches_the_reference() -> None:
    """A spliced 1-D table of C beside one that is not (over −180 … 180): each is
    taken modulo 360° or not on its own, as the reference does."""
    gc = np.array([0.0, 90.0, 180.0, 270.0, 360.0])
    exc = ParamTable("EXC", ("C",), (gc,), np.array([0.0, 3e-3, 0.0, -3e-3, 0.0]), spliced=True)
    eyc = table("EYC", "C", (-180.0, 0.0, 180.0), (3e-3, 0.0, -3e-3))
    mdl = model("CYXZ", exc, eyc, wp=1)
    ev = Evaluator(mdl)
    for c in (-90.0, 45.0, 300.0):
        ref = R.correction(mdl, {"C": c, "X": 10.0, "Y": 5.0, "Z": 0.0})
        got = ev.correction(np.array([[c, 5.0, 10.0, 0.0]]), np.zeros(3))[0]
        assert got == pytest.approx([ref["X"], ref["Y"], ref["Z"]], abs=1e-9)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("#VOLCOMP ON [ID0 ID1]", "one ID per command"),
        ("#VOLCOMP ON [ID0] M30", "must stand alone"),
        ("G01 X1 #VOLCOMP ON [ID0]", "must stand alone"),
        ("#VOLCOMP ON [ID0 CFACT_X=1.5]", "permitted values are 0.0"),
        ("#VOLCOMP [ID0 UPDATE NO_MOVE]", "takes no ON/OFF, NO_MOVE or CFACT"),
        ("#VOLCOMP ON [ID7]", "the IDs are 0 … 4"),
        ("#VOLCOMP ON", "name the compensation"),
    ],
)
def test_volcomp_nc_errors(text: str, message: str) -> None:
    from geo_server.machine.nc import NcError, parse_program

    with pytest.raises(NcError, match=message):
        parse_program(text, {"X": 0, "Y": 1, "Z": 2}, mdi=True)


def test_volcomp_nc_forms() -> None:
    """The manual's forms (004 p.21, p.23), a continuation and an exponent."""
    from geo_server.machine.nc import VolcompCommand, parse_program

    prog = parse_program(
        "N10 #VOLCOMP ON [ID0]\nN90 #VOLCOMP OFF [ID0]\nN100 #VOLCOMP [ID0 UPDATE]\n"
        "#VOLCOMP ON ALL\n#VOLCOMP ON [ID=1 \\\n NO_MOVE CFACT_X=5E-1 CFACT_Z=0]\n",
        {"X": 0},
        mdi=True,
    )
    assert [b.volcomp for b in prog.blocks] == [
        VolcompCommand(True, (0,)),
        VolcompCommand(False, (0,)),
        VolcompCommand(False, (0,), update=True),
        VolcompCommand(True, None),
        VolcompCommand(True, (1,), True, (0.5, 1.0, 0.0)),
    ]


# ---------------------------------------------------------------------- SCATTER, PATH


def point_table(mode: str, args, points, values) -> ParamTable:
    return ParamTable(
        "EZZ",
        tuple(args),
        (),
        np.array(np.nan),
        mode=mode,
        points=np.array(points, float),
        point_values=np.array(values, float),
    )


def test_scatter_is_inverse_distance_weighting() -> None:
    """Records at (0, 0), (100, 0), (0, 100) of 0, 3, 6 µm: at a record its value; at
    (50, 0) the distances² are 2500, 2500, 12500, so the weights 1/2500, 1/2500,
    1/12500: (0 + 3/2500 + 6/12500)/(2/2500 + 1/12500) = (0.0012 + 0.00048)/0.00088
    = 1.909090… µm."""
    from geo_server.volcomp.tables import evaluate

    t = point_table("SCATTER", "XY", [(0, 0), (100, 0), (0, 100)], [0.0, 3e-3, 6e-3])
    assert evaluate(t, {"X": 100.0, "Y": 0.0}) == 3e-3
    assert evaluate(t, {"X": 50.0, "Y": 0.0}) == pytest.approx(1.68e-6 / 0.00088, abs=1e-15)
    mdl = model("YXZ", t)
    ev = Evaluator(mdl)
    for x, y in ((50.0, 0.0), (100.0, 0.0), (20.0, 70.0)):
        ref = R.correction(mdl, {"X": x, "Y": y, "Z": 0.0})
        got = ev.correction(np.array([[y, x, 0.0]]), np.zeros(3))[0]
        assert got == pytest.approx([ref["X"], ref["Y"], ref["Z"]], abs=1e-12)
    # EZZ moves the tool in Z: Δz = −EZZ (it depends on X, Y only)
    assert R.correction(mdl, {"X": 50.0, "Y": 0.0, "Z": 0.0})["Z"] == pytest.approx(
        -1.68e-6 / 0.00088, abs=1e-12
    )


def test_path_interpolates_along_the_nearest_section() -> None:
    """Corners (0, 0), (100, 0), (100, 100) with 0, 1, 2 µm: at (50, 10) the nearest
    point of the polygon is (50, 0), half way along the first section: 0.5 µm; at
    (120, 40) it is (100, 40) on the second: 1.4 µm; beyond the ends the end values."""
    from geo_server.volcomp.tables import evaluate

    t = point_table("PATH", "XY", [(0, 0), (100, 0), (100, 100)], [0.0, 1e-3, 2e-3])
    assert evaluate(t, {"X": 50.0, "Y": 10.0}) == pytest.approx(0.5e-3, abs=1e-15)
    assert evaluate(t, {"X": 120.0, "Y": 40.0}) == pytest.approx(1.4e-3, abs=1e-15)
    assert evaluate(t, {"X": -30.0, "Y": -5.0}) == 0.0
    assert evaluate(t, {"X": 100.0, "Y": 300.0}) == 2e-3
    xy = point_table("PATH_XY", "XYZ", [(0, 0, 0), (100, 0, 500)], [0.0, 1e-3])
    assert evaluate(xy, {"X": 50.0, "Y": 10.0, "Z": -400.0}) == pytest.approx(0.5e-3)
    for tab in (t, xy):
        mdl = model("YXZ", tab)
        ev = Evaluator(mdl)
        for x, y, z in ((50.0, 10.0, 0.0), (120.0, 40.0, -3.0), (-30.0, -5.0, 7.0)):
            ref = R.correction(mdl, {"X": x, "Y": y, "Z": z})
            got = ev.correction(np.array([[y, x, z]]), np.zeros(3))[0]
            assert got == pytest.approx([ref["X"], ref["Y"], ref["Z"]], abs=1e-12)


@pytest.mark.parametrize(
    ("interp", "csv", "mode"),
    [
        ("AUTO", "X Y EZZ\n0 0 0\n100 0 0.001\n0 100 0.002\n100 100 0.003\n", "GRID"),
        ("AUTO", "X Y EZZ\n0 0 0\n100 0 0.001\n0 100 0.002\n", "SCATTER"),
        ("SCATTER", "X Y EZZ\n0 0 0\n100 0 0.001\n0 100 0.002\n", "SCATTER"),
        ("PATH", "X Y EZZ\n0 0 0\n100 0 0.001\n100 100 0.002\n", "PATH"),
        ("PATH_XY", "X Y Z EZZ\n0 0 0 0\n100 0 9 0.001\n", "PATH_XY"),
    ],
)
def test_interpolation_modes_load(lists_copy: Path, interp: str, csv: str, mode: str) -> None:
    """004 p.34: AUTO takes GRID when the records form a grid, else SCATTER."""
    folder = lists_copy.parent
    (folder / "e.csv").write_text(csv, encoding="utf-8")
    volc = f"X 1\nY 2\nZ 3\ninterpolation {interp}\nfile[0] e.csv\nfile_format[0] ISG_CSV\n"
    add_volc(lists_copy, volc, {})
    (comp,) = load_machine(lists_copy).volumetric
    assert comp.available, comp.problem
    assert comp.model.tables["EZZ"].mode == mode


def test_path_xy_needs_x_and_y(lists_copy: Path) -> None:
    (lists_copy.parent / "e.csv").write_text("X Z EZZ\n0 0 0\n1 1 1\n", encoding="utf-8")
    volc = "X 1\nY 2\nZ 3\ninterpolation PATH_XY\nfile[0] e.csv\nfile_format[0] ISG_CSV\n"
    add_volc(lists_copy, volc, {})
    (comp,) = load_machine(lists_copy).volumetric
    assert "PATH_XY needs X and Y" in comp.problem


def test_v_g_volcomp_variables_read_write_and_update(lists_copy: Path) -> None:
    """004 p.18: `V.G.VOLCOMP[i].ACTIVE` reads whether compensation i is active (no write
    access); `V.G.VOLCOMP[i].FILE[j]` reads and writes the name of its file j (the VOLC
    list's file[j]); reading them flushes the channel (read when the block is reached).
    The program switches ID0 on only while it is off, checks the listed file by name,
    names a second file with twice the error (EXX = 4e-5·x), updates and switches on:
    at x = 100 mm Δx = −20 increments before (−2e-5·100/1.00002 mm) and −40 after
    (−4e-5·100/1.00004 mm = −39.998). Each #MSG below says a condition held."""
    folder = lists_copy.parent
    add_volc(lists_copy, smooth_files(folder), {"exx2.csv": "X EXX\n-1000 -0.04\n1000 0.04\n"})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    program = (
        "N10 $IF V.G.VOLCOMP[0].ACTIVE == FALSE\n"
        "N20 #VOLCOMP ON [ID0]\n"
        "N30 $ENDIF\n"
        '$IF V.G.VOLCOMP[0].ACTIVE AND V.G.VOLCOMP[0].FILE[0] == "exx.csv"\n'
        '#MSG ["on, from exx.csv"]\n'
        "$ENDIF\n"
        '$IF V.G.VOLCOMP[0].FILE[1] == ""\n'
        '#MSG ["no file[1]"]\n'
        "$ENDIF\n"
        'N40 V.G.VOLCOMP[0].FILE[0] = "exx2.csv"\n'
        '$IF V.G.VOLCOMP[0].FILE[0] != "exx.csv"\n'
        '#MSG ["renamed"]\n'
        "$ENDIF\n"
        "#VOLCOMP OFF [ID0]\n"
        "#VOLCOMP [ID0 UPDATE]\n"
        "#VOLCOMP ON [ID0]\n"
        "M30\n"
    )
    m.start_program(program)
    seen = []
    for _ in range(3000):
        updates_read(m)
        m.run_cycle()
        seen.append(value(m, "VOLC::correction", 1))
        if m.player is not None and not m.player.running:
            break
    assert m.player is not None and m.player.error is None and m.player.finished
    messages = [ev.diagnostic.message for ev in m.events if ev.diagnostic.severity == "message"]
    assert messages == ["on, from exx.csv", "no file[1]", "renamed"]
    assert -20 in seen and seen[-1] == -40
    # the list on disk is unchanged (004 p.23: an update does not change the configuration)
    assert "file[0] exx.csv" in (folder / "volc0.lis").read_text(encoding="utf-8")


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("V.G.VOLCOMP[0].ACTIVE = 1", "is read only"),
        ('V.G.VOLCOMP[5].FILE[0] = "a.csv"', "the ID is 0 … 4"),
        ('V.G.VOLCOMP[0].FILE[10] = "a.csv"', "the index is 0 … 9"),
        ('$IF V.G.VOLCOMP[0].FILE[0] < "a.csv"', "by == or != only"),
        ("$IF V.G.VOLCOMP[0].FILE[0] == 1", "by == or != only"),
        ('$IF "a.csv"', "by == or != only"),
        ('X10 V.G.VOLCOMP[0].FILE[0] = "a.csv"', "stands alone"),
    ],
)
def test_v_g_volcomp_syntax_errors(line: str, message: str) -> None:
    from geo_server.machine.nc import NcError, parse_program

    with pytest.raises(NcError, match=message):
        parse_program(line + "\n$ENDIF\nM30\n" if line.startswith("$IF") else line, {"X": 0})


def test_v_g_volcomp_file_of_an_unconfigured_compensation_stops_the_program(
    lists_copy: Path,
) -> None:
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.start_program('N10 V.G.VOLCOMP[3].FILE[0] = "a.csv"\nM30\n')
    for _ in range(3):
        m.run_cycle()
    assert m.player is not None and m.player.error is not None
    assert "no volumetric compensation 3" in m.player.error.message


def test_a_ramped_switch_executes_what_a_no_move_held(lists_copy: Path) -> None:
    """#VOLCOMP ON [ID0 NO_MOVE] at rest at x = 100 mm: the drive keeps 0 (VOLC::held
    +20). #VOLCOMP OFF [ID0] (ramped, the axis standing): the held +20 ramps out with the
    switch over filter_steps 4 while the correction ramps from −20 to 0 — the output, sum
    plus held, goes from 0 to 0 through −20·(1−k/4) + 20·(1−k/4) = 0 and both end at 0.
    Then ON [ID0] ramps −5, −10, −15, −20 into the drive. Before: the whole ramp went into
    VOLC::held and the output never changed."""
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.run_cycle()
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\n", mdi=True)
    for _ in range(3):
        m.run_cycle()
    assert value(m, "VOLC::held", 1) == 20
    m.start_program("#VOLCOMP OFF [ID0]\n", mdi=True)
    for _ in range(8):
        m.run_cycle()
    assert value(m, "VOLC::held", 1) == 0 and value(m, "VOLC::correction", 1) == 0
    m.start_program("#VOLCOMP ON [ID0]\n", mdi=True)
    out = []  # what the drive gets of the volumetric compensation: sum + held
    for _ in range(8):
        m.run_cycle()
        out.append(value(m, "VOLC::correction", 1) + value(m, "VOLC::held", 1))
    assert [d for d in out if d][:4] == [-5, -10, -15, -20]


def test_a_reload_without_volumetric_compensation_leaves_no_stale_correction(
    lists_copy: Path,
) -> None:
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    m.start_program("#VOLCOMP ON [ID0 NO_MOVE]\nG91 G01 X0.001 F600\n", mdi=True)
    for _ in range(40):
        m.run_cycle()
    assert value(m, "VOLC::correction", 1) == -20
    text = lists_copy.read_text(encoding="utf-8")
    lists_copy.write_text(
        "".join(ln + "\n" for ln in text.splitlines() if not ln.startswith("vol_comp[")),
        encoding="utf-8",
    )
    m.reload(load_machine(lists_copy))
    m.run_cycle()
    assert value(m, "VOLC::correction", 1) == 0 and value(m, "VOLC::held", 1) == 0


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("secret.txt", "password\n"),  # not a correction file: its content is not quoted
        ("nothere.csv", None),  # missing: not where it was looked for
        ("sub", "dir"),  # a directory
        ("../outside.csv", "X EXX\n0 0\n"),  # outside the machine's folder
    ],
)
def test_a_file_an_nc_program_names_is_refused_with_one_text(
    lists_copy: Path, name: str, text: str | None
) -> None:
    """docs/security.md "Files": a name from the network that cannot be used gets one
    text, which says nothing of the file (its content, existence, path)."""
    from geo_server.safefile import REFUSED

    folder = lists_copy.parent
    add_volc(lists_copy, smooth_files(folder), {})
    if text == "dir":
        (folder / name).mkdir()
    elif text is not None:
        (folder / name).write_text(text, encoding="utf-8")
    m = Machine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    m.start_program(f'V.G.VOLCOMP[0].FILE[0] = "{name}"\n#VOLCOMP [ID0 UPDATE]\n', mdi=True)
    for _ in range(3000):
        updates_read(m)
        m.run_cycle()
        if m.player is not None and not m.player.running:
            break
    message = value(m, "SIM::last_error")
    assert "UPDATE] failed, compensation unchanged" in message and REFUSED in message
    for leak in ("password", "looked for", "directory", str(folder), "outside"):
        assert leak not in message, message
