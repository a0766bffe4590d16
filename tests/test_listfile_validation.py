"""Every validation check reports its documented error ID, file, line and entry, and
switches off only that compensation of that axis (docs/design.md §4, table in checks.py).

The scratch machine: axes 1, 2, 3 linear, 4 a spindle, 5 a rotary modulo axis. The
compensation list under test belongs to axis 3 (or the axis the case names); it always
also holds a second, valid compensation that must stay valid.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from geo_server.listfile import CHECKS, checks_markdown, load_machine
from geo_server.listfile.checks import EMU_TEMP_ERROR, EMU_VOLC_ERROR
from geo_server.model import CompKind, Diagnostic, MachineConfig

AXES = {
    1: "kopf.achs_nr 1\n",
    2: "kopf.achs_nr 2\n",
    3: "kopf.achs_nr 3\n",
    4: "kopf.achs_nr 4\nkenngr.achs_typ 4\n",
    5: "kopf.achs_nr 5\nkenngr.achs_typ 2\nkenngr.modulo_calc 1\nkenngr.modulo_wert 3600000\n",
}
GOOD_CROSS = """kw.crosscomp.last_index 1
kw.crosscomp.master_ax_nr 1
kw.crosscomp.table[0].setpoint 0
kw.crosscomp.table[0].correction 1
kw.crosscomp.table[1].setpoint 100
kw.crosscomp.table[1].correction 2
"""
GOOD_LSEC = """kw.ssfk.interval 1000
kw.ssfk.kw_nr_max 2
kw.ssfk.table[0].pos 1
kw.ssfk.table[1].pos 2
"""


def build(
    tmp: Path, comps: dict[int, str], axes: dict[int, str] | None = None, log_nr: bool = True
) -> MachineConfig:
    """Write the scratch machine with `comps` (axis -> list text) and load it."""
    axes = {**AXES, **(axes or {})}
    lines = [f"zahl_mds {len(axes)}"]
    for i, (nr, text) in enumerate(sorted(axes.items())):
        (tmp / f"md{nr}.lis").write_text(text)
        lines += [f"achs_mds[{i}] md{nr}.lis", f"achs_mds_log_ax_nr[{i}] {nr}"]
    lines.append(f"zahl_kw {len(comps)}")
    for i, (nr, text) in enumerate(sorted(comps.items())):
        (tmp / f"kw{nr}.lis").write_text(text)
        lines.append(f"achs_kw[{i}] kw{nr}.lis")
        if log_nr:
            lines.append(f"achs_kw_log_ax_nr[{i}] {nr}")
    (tmp / "hochlauf.lis").write_text("\n".join(lines) + "\n")
    return load_machine(tmp / "hochlauf.lis")


def with_id(cfg: MachineConfig, error_id: int) -> Diagnostic:
    found = [d for d in cfg.diagnostics if d.error_id == error_id]
    assert found, [str(d) for d in cfg.diagnostics]
    return found[0]


def L(*lines: str) -> str:
    """List text from lines."""
    return "".join(line + "\n" for line in lines)


ATTR = {
    CompKind.CROSS: "cross",
    CompKind.PLANE: "plane",
    CompKind.LEAD: "lsec",
    CompKind.FRICT: "frict",
    CompKind.CROSSTALK: "crosstalk",
}

# (case id, axis, section text, error ID, line, entry, compensation).  Lines count from
# the two header lines `kopf.achs_nr N` / `kopf.log_achs_name T`: the section starts at 3.
CASES = [
    # ---- cross compensation
    (
        "cross.master",
        3,
        L(
            "kw.crosscomp.last_index 0",
            "kw.crosscomp.table[0].setpoint 5",
            "kw.crosscomp.table[0].correction 1",
        ),
        70244,
        3,
        "kw.crosscomp.master_ax_nr",
        CompKind.CROSS,
    ),
    (
        "cross.axis-unknown",
        3,
        L(
            "kw.crosscomp.master_ax_nr 9",
            "kw.crosscomp.last_index 0",
            "kw.crosscomp.table[0].setpoint 5",
            "kw.crosscomp.table[0].correction 1",
        ),
        70245,
        3,
        "kw.crosscomp.master_ax_nr",
        CompKind.CROSS,
    ),
    (
        "cross.axis-self",
        3,
        L(
            "kw.crosscomp.last_index 0",
            "kw.crosscomp.master_ax_nr 3",
            "kw.crosscomp.table[0].setpoint 5",
            "kw.crosscomp.table[0].correction 1",
        ),
        70245,
        4,
        "kw.crosscomp.master_ax_nr",
        CompKind.CROSS,
    ),
    (
        "cross.last_index",
        3,
        L(
            "kw.crosscomp.master_ax_nr 1",
            "kw.crosscomp.table[0].setpoint 5",
            "kw.crosscomp.table[0].correction 1",
        ),
        70246,
        3,
        "kw.crosscomp.last_index",
        CompKind.CROSS,
    ),
    (
        "cross.size",
        3,
        L(
            "kw.crosscomp.max_points 2",
            "kw.crosscomp.master_ax_nr 1",
            "kw.crosscomp.last_index 2",
        ),
        70247,
        5,
        "kw.crosscomp.last_index",
        CompKind.CROSS,
    ),
    (
        "cross.index",
        3,
        L(
            "kw.crosscomp.master_ax_nr 1",
            "kw.crosscomp.last_index 0",
            "kw.crosscomp.table[0].setpoint 5",
            "kw.crosscomp.table[0].correction 1",
            "kw.crosscomp.table[1].setpoint 9",
        ),
        70248,
        7,
        "kw.crosscomp.table[1].setpoint",
        CompKind.CROSS,
    ),
    (
        "cross.order",
        3,
        L(
            "kw.crosscomp.master_ax_nr 1",
            "kw.crosscomp.last_index 1",
            "kw.crosscomp.table[0].setpoint 10",
            "kw.crosscomp.table[0].correction 1",
            "kw.crosscomp.table[1].setpoint 10",
            "kw.crosscomp.table[1].correction 1",
        ),
        70249,
        7,
        "kw.crosscomp.table[1].setpoint",
        CompKind.CROSS,
    ),
    (
        "cross.range",
        3,
        L(
            "kw.crosscomp.master_ax_nr 1",
            "kw.crosscomp.n_cycles 21",
            "kw.crosscomp.last_index 0",
            "kw.crosscomp.table[0].setpoint 10",
            "kw.crosscomp.table[0].correction 1",
        ),
        70250,
        4,
        "kw.crosscomp.n_cycles",
        CompKind.CROSS,
    ),
    (
        "cross.incomplete",
        3,
        L(
            "kw.crosscomp.master_ax_nr 1",
            "kw.crosscomp.last_index 1",
            "kw.crosscomp.table[0].setpoint 10",
            "kw.crosscomp.table[0].correction 1",
            "kw.crosscomp.table[1].setpoint 20",
        ),
        70432,
        3,
        "kw.crosscomp.table[1].correction",
        CompKind.CROSS,
    ),
    # ---- plane compensation
    (
        "plane.missing",
        3,
        L(
            "kw.crosscomp2.last_index_master1 0",
            "kw.crosscomp2.last_index_master2 0",
            "kw.crosscomp2.master1_ax_nr 1",
            "kw.crosscomp2.master2_ax_nr 2",
        ),
        70182,
        3,
        "kw.crosscomp2.interval",
        CompKind.PLANE,
    ),
    (
        "plane.axis",
        3,
        L(
            "kw.crosscomp2.interval 10",
            "kw.crosscomp2.last_index_master1 0",
            "kw.crosscomp2.last_index_master2 0",
            "kw.crosscomp2.master1_ax_nr 1",
            "kw.crosscomp2.master2_ax_nr 1",
        ),
        70183,
        7,
        "kw.crosscomp2.master2_ax_nr",
        CompKind.PLANE,
    ),
    (
        "plane.size",
        3,
        L(
            "kw.crosscomp2.max_points 5",
            "kw.crosscomp2.interval 10",
            "kw.crosscomp2.last_index_master1 2",
            "kw.crosscomp2.last_index_master2 1",
            "kw.crosscomp2.master1_ax_nr 1",
            "kw.crosscomp2.master2_ax_nr 2",
        ),
        70184,
        6,
        "kw.crosscomp2.last_index_master2",
        CompKind.PLANE,
    ),
    (
        # 000 p.44: without max_points each last index is at most 100, although 201 x 21
        # points fit the default 10201
        "plane.size",
        3,
        L(
            "kw.crosscomp2.interval 10",
            "kw.crosscomp2.last_index_master1 200",
            "kw.crosscomp2.last_index_master2 20",
            "kw.crosscomp2.master1_ax_nr 1",
            "kw.crosscomp2.master2_ax_nr 2",
        ),
        70184,
        4,
        "kw.crosscomp2.last_index_master1",
        CompKind.PLANE,
    ),
    (
        "plane.index",
        3,
        L(
            "kw.crosscomp2.interval 10",
            "kw.crosscomp2.last_index_master1 1",
            "kw.crosscomp2.last_index_master2 1",
            "kw.crosscomp2.master1_ax_nr 1",
            "kw.crosscomp2.master2_ax_nr 2",
            "kw.crosscomp2.table[2][0].correction 4",
        ),
        70184,
        8,
        "kw.crosscomp2.table[2][0].correction",
        CompKind.PLANE,
    ),
    (
        "plane.range",
        3,
        L(
            "kw.crosscomp2.grid HEXAGONAL",
            "kw.crosscomp2.interval 10",
            "kw.crosscomp2.last_index_master1 0",
            "kw.crosscomp2.last_index_master2 0",
            "kw.crosscomp2.master1_ax_nr 1",
            "kw.crosscomp2.master2_ax_nr 2",
        ),
        70185,
        3,
        "kw.crosscomp2.grid",
        CompKind.PLANE,
    ),
    # ---- LSEC
    (
        "lead.missing",
        3,
        L(
            "kw.ssfk.interval 10",
            "kw.ssfk.table[0].pos 1",
        ),
        110217,
        3,
        "kw.ssfk.kw_nr_max",
        CompKind.LEAD,
    ),
    (
        "lead.size",
        3,
        L(
            "kw.ssfk.max_points 3",
            "kw.ssfk.interval 10",
            "kw.ssfk.kw_nr_max 4",
        ),
        110218,
        5,
        "kw.ssfk.kw_nr_max",
        CompKind.LEAD,
    ),
    (
        # 000 p.57: kw_nr_max "must be smaller than" max_points: equal is refused too
        "lead.size",
        3,
        L(
            "kw.ssfk.max_points 4",
            "kw.ssfk.interval 10",
            "kw.ssfk.kw_nr_max 4",
        ),
        110218,
        5,
        "kw.ssfk.kw_nr_max",
        CompKind.LEAD,
    ),
    (
        "lead.bilateral",
        3,
        L(
            "kw.ssfk.interval 10",
            "kw.ssfk.kw_nr_max 2",
            "kw.ssfk.bilateral 1",
            "kw.ssfk.table[0].pos 1",
            "kw.ssfk.table[1].pos 2",
            "kw.ssfk.table[0].neg 3",
        ),
        110392,
        3,
        "kw.ssfk.table[1].neg",
        CompKind.LEAD,
    ),
    (
        "lead.index",
        3,
        L(
            "kw.ssfk.interval 10",
            "kw.ssfk.kw_nr_max 2",
            "kw.ssfk.table[0].pos 1",
            "kw.ssfk.table[1].pos 2",
            "kw.ssfk.table[2].pos 3",
        ),
        110474,
        7,
        "kw.ssfk.table[2].pos",
        CompKind.LEAD,
    ),
    (
        "lead.order",
        3,
        L(
            "kw.ssfk.kw_nr_max 2",
            "kw.ssfk.table[0].setpoint 50",
            "kw.ssfk.table[1].setpoint 40",
            "kw.ssfk.table[0].pos 1",
            "kw.ssfk.table[1].pos 2",
        ),
        110476,
        5,
        "kw.ssfk.table[1].setpoint",
        CompKind.LEAD,
    ),
    (
        "lead.setpoint",
        3,
        L(
            "kw.ssfk.interval 0",
            "kw.ssfk.kw_nr_max 2",
            "kw.ssfk.table[0].setpoint 50",
            "kw.ssfk.table[0].pos 1",
            "kw.ssfk.table[1].pos 2",
        ),
        110477,
        3,
        "kw.ssfk.table[1].setpoint",
        CompKind.LEAD,
    ),
    (
        "lead.range",
        3,
        L(
            "kw.ssfk.interval -5",
            "kw.ssfk.kw_nr_max 1",
            "kw.ssfk.table[0].pos 1",
        ),
        110478,
        3,
        "kw.ssfk.interval",
        CompKind.LEAD,
    ),
    (
        "lead.modulo-axis",
        3,
        L(
            "kw.ssfk.interval 10",
            "kw.ssfk.kw_nr_max 1",
            "kw.ssfk.modulo 1",
            "kw.ssfk.table[0].pos 1",
        ),
        110479,
        5,
        "kw.ssfk.modulo",
        CompKind.LEAD,
    ),
    (
        "lead.modulo-period",
        5,
        L(
            "kw.ssfk.modulo 1",
            "kw.ssfk.interval 900000",
            "kw.ssfk.kw_nr_max 4",
            "kw.ssfk.table[0].pos 0",
            "kw.ssfk.table[1].pos 1",
            "kw.ssfk.table[2].pos 2",
            "kw.ssfk.table[3].pos 0",
        ),
        110479,
        3,
        "kw.ssfk.modulo",
        CompKind.LEAD,
    ),
    (
        "lead.axis_type",
        4,
        L(
            "kw.ssfk.interval 10",
            "kw.ssfk.kw_nr_max 1",
            "kw.ssfk.table[0].pos 1",
        ),
        110480,
        4,
        "kw.ssfk.kw_nr_max",
        CompKind.LEAD,
    ),
    (
        "lead.pos",
        3,
        L(
            "kw.ssfk.interval 10",
            "kw.ssfk.kw_nr_max 2",
            "kw.ssfk.table[0].pos 1",
        ),
        110590,
        3,
        "kw.ssfk.table[1].pos",
        CompKind.LEAD,
    ),
    # ---- friction
    (
        "frict.velocity-order",
        3,
        L(
            "frict_comp.mode 3",
            "frict_comp.table_entries 3",
            "frict_comp.table[0].in 0",
            "frict_comp.table[0].out 0",
            "frict_comp.table[1].in 316",
            "frict_comp.table[1].out 3722",
            "frict_comp.table[2].in 200",
            "frict_comp.table[2].out 3884",
        ),
        110591,
        9,
        "frict_comp.table[2].in",
        CompKind.FRICT,
    ),
    (
        "frict.velocity-negative",
        3,
        L(
            "frict_comp.mode 3",
            "frict_comp.table_entries 2",
            "frict_comp.table[0].in -5",
            "frict_comp.table[0].out 0",
            "frict_comp.table[1].in 316",
            "frict_comp.table[1].out 3722",
        ),
        110591,
        5,
        "frict_comp.table[0].in",
        CompKind.FRICT,
    ),
    (
        "frict.mode",
        3,
        L(
            "frict_comp.mode 2",
            "frict_comp.table_entries 1",
            "frict_comp.table[0].in 0",
            "frict_comp.table[0].out 0",
        ),
        110592,
        3,
        "frict_comp.mode",
        CompKind.FRICT,
    ),
    (
        "frict.no-values",
        3,
        L(
            "frict_comp.mode 3",
            "frict_comp.table_entries 0",
        ),
        110592,
        4,
        "frict_comp.table_entries",
        CompKind.FRICT,
    ),
    (
        "frict.too-many",
        3,
        L(
            "frict_comp.mode 3",
            "frict_comp.max_points 2",
            "frict_comp.table_entries 3",
        ),
        110592,
        5,
        "frict_comp.table_entries",
        CompKind.FRICT,
    ),
    # ---- crosstalk, new model
    (
        "crosstalk.master",
        3,
        L(
            "kw.crosstalk.mode 1",
            "kw.crosstalk.acceleration 10",
            "kw.crosstalk.deceleration -10",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
        ),
        70625,
        3,
        "kw.crosstalk.master_dyn_ax_nr",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.mode",
        3,
        L(
            "kw.crosstalk.mode 4",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 10",
            "kw.crosstalk.deceleration -10",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
        ),
        70626,
        3,
        "kw.crosstalk.mode",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.mixed",
        3,
        L(
            "kw.crosstalk.mode 1",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 10",
            "kw.crosstalk.deceleration -10",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
            "kw.crosstalk.table[0].acceleration 5",
        ),
        70626,
        3,
        "kw.crosstalk.mode",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.acceleration",
        3,
        L(
            "kw.crosstalk.mode 1",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 0",
            "kw.crosstalk.deceleration -10",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
        ),
        70627,
        5,
        "kw.crosstalk.acceleration",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.deceleration",
        3,
        L(
            "kw.crosstalk.mode 1",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 10",
            "kw.crosstalk.deceleration 5",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
        ),
        70629,
        6,
        "kw.crosstalk.deceleration",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.range",
        3,
        L(
            "kw.crosstalk.n_cycles 30",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 10",
            "kw.crosstalk.deceleration -10",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
        ),
        70631,
        3,
        "kw.crosstalk.n_cycles",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.points-max",
        3,
        L(
            "kw.crosstalk.max_points 16",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 10",
            "kw.crosstalk.deceleration -10",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
        ),
        70632,
        3,
        "kw.crosstalk.max_points",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.points-index",
        3,
        L(
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 10",
            "kw.crosstalk.deceleration -10",
            "kw.crosstalk.position[0].correction_accelerate_dir_pos 5",
            "kw.crosstalk.position[15].correction_accelerate_dir_pos 5",
        ),
        70632,
        3,
        "kw.crosstalk.position[15]",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.adapt1",
        3,
        L(
            "kw.crosstalk.mode 2",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.acceleration 1000",
            "kw.crosstalk.deceleration -1000",
            "kw.crosstalk.position[0].ax_1 0",
            "kw.crosstalk.position[1].ax_1 1000",
        ),
        70657,
        3,
        "kw.crosstalk.master_pos1_ax_nr",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.adapt2",
        3,
        L(
            "kw.crosstalk.mode 3",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.master_pos1_ax_nr 2",
            "kw.crosstalk.master_pos2_ax_nr 8",
            "kw.crosstalk.acceleration 1000",
            "kw.crosstalk.deceleration -1000",
            "kw.crosstalk.position[0].ax_1 0",
            "kw.crosstalk.position[1].ax_1 1000",
            "kw.crosstalk.position[2].ax_2 1000",
        ),
        70658,
        6,
        "kw.crosstalk.master_pos2_ax_nr",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.records",
        3,
        L(
            "kw.crosstalk.mode 3",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.master_pos1_ax_nr 2",
            "kw.crosstalk.master_pos2_ax_nr 3",
            "kw.crosstalk.acceleration 1000",
            "kw.crosstalk.deceleration -1000",
            "kw.crosstalk.position[0].ax_1 0",
            "kw.crosstalk.position[1].ax_1 1000",
        ),
        70659,
        3,
        "kw.crosstalk.position[]",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.geometry",
        3,
        L(
            "kw.crosstalk.mode 2",
            "kw.crosstalk.master_dyn_ax_nr 1",
            "kw.crosstalk.master_pos1_ax_nr 2",
            "kw.crosstalk.acceleration 1000",
            "kw.crosstalk.deceleration -1000",
            "kw.crosstalk.position[0].ax_1 2000",
            "kw.crosstalk.position[1].ax_1 1000",
        ),
        70660,
        3,
        "kw.crosstalk.position[].ax_1",
        CompKind.CROSSTALK,
    ),
    # ---- crosstalk, old model
    (
        "crosstalk.old_table",
        3,
        L(
            "kw.crosstalk.last_index 5",
            "kw.crosstalk.master_ax_nr 1",
            "kw.crosstalk.table[0].acceleration -10000",
            "kw.crosstalk.table[0].correction -1000",
        ),
        70630,
        3,
        "kw.crosstalk.last_index",
        CompKind.CROSSTALK,
    ),
    (
        "crosstalk.old_order",
        3,
        L(
            "kw.crosstalk.last_index 1",
            "kw.crosstalk.master_ax_nr 1",
            "kw.crosstalk.table[0].acceleration 100",
            "kw.crosstalk.table[0].correction 1",
            "kw.crosstalk.table[1].acceleration -100",
            "kw.crosstalk.table[1].correction 1",
        ),
        70630,
        7,
        "kw.crosstalk.table[1].acceleration",
        CompKind.CROSSTALK,
    ),
]


@pytest.mark.parametrize(
    ("axis", "section", "error_id", "line", "entry", "kind"),
    [c[1:] for c in CASES],
    ids=[c[0] for c in CASES],
)
def test_check_reports_id_and_deactivates_only_that_compensation(
    tmp_path: Path, axis: int, section: str, error_id: int, line: int, entry: str, kind: CompKind
) -> None:
    other = GOOD_CROSS if kind == CompKind.LEAD else GOOD_LSEC
    if axis == 4:
        other = GOOD_CROSS  # a spindle: LSEC would itself be wrong there
    text = f"kopf.achs_nr {axis}\nkopf.log_achs_name T\n{section}{other}"
    cfg = build(tmp_path, {axis: text})
    d = with_id(cfg, error_id)
    assert (Path(d.file).name, d.line, d.entry) == (f"kw{axis}.lis", line, entry)
    assert (d.axis, d.deactivated) == (axis, kind)
    assert {x.deactivated for x in cfg.deactivated} == {kind}
    comp = cfg.axes[axis].comp
    assert getattr(comp, ATTR[kind]).valid is False
    other_attr = "cross" if other is GOOD_CROSS else "lsec"
    assert getattr(comp, other_attr).valid is True


def test_all_manual_ids_are_used() -> None:
    """Every ID that the manual lists for a compensation has a check (000 §2–§4, 002)."""
    used = {c.error_id for c in CHECKS}
    listed = {110392, 110217, 110218, 110474, 110476, 110477, 110478, 110479, 110480, 110590}
    listed |= {70242, 70244, 70245, 70246, 70247, 70248, 70249, 70250, 70432}
    listed |= {70182, 70183, 70184, 70185, 110591, 110592}
    listed |= {70622, 70625, 70626, 70627, 70629, 70630, 70631, 70632, 70657, 70658, 70659, 70660}
    assert listed <= used
    assert used - listed == {0, EMU_TEMP_ERROR, EMU_VOLC_ERROR}  # 004 lists no IDs


@pytest.mark.parametrize(
    ("axis_text", "line", "entry", "attr", "off"),
    [
        ("lr_param.anwahl_losekomp 3\n", 2, "lr_param.anwahl_losekomp", "anwahl_losekomp", 0),
        (
            "lr_param.anwahl_losekomp 1\ngetriebe[0].lose 40000\n",
            3,
            "getriebe[0].lose",
            "anwahl_losekomp",
            0,
        ),
        (
            "lr_param.anwahl_losekomp 1\nlr_param.n_backlash_cyc 21\n",
            3,
            "lr_param.n_backlash_cyc",
            "anwahl_losekomp",
            0,
        ),
    ],
)
def test_backlash_range_110392(
    tmp_path: Path, axis_text: str, line: int, entry: str, attr: str, off: int
) -> None:
    axes = {2: "kopf.achs_nr 2\n" + axis_text + "lr_param.temp_comp 1\n"}
    cfg = build(tmp_path, {}, axes)
    d = with_id(cfg, 110392)
    assert (Path(d.file).name, d.line, d.entry, d.axis) == ("md2.lis", line, entry, 2)
    assert d.deactivated == CompKind.BACKLASH
    p = cfg.axes[2].params
    assert getattr(p, attr) == off
    assert p.temp_comp is True  # temperature untouched
    assert [x.axis for x in cfg.deactivated] == [2]


@pytest.mark.parametrize(
    ("axis_text", "line", "entry"),
    [
        ("lr_param.temp_comp_coefficient 20000\n", 3, "lr_param.temp_comp_coefficient"),
        ("lr_param.temp_comp_coefficient -10000.5\n", 3, "lr_param.temp_comp_coefficient"),
        ("lr_param.temp_comp_n_cycles 21\n", 3, "lr_param.temp_comp_n_cycles"),
        ("lr_param.temp_comp_position_0 2147483648\n", 3, "lr_param.temp_comp_position_0"),
    ],
)
def test_temperature_range_emulator_id(
    tmp_path: Path, axis_text: str, line: int, entry: str
) -> None:
    axes = {
        2: "kopf.achs_nr 2\nlr_param.temp_comp 1\n" + axis_text + "lr_param.anwahl_losekomp 1\n"
    }
    cfg = build(tmp_path, {}, axes)
    d = with_id(cfg, EMU_TEMP_ERROR)
    assert (Path(d.file).name, d.line, d.entry, d.deactivated) == (
        "md2.lis",
        line,
        entry,
        CompKind.TEMP,
    )
    p = cfg.axes[2].params
    assert p.temp_comp is False and p.anwahl_losekomp == 1


@pytest.mark.parametrize(
    "text",
    [
        "lr_param.temp_comp_n_cycles 20",
        "lr_param.temp_comp_n_cycles 0",
        "lr_param.n_backlash_cyc 20",
        "lr_param.temp_comp_coefficient -10000",
    ],
)
def test_inclusive_bounds_accepted(tmp_path: Path, text: str) -> None:
    cfg = build(tmp_path, {}, {2: f"kopf.achs_nr 2\n{text}\n"})
    assert cfg.diagnostics == []


@pytest.mark.parametrize(
    ("selection", "error_id", "kind"),
    [
        ("lr_param.crosscomp", 70242, CompKind.CROSS),
        ("lr_param.crosscomp2", 70182, CompKind.PLANE),
        ("lr_param.ssfk", 110217, CompKind.LEAD),
        ("lr_param.frict_comp", 110592, CompKind.FRICT),
        ("lr_param.crosstalk", 70622, CompKind.CROSSTALK),
    ],
)
def test_selected_without_table(
    tmp_path: Path, selection: str, error_id: int, kind: CompKind
) -> None:
    cfg = build(tmp_path, {}, {3: f"kopf.achs_nr 3\nkopf.log_achs_name Z\n{selection} 1\n"})
    (d,) = cfg.diagnostics
    assert (Path(d.file).name, d.line, d.entry, d.error_id) == ("md3.lis", 3, selection, error_id)
    assert (d.axis, d.deactivated) == (3, kind)


def test_list_for_an_axis_not_in_the_machine(tmp_path: Path) -> None:
    text = "kopf.achs_nr 9\n" + GOOD_CROSS + GOOD_LSEC
    cfg = build(tmp_path, {9: text}, log_nr=False)
    got = sorted((d.error_id, d.line, d.entry, d.axis) for d in cfg.diagnostics)
    assert got == [(70245, 1, "kopf.achs_nr", 9), (110217, 1, "kopf.achs_nr", 9)]
    assert all(a.comp is None for a in cfg.axes.values())


def test_header_disagrees_with_startup(tmp_path: Path) -> None:
    cfg = build(tmp_path, {3: "kopf.achs_nr 2\n" + GOOD_LSEC})
    d = with_id(cfg, 110217)
    assert (d.line, d.entry, d.deactivated) == (1, "kopf.achs_nr", CompKind.LEAD)
    assert cfg.axes[3].comp is None


def test_unknown_entry_warns_and_is_ignored(tmp_path: Path) -> None:
    cfg = build(tmp_path, {3: "kopf.achs_nr 3\nkw.ssfk.foo 1\n" + GOOD_LSEC})
    (d,) = cfg.diagnostics
    assert (d.severity, Path(d.file).name, d.line, d.entry, d.error_id) == (
        "warning",
        "kw3.lis",
        2,
        "kw.ssfk.foo",
        0,
    )
    assert d.deactivated is None and cfg.axes[3].comp.lsec.valid


@pytest.mark.parametrize(
    ("axis_text", "entry", "attr", "default"),
    [
        (
            "lr_param.temp_comp_position_0 abc\n",
            "lr_param.temp_comp_position_0",
            "temp_comp_position_0",
            0,
        ),
        ("lr_param.ssfk 2\n", "lr_param.ssfk", "ssfk", False),
        ("kenngr.achs_typ 3\n", "kenngr.achs_typ", "kind", "T"),
        ("sim.homed yes\n", "sim.homed", "homed", False),
    ],
)
def test_defective_value_warns_and_uses_default(
    tmp_path: Path, axis_text: str, entry: str, attr: str, default: object
) -> None:
    cfg = build(tmp_path, {}, {2: "kopf.achs_nr 2\n" + axis_text})
    (d,) = cfg.diagnostics
    assert (d.severity, Path(d.file).name, d.line, d.entry, d.deactivated) == (
        "warning",
        "md2.lis",
        2,
        entry,
        None,
    )
    assert getattr(cfg.axes[2].params, attr) == default


def test_defective_table_value_warns(tmp_path: Path) -> None:
    cfg = build(tmp_path, {3: "kopf.achs_nr 3\n" + GOOD_LSEC + "kw.ssfk.table[1].pos abc\n"})
    d = cfg.diagnostics[0]
    assert (d.line, d.entry, d.error_id) == (6, "kw.ssfk.table[1].pos", 0)


def test_friction_position_delay_only_warns(tmp_path: Path) -> None:
    text = L(
        "kopf.achs_nr 3",
        "frict_comp.mode 3",
        "frict_comp.table_entries 1",
        "frict_comp.position_delay 30",
        "frict_comp.table[0].in 0",
        "frict_comp.table[0].out 5",
    )
    cfg = build(tmp_path, {3: text})
    (d,) = cfg.diagnostics
    assert (d.line, d.entry, d.deactivated) == (4, "frict_comp.position_delay", None)
    assert cfg.axes[3].comp.frict.valid


def test_two_compensations_fail_independently_on_two_axes(tmp_path: Path) -> None:
    bad_cross = GOOD_CROSS.replace("master_ax_nr 1", "master_ax_nr 7")
    cfg = build(
        tmp_path,
        {
            2: "kopf.achs_nr 2\n" + bad_cross + GOOD_LSEC,
            3: "kopf.achs_nr 3\n" + GOOD_CROSS + GOOD_LSEC,
        },
    )
    assert [(d.axis, d.deactivated) for d in cfg.deactivated] == [(2, CompKind.CROSS)]
    assert not cfg.axes[2].comp.cross.valid and cfg.axes[2].comp.lsec.valid
    assert cfg.axes[3].comp.cross.valid and cfg.axes[3].comp.lsec.valid


def test_docs_table_is_generated_from_checks() -> None:
    doc = Path(__file__).parent.parent / "docs" / "list_checks.md"
    assert doc.read_text(encoding="utf-8") == checks_markdown()
    for c in CHECKS:
        assert f"`{c.key}`" in doc.read_text(encoding="utf-8")


def test_duplicate_entry_warns_and_the_last_one_counts(tmp_path: Path) -> None:
    text = "kopf.achs_nr 2\nlr_param.temp_comp_offset_0 10\nlr_param.temp_comp_offset_0 25\n"
    cfg = build(tmp_path, {}, {2: text})
    (d,) = cfg.diagnostics
    assert (d.severity, Path(d.file).name, d.line, d.entry) == (
        "warning",
        "md2.lis",
        3,
        "lr_param.temp_comp_offset_0",
    )
    assert "line 2" in d.message
    assert cfg.axes[2].params.temp_comp_offset_0 == 25


def _startup(tmp: Path, mds: list[tuple[str, str, int | None]]) -> Path:
    """A start-up list naming only axis lists: (file, text, achs_mds_log_ax_nr or None)."""
    lines = [f"zahl_mds {len(mds)}"]
    for i, (name, text, nr) in enumerate(mds):
        (tmp / name).write_text(text)
        lines.append(f"achs_mds[{i}] {name}")
        if nr is not None:
            lines.append(f"achs_mds_log_ax_nr[{i}] {nr}")
    (tmp / "hochlauf.lis").write_text("\n".join(lines) + "\n")
    return tmp / "hochlauf.lis"


def test_axis_list_without_number_is_skipped_at_the_startup_line(tmp_path: Path) -> None:
    path = _startup(
        tmp_path, [("a.lis", "kopf.achs_nr 1\n", None), ("b.lis", "kopf.log_achs_name B\n", None)]
    )
    cfg = load_machine(path)
    assert sorted(cfg.axes) == [1]
    (d,) = cfg.diagnostics
    # reported where the user fixes it: line 3 of the start-up list, `achs_mds[1] b.lis`
    assert (d.severity, Path(d.file).name, d.line, d.entry) == (
        "error",
        "hochlauf.lis",
        3,
        "achs_mds",
    )
    assert "b.lis" in d.message and "skipped" in d.message


def test_same_axis_twice_is_skipped_at_its_number(tmp_path: Path) -> None:
    path = _startup(
        tmp_path, [("a.lis", "kopf.achs_nr 1\n", None), ("b.lis", "# b\nkopf.achs_nr 1\n", None)]
    )
    cfg = load_machine(path)
    (d,) = cfg.diagnostics
    assert (d.severity, Path(d.file).name, d.line, d.entry) == ("error", "b.lis", 2, "kopf.achs_nr")
    assert "axis 1 defined twice" in d.message


def test_axis_number_mismatch_warns_and_the_startup_list_wins(tmp_path: Path) -> None:
    path = _startup(tmp_path, [("a.lis", "kopf.achs_nr 7\n", 2)])
    cfg = load_machine(path)
    assert sorted(cfg.axes) == [2]
    (d,) = cfg.diagnostics
    assert (d.severity, Path(d.file).name, d.line, d.entry) == (
        "warning",
        "a.lis",
        1,
        "kopf.achs_nr",
    )
