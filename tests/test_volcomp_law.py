"""The compiled volumetric law (`volcomp.law`, docs/volumetric.md §2, §3, §6) against the
readable oracle (`volcomp.reference`).

Models: the manual's example VOLC lists (lists/examples/volumetric/: the p.23 example
with its own correction file; the configuration of every other example — chain,
workpiece axes, alternative model, splicing, interpolation — with random tables, since
the manual prints no data for them) and random models that cover linear and rotary
axes, the workpiece side, splicing (also mixed on one axis), the alternative model, IDk
offsets, tilted axis directions, and each kind of general table (N-D GRID, SCATTER,
PATH, PATH_XY). The expected numbers are the reference's; the tolerances are those of
tests/test_volcomp.py (1e-9 mm for the correction after two Newton steps, which the
reference iterates to 1e-13 mm; the forward model to 1e-9 mm).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from geo_server.listfile.loader import load_machine
from geo_server.listfile.schema import ListKind
from geo_server.listfile.syntax import parse_list
from geo_server.listfile.values import Reporter, read_values
from geo_server.paths import data_dir
from geo_server.volcomp import law
from geo_server.volcomp import reference as R
from geo_server.volcomp.evaluator import Evaluator
from geo_server.volcomp.model import VolModel, build_model
from geo_server.volcomp.names import ROTARY
from geo_server.volcomp.tables import ParamTable

EXAMPLES = data_dir("lists") / "examples" / "volumetric"
TOL = 1e-9  # mm
LENGTH = 120.0  # mm, the tool


#: grid points are drawn from these (mm or °): at least 50 mm apart, so a few µm between
#: neighbours is a slope a measured machine may have
_LATTICE = np.arange(-600.0, 601.0, 50.0)


def _points(rng: np.random.Generator, lattice: np.ndarray, m: int) -> np.ndarray:
    return np.sort(rng.choice(lattice, size=min(m, len(lattice)), replace=False))


def _grid(rng: np.random.Generator, rotary: bool, spliced: bool) -> np.ndarray:
    if spliced:
        inner = np.sort(rng.choice(np.arange(15.0, 350.0, 15.0), size=5, replace=False))
        return np.concatenate([[0.0], inner, [360.0]])
    m = int(rng.integers(1, 9))
    return _points(rng, np.arange(-200.0, 401.0, 40.0) if rotary else _LATTICE, m)


def _component(
    rng: np.random.Generator, name: str, axis: str, spliced: bool, big: float
) -> ParamTable:
    """A 1-D GRID table of `name` over its own axis (a few µm or µrad), or a constant."""
    scale = big * (3e-3 if name[1] in "XYZ" else 1e-5)
    if rng.random() < 0.2:
        return ParamTable(name, (), (), np.array(scale * rng.uniform(-1, 1)))
    g = _grid(rng, axis in ROTARY, spliced)
    v = scale * rng.uniform(-1, 1, size=len(g))
    if spliced:
        v[-1] = v[0]
    return ParamTable(name, (axis,), (g,), v, spliced=spliced)


def _general(rng: np.random.Generator, name: str, args: tuple[str, ...], mode: str) -> ParamTable:
    """A table over other or several arguments: an N-D GRID, or records for SCATTER,
    PATH, PATH_XY."""
    scale = 3e-3 if name[1] in "XYZ" else 1e-5
    if mode == "GRID":
        grid = tuple(_points(rng, _LATTICE, int(rng.integers(1, 5))) for _ in args)
        values = scale * rng.uniform(-1, 1, size=tuple(len(g) for g in grid))
        return ParamTable(name, args, grid, values)
    m = int(rng.integers(1, 7))
    lattice = np.arange(-500.0, 501.0, 100.0)
    pts = rng.choice(lattice, size=(m, len(args)))
    if mode == "SCATTER":
        pts = np.unique(pts, axis=0)
    else:  # a polygon that runs one way (no section doubling back on another: a tie)
        pts[:, 0] = _points(rng, lattice, m)
        m = len(pts)
    return ParamTable(
        name,
        args,
        (),
        np.array(np.nan),
        mode=mode,
        points=pts,
        point_values=scale * rng.uniform(-1, 1, size=len(pts)),
    )


def random_model(
    seed: int,
    chain: str,
    wp: int,
    alternative: bool = False,
    splicing: bool = False,
    interpolation: str = "GRID",
) -> VolModel:
    """Every component error of every axis (tables over its own axis or constants),
    position errors, tool point, IDk offsets, tilted directions and centres of rotary
    axes, and general tables of `interpolation` (GRID: also an N-D one). Errors of a few
    µm and µrad at random grid points: rougher than a measured machine, within the
    two Newton steps' bound at 1e-9 mm (docs/volumetric.md §2)."""
    rng = np.random.default_rng(seed)
    tabs: dict[str, ParamTable] = {}

    def put(t: ParamTable) -> None:
        tabs[t.name] = t

    def const(name: str, value: float) -> None:
        put(ParamTable(name, (), (), np.array(value)))

    for a in chain:
        rot = a in ROTARY
        for c in ("EX", "EY", "EZ", "EA", "EB", "EC"):
            # splicing on some tables of a rotary axis only: mixed splicing on one axis
            spl = splicing and rot and rng.random() < 0.6
            put(_component(rng, f"{c}{a}", a, spl, 1.0))
        for d in "XYZ":
            const(f"{d}0{a}", 2e-3 * rng.uniform(-1, 1))
        for d in "ABC":
            const(f"{d}0{a}", 1e-5 * rng.uniform(-1, 1))
        if rng.random() < 0.5:
            const(f"ID{a}", float(rng.uniform(-5, 5)))
        if rot:
            for d in "XYZ":
                const(f"P{d}{a}", float(rng.uniform(-100, 100)))
            if rng.random() < 0.5:  # a direction a little off the nominal one
                u = np.eye(3)["ABC".index(a)] + 0.05 * rng.uniform(-1, 1, size=3)
                for d, x in zip("XYZ", u, strict=True):
                    const(f"V{d}{a}", float(x))
    for d in "XYZ":
        const(f"P0{d}", float(rng.uniform(-20, 20)))
    const("N0Z", -1.0)
    const("N0X", 0.1 * rng.uniform(-1, 1))
    # general tables: a component of one axis over another axis, over two axes
    lin = [a for a in chain if a in "XYZ"]
    others = [a for a in chain if a != lin[0]]
    modes = ["GRID", "SCATTER", "PATH", "PATH_XY"] if interpolation == "MIXED" else [interpolation]
    for k, mode in enumerate(modes):
        other = others[k % len(others)]
        args = ("X", "Y") if mode == "PATH_XY" else (other, lin[-1] if other != lin[-1] else lin[0])
        if mode == "GRID" and k == 0:
            args = tuple(sorted(set(chain) & set(rng.permutation(list(chain))[:3]))) or args
        name = (
            f"{('EX', 'EY', 'EZ', 'EA', 'EB', 'EC')[int(rng.integers(6))]}{chain[k % len(chain)]}"
        )
        put(_general(rng, name, args, mode))
    if interpolation == "GRID":  # a second, 1-D table over another axis
        put(_general(rng, f"EZ{lin[0]}", (lin[1],), "GRID"))
    return build_model(chain, wp, tabs, alternative)


