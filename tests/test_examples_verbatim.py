"""The manuals' list examples in `lists/examples/` are verbatim copies of the manuals.

Every example file starts with `# Source: <seed file> p.<N>` (000, PDF pages) or
`# Source: <seed file> §x.y` (001/002/003). Every other line, except the lines of a
`# completed: ...` / `# end completed` block (data filled in by hand where the manual
elides it), must occur in the manual text, compared with runs of whitespace collapsed
(the PDF text of 000 has lost its line breaks and column alignment). For 000 the line
must occur on the cited page(s).

The manuals are Beckhoff/ISG publications the repository does not ship. Point the
environment variable `GEO_SERVER_MANUALS` at a folder with their text (`000_*.txt` …
`004_*.txt`, `## Page N` markers as in PDF-to-text output) to run these tests; without it
they are skipped, and the skip says so.
"""

from __future__ import annotations

import os
import re
from functools import cache
from pathlib import Path

import pytest

from geo_server.paths import data_dir

EXAMPLES = data_dir("lists") / "examples"
_REPO = Path(__file__).resolve().parent.parent


def _manuals_dir() -> Path | None:
    folder = os.environ.get("GEO_SERVER_MANUALS", "")
    if folder and Path(folder).is_dir() and any(Path(folder).glob("000_*.txt")):
        return Path(folder)
    return None


SEEDS = _manuals_dir()
pytestmark = pytest.mark.skipif(
    SEEDS is None,
    reason="the manuals' text is not part of the repository: set GEO_SERVER_MANUALS to a "
    "folder with 000_*.txt … 004_*.txt to compare the examples with it",
)

ELISIONS = {"...", "…", ":", "#…", "etc."}
_WS = re.compile(r"\s+")


def norm(text: str) -> str:
    return _WS.sub(" ", text).strip()


@cache
def seed_text(name: str) -> str:
    assert SEEDS is not None
    return (SEEDS / name).read_text(encoding="utf-8")


@cache
def seed_pages(name: str) -> dict[int, str]:
    """Page number -> normalised text of that page (000/004 have `## Page N` markers)."""
    pages: dict[int, str] = {}
    cur, buf = None, []
    for line in seed_text(name).splitlines():
        m = re.fullmatch(r"## Page (\d+)\s*", line)
        if m:
            if cur is not None:
                pages[cur] = norm(" ".join(buf))
            cur, buf = int(m.group(1)), []
        else:
            buf.append(line)
    if cur is not None:
        pages[cur] = norm(" ".join(buf))
    return pages


def example_files() -> list[Path]:
    vol = EXAMPLES / "volumetric"
    return (
        sorted(EXAMPLES.glob("*.lis"))
        + sorted((EXAMPLES / "nc").glob("*.nc"))
        + sorted(vol.glob("*.lis"))
        + sorted(vol.glob("*.csv"))
    )