def positions(rng: np.random.Generator, chain: str, count: int) -> np.ndarray:
    q = rng.uniform(-480.0, 480.0, size=(count, len(chain)))
    for i, a in enumerate(chain):
        if a in ROTARY:
            q[:, i] = rng.uniform(-400.0, 720.0, size=count)
    return q


def assert_matches_reference(mdl: VolModel, seed: int, count: int = 25) -> None:
    """The compiled correction (one position, and the same law in a loop) and forward
    model against the reference."""
    ev = Evaluator(mdl)
    chain = mdl.chain
    q = positions(np.random.default_rng(seed), "".join(chain), count)
    tip = mdl.tool_point(LENGTH)
    batch = ev.correction(q, tip)
    offset = np.array([mdl.axes[a].offset for a in chain])
    fwd = ev.forward(q + offset, tip)
    ideal = ev.forward(q + offset, tip, errors=False)
    for i, row in enumerate(q):
        point = dict(zip(chain, row.tolist(), strict=True))
        ref = R.correction(mdl, point, LENGTH)
        want = [ref["X"], ref["Y"], ref["Z"]]
        one = ev.correction_one(row.tolist(), (float(tip[0]), float(tip[1]), float(tip[2])))
        assert one == pytest.approx(want, abs=TOL), (i, point)
        assert batch[i].tolist() == one  # the same compiled law
        assert fwd[i] == pytest.approx(R.forward(mdl, point, LENGTH), abs=TOL)
        assert ideal[i] == pytest.approx(R.forward(mdl, point, LENGTH, errors=False), abs=TOL)


# ---------------------------------------------------------------------- the examples


def _volc_lists() -> list[Path]:
    out = []
    for p in sorted(EXAMPLES.glob("*.lis")):
        text = p.read_text(encoding="utf-8")
        if "vol_comp[" in text or "lr_param" in text:
            continue  # a start-up or axis list
        out.append(p)
    return out


@pytest.mark.parametrize("path", _volc_lists(), ids=lambda p: p.name)
def test_example_configurations_match_the_reference(path: Path) -> None:
    """Each VOLC list of 004 — whole lists and the excerpts that print only some
    entries (the rest at their defaults: chain XYZ, tool side, GRID) — with random
    tables of every kind its interpolation mode allows."""
    values = read_values(parse_list(path), ListKind.VOLC, Reporter([]))

    def entry(name: str, default: object) -> object:
        v = values.get(name)
        return default if v is None else v

    chain = str(entry("chain", "XYZ")).strip().upper()
    interpolation = str(entry("interpolation", "GRID")).strip().upper()
    mdl = random_model(
        len(path.name),
        chain,
        int(entry("workpiece_axes", 0)),  # type: ignore[call-overload]
        bool(entry("alternative_model", False)),
        bool(entry("enable_splicing", False)),
        "SCATTER" if interpolation == "AUTO" else interpolation,
    )
    assert_matches_reference(mdl, seed=3)


def test_p23_example_with_its_file_matches_the_reference(tmp_path: Path) -> None:
    """004 p.23: C:\\vc\\volcomp1.lis and its correction file (EXX, EYY over X, Y, Z: a
    3-D GRID) on the default machine, at positions inside and beyond its grid."""
    lists = tmp_path / "lists"
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    shutil.copy(EXAMPLES / "004_p23_volcomp1.csv", lists / "volcomp1.csv")
    shutil.copy(EXAMPLES / "004_p23_volcomp1.lis", lists / "volcomp1.lis")
    with (lists / "hochlauf.lis").open("a", encoding="utf-8") as fh:
        fh.write("vol_comp[0].max_records 1000\nvol_comp[0].file_name volcomp1.lis\n")
    cfg = load_machine(lists / "hochlauf.lis")
    comp = cfg.volumetric[0]
    assert comp.model is not None and "EXX" in comp.model.tables
    assert comp.model.tables["EXX"].arguments == ("X", "Y", "Z")
    assert_matches_reference(comp.model, seed=4, count=40)


# ---------------------------------------------------------------------- random models


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    ("chain", "wp", "alternative", "splicing"),
    [
        ("YXZ", 0, False, False),
        ("XYZ", 2, False, False),
        ("CYXZ", 1, False, True),
        ("CYXZ", 1, True, True),
        ("BCXYZ", 2, False, False),
        ("BCXYZ", 2, True, True),
        ("XYZAC", 0, False, True),
        ("AXYZC", 1, True, False),
    ],
)
@pytest.mark.parametrize("interpolation", ["GRID", "MIXED"])
def test_random_models_match_the_reference(
    seed: int, chain: str, wp: int, alternative: bool, splicing: bool, interpolation: str
) -> None:
    mdl = random_model(100 + seed, chain, wp, alternative, splicing, interpolation)
    assert_matches_reference(mdl, seed)