def split_example(path: Path) -> tuple[str, list[str], list[list[str]]]:
    """(source header, verbatim lines, completed blocks)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    header = lines[0]
    verbatim: list[str] = []
    blocks: list[list[str]] = []
    block: list[str] | None = None
    for line in lines[1:]:
        if line.startswith("# completed:"):
            assert block is None, f"{path.name}: nested completed block"
            block = []
            continue
        if line.strip() == "# end completed":
            assert block is not None, f"{path.name}: '# end completed' without start"
            blocks.append(block)
            block = None
            continue
        if block is not None:
            block.append(line)
        elif line.strip():
            verbatim.append(line)
    assert block is None, f"{path.name}: unterminated completed block"
    return header, verbatim, blocks


def source_of(path: Path, header: str) -> tuple[str, list[int]]:
    m = re.match(r"[#;] Source: (\S+\.txt)", header)
    assert m, f"{path.name}: first line must be '# Source: <manual file> ...'"
    pages: list[int] = []
    pm = re.search(r" p\.(\d+)(?:[–-](\d+))? ", header)
    if pm and m.group(1).startswith(("000_", "004_")):
        a = int(pm.group(1))
        b = int(pm.group(2) or a)
        pages = list(range(a, b + 1))
    return m.group(1), pages


def test_there_are_examples_from_every_manual():
    names = [p.name for p in example_files()]
    assert len(names) >= 40
    for prefix in ("000_", "001_", "002_", "003_", "004_"):
        assert any(n.startswith(prefix) for n in names), prefix


@pytest.mark.parametrize("path", example_files(), ids=lambda p: p.name)
def test_every_line_is_in_the_manual(path: Path):
    header, verbatim, _ = split_example(path)
    seed, pages = source_of(path, header)
    assert seed.split("_")[0] == path.name.split("_")[0], "file prefix names its manual"
    if pages:
        text = norm(" ".join(seed_pages(seed)[p] for p in pages))
        where = f"{seed} p.{pages}"
    else:
        text = norm(seed_text(seed))
        where = seed
    missing = [line for line in verbatim if norm(line) not in text]
    assert not missing, f"{path.name}: lines not found in {where}: {missing[:5]}"


@pytest.mark.parametrize("path", example_files(), ids=lambda p: p.name)
def test_completed_blocks_follow_an_elision_marker(path: Path):
    lines = path.read_text(encoding="utf-8").splitlines()
    for k, line in enumerate(lines):
        if line.startswith("# completed:"):
            assert lines[k - 1].strip() in ELISIONS, (
                f"{path.name}:{k + 1}: completion must follow the manual's elision marker"
            )


# Key lines (name and value as printed), checked one by one against the manual text:
# the file must contain the line, and the manual must contain the name followed by the
# value (whitespace-insensitive).
KEY_LINES = [
    ("000_p13_backlash_axis.lis", "getriebe[0].lose", "1000"),
    ("000_p13_backlash_axis.lis", "lr_param. n_backlash_cyc", "10"),
    ("000_p17_temperature_axis.lis", "lr_param.temp_comp_coefficient", "4000 [µm/m]"),
    ("000_p24_temperature_example.lis", "lr_param.temp_comp_n_cycles", "20"),
    ("000_p26_startup_hochlauf.lis", "achs_kw[2]", r"..\listen\achskw6.lis"),
    ("000_p35_crosscomp.lis", "kw.crosscomp.table[99].setpoint", "10000000"),
    ("000_p43_plane_fig13.lis", "kw.crosscomp2.table[6][7].correction", "324"),
    ("000_p43_plane_fig13.lis", "kw.crosscomp2.start_position_master2", "-160000"),
    ("000_p49_plane_max_points.lis", "kw.crosscomp2.table[ 20][1000].correction", "49"),
    ("000_p49_plane_full.lis", "kw.crosscomp2.table[ 0][ 22].correction", "-99"),
    ("000_p62_lsec_bilateral.lis", "kw.ssfk.table[1].setpoint", "-199306"),
    ("000_p62_lsec_bilateral.lis", "kw.ssfk.table[2].pos", "-102"),
    ("000_p62_lsec_bilateral.lis", "kw.ssfk.table[139].neg", "114"),
    ("000_p70_friction.lis", "frict_comp.table[1].out", "3722"),
    ("000_p91_crosstalk_mode1.lis", "kw.crosstalk.acceleration", "10000 ( mm/s^2)"),
    ("000_p91_crosstalk_mode1.lis", "Kw.crosstalk.position[0].correction_decelerate_dir_pos", "25"),
    ("000_p91_crosstalk_mode2.lis", "kw.crosstalk.position[2].ax_1", "2000 ( 0.1 um)"),
    ("000_p92_crosstalk_mode3.lis", "kw.crosstalk.acceleration_neg", "-1000 ( mm/s^2 )"),
    (
        "000_p98_prog_movement_requires.lis",
        "lr_param.prog_movement_requires_compensations",
        "LEAD | CROSS",
    ),
    ("001_s4.5.3_crosstalk_old.lis", "kw.crosstalk.table[1].acceleration", "10000"),
    ("001_s4.4.2_plane_full.lis", "kw.crosscomp2.table[200][100].correction", "49"),
    ("001_s4.2.2_lsec_bilateral.lis", "kopf.log_achs_name", "Y-ACHSE"),
    ("002_s3.3.11_lsec_bilateral.lis", "kopf.log_achs_nr", "2"),
    ("002_s3.2.15_plane.lis", "kw.crosscomp2.last_index_master2", "100"),
    ("002_s3.1.7_crosscomp.lis", "kw.crosscomp.n_cycles", "10"),
    ("003_s3.1.7_crosscomp.lis", "kw.crosscomp.table[1].setpoint", "11523"),
    ("003_s3.3.11_lsec_bilateral.lis", "kw.ssfk.table[138].setpoint", "334488"),
]


@pytest.mark.parametrize(
    ("fname", "name", "value"), KEY_LINES, ids=[f"{f}:{n}" for f, n, _ in KEY_LINES]
)
def test_key_line(fname: str, name: str, value: str):
    path = EXAMPLES / fname
    _, verbatim, _ = split_example(path)
    want = norm(f"{name} {value}")
    in_file = [line for line in verbatim if norm(line) == want or norm(line).startswith(want + " ")]
    assert in_file, f"{fname} has no line '{name} {value}'"
    seed, _ = source_of(path, path.read_text(encoding="utf-8").splitlines()[0])
    assert want in norm(seed_text(seed)), f"{seed} does not print '{name} {value}'"