def test_the_general_tables_are_each_evaluated() -> None:
    """A model of general tables alone (one per kind, on different components): each
    moves the correction, and the whole matches the reference."""
    rng = np.random.default_rng(9)
    tabs = {
        "EXX": _general(rng, "EXX", ("Y", "Z"), "GRID"),
        "EYY": _general(rng, "EYY", ("X", "Y"), "SCATTER"),
        "EZZ": _general(rng, "EZZ", ("X", "Y", "Z"), "PATH"),
        "EZX": _general(rng, "EZX", ("X", "Y", "Z"), "PATH_XY"),
    }
    mdl = build_model("YXZ", 0, tabs)
    _, ti = law.pack(mdl)
    assert ti[law.NGEN] == 4
    assert_matches_reference(mdl, seed=5, count=40)


def test_models_packed_side_by_side_are_read_at_their_bases() -> None:
    """The models of a machine's compensations live in one pair of arrays (`VolKernel`):
    the second is read at its offsets as it is alone."""
    a = random_model(1, "YXZ", 0, interpolation="MIXED")
    b = random_model(2, "CYXZ", 1, True, True, "GRID")
    fa, ia = law.pack(a)
    fb_, ib_ = law.pack(b)
    tf, ti = np.concatenate([fa, fb_]), np.concatenate([ia, ib_])
    q = np.array([123.0, 35.0, -120.0, -40.0])
    x, y, z = b.tool_point(LENGTH).tolist()
    out, alone = np.zeros(3), np.zeros(3)
    law.correction(tf, ti, len(fa), len(ia), q, x, y, z, out)
    law.correction(fb_, ib_, 0, 0, q, x, y, z, alone)
    assert out.tolist() == alone.tolist()
    ref = R.correction(b, dict(zip("CYXZ", q.tolist(), strict=True)), LENGTH)
    assert alone == pytest.approx([ref["X"], ref["Y"], ref["Z"]], abs=TOL)


@pytest.mark.parametrize(
    ("chain", "wp", "alternative"),
    [("YXZ", 0, False), ("CYXZ", 1, False), ("CYXZ", 1, True), ("XYZAC", 2, True)],
)
def test_position_errors_over_arguments_match_the_reference(
    chain: str, wp: int, alternative: bool
) -> None:
    """004 p.32: position errors "typically (but not necessarily) constant". Every
    position error of every axis also given as a table over arguments (GRID over one or
    two axes, SCATTER, PATH) on top of a random model's constants: the tilt of a linear
    axis' travel, the centre and the tilt of a rotary one, in the default and the
    alternative model (where they distort the axis itself, 004 p.16). The compiled law
    matches the reference, and each table moves the correction."""
    rng = np.random.default_rng(17)
    mdl = random_model(40, chain, wp, alternative, interpolation="GRID")
    tabs = dict(mdl.tables)
    modes = ["GRID", "SCATTER", "PATH"]
    names = [f"{d}0{a}" for a in chain for d in ("XYZ" if a in ROTARY else "") + "ABC"]
    for k, name in enumerate(names):
        args = (chain[(k + 1) % len(chain)],) if k % 2 else (chain[k % len(chain)], chain[-1])
        args = tuple(dict.fromkeys(args))
        t = _general(rng, f"E{name[0]}{name[2]}", args, modes[k % 3])
        tabs[name] = ParamTable(
            name, t.arguments, t.grid, t.values, mode=t.mode, points=t.points,
            point_values=t.point_values,
        )  # fmt: skip
    varying = build_model(chain, wp, tabs, alternative)
    assert_matches_reference(varying, seed=3, count=30)
    q = positions(np.random.default_rng(4), chain, 5)
    tip = mdl.tool_point(LENGTH)
    assert not np.allclose(Evaluator(varying).correction(q, tip), Evaluator(mdl).correction(q, tip))
