"""Every list example printed in the manuals parses, and the loader reads the printed values.

`parse_list` must accept every example in `lists/examples/` as printed, extraction
artefacts included (`lr_param. n_backlash_cyc`, `Kw.crosstalk`, `table[ 0][ 1]`, `/* */`,
`( … )`, `[0.1µm]`, `End`/`Ende`/`# End`, elision lines `...`/`:`/`…`/`etc.`).

The spot checks load an example through `load_machine`: a small start-up list in a temp
folder names the example as the compensation value list of its axis (and minimal axis
lists that select the compensation), so the checks read the typed `MachineConfig` of
`geo_server/model.py` at the table indices printed in the manual.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from geo_server.listfile import load_machine, parse_list
from geo_server.listfile.schema import ListKind
from geo_server.listfile.values import Reporter, read_values
from geo_server.model import CROSSTALK_COLUMNS, CompKind, MachineConfig
from geo_server.paths import data_dir, default_startup_list

EXAMPLES = data_dir("lists") / "examples"
LIST_EXAMPLES = sorted(EXAMPLES.glob("*.lis"))


#: The only tokenizer or reader warnings an example may give: the manuals' own misprints,
#: accepted on purpose (`list.alias`).
EXPECTED_WARNINGS = {
    "000_p13_backlash_axis.lis": [(4, "lr_param.n_backlash_cyc")],  # `lr_param. n_backlash_cyc`
    "002_s3.3.11_lsec_bilateral.lis": [(2, "kopf.log_achs_nr")],  # for kopf.achs_nr
    "003_s3.3.11_lsec_bilateral.lis": [(2, "kopf.log_achs_nr")],
}


def _kind(name: str) -> ListKind | None:
    """The kind of list an example is; None for the syntax examples (made-up names)."""
    if "hochlauf" in name:
        return ListKind.STUP
    if any(k in name for k in ("axis", "temperature", "prog_movement", "backlash")):
        return ListKind.AXIS
    return None if "_s1." in name else ListKind.COMP


@pytest.mark.parametrize("path", LIST_EXAMPLES, ids=lambda p: p.name)
def test_every_example_parses(path: Path):
    """Every entry is read as its list kind knows it: no unknown entry, no defective
    value, no malformed line — only the manuals' misprints we accept on purpose."""
    parsed = parse_list(path)
    assert parsed.entries
    out: list = []
    kind = _kind(path.name)
    if kind is None:
        out = list(parsed.warnings)
    else:
        read_values(parsed, kind, Reporter(out))
    assert [(d.line, d.entry) for d in out] == EXPECTED_WARNINGS.get(path.name, [])


def _machine(
    tmp_path: Path,
    slave: int,
    *,
    comp: str | None = None,
    axis_lists: dict | None = None,
    select: tuple[str, ...] = (),
    axes: tuple[int, ...] = (1, 2, 3),
) -> MachineConfig:
    """Start-up list with linear axes `axes`; `comp` is the slave's compensation list,
    `axis_lists` maps an axis number to an example axis list used instead of a minimal one,
    `select` are the lr_param selections written into the slave's minimal axis list."""
    axis_lists = axis_lists or {}
    names = {1: "X", 2: "Y", 3: "Z", 4: "A", 5: "B", 6: "C"}
    stup = [f"zahl_mds {len(axes)}"]
    for k, nr in enumerate(axes):
        if nr in axis_lists:
            shutil.copy(EXAMPLES / axis_lists[nr], tmp_path / f"achsmd{nr}.lis")
        else:
            lines = [f"kopf.achs_nr {nr}", f"kopf.log_achs_name {names[nr]}", "kenngr.achs_typ 1"]
            if nr == slave:
                lines += [f"lr_param.{s} 1" for s in select]
            (tmp_path / f"achsmd{nr}.lis").write_text("\n".join(lines) + "\n", encoding="utf-8")
        stup += [f"achs_mds_log_ax_nr[{k}] {nr}", f"achs_mds[{k}] achsmd{nr}.lis"]
    if comp is not None:
        shutil.copy(EXAMPLES / comp, tmp_path / "achskw.lis")
        stup += ["zahl_kw 1", f"achs_kw_log_ax_nr[0] {slave}", "achs_kw[0] achskw.lis"]
    else:
        stup += ["zahl_kw 0"]
    (tmp_path / "hochlauf.lis").write_text("\n".join(stup) + "\n", encoding="utf-8")
    return load_machine(tmp_path / "hochlauf.lis")


def test_backlash_000_p13(tmp_path):
    cfg = _machine(tmp_path, 1, axis_lists={1: "000_p13_backlash_axis.lis"})
    p = cfg.axes[1].params
    # the manual prints "lr_param. n_backlash_cyc" with a blank after the dot
    assert (p.lose, p.anwahl_losekomp, p.n_backlash_cyc) == (1000, 1, 10)


def test_temperature_000_p24(tmp_path):
    cfg = _machine(tmp_path, 1, axis_lists={1: "000_p24_temperature_example.lis"})
    p = cfg.axes[1].params
    assert p.temp_comp
    assert (p.temp_comp_position_0, p.temp_comp_offset_0) == (100, 40)
    assert p.temp_comp_coefficient == 4000.0
    assert p.temp_comp_n_cycles == 20


def test_prog_movement_requires_000_p98(tmp_path):
    cfg = _machine(tmp_path, 1, axis_lists={1: "000_p98_prog_movement_requires.lis"})
    p = cfg.axes[1].params
    assert p.prog_movement_requires_compensations == CompKind.LEAD | CompKind.CROSS
    assert p.ssfk and p.crosscomp


def test_cross_000_p35(tmp_path):
    cfg = _machine(tmp_path, 3, comp="000_p35_crosscomp.lis", select=("crosscomp",))
    cross = cfg.axes[3].comp.cross
    assert cross.master_ax_nr == 1 and cross.n_cycles == 20
    assert len(cross.setpoint) == 100
    assert (cross.setpoint[0], cross.correction[0]) == (10735, 3)
    assert (cross.setpoint[1], cross.correction[1]) == (11523, 5)
    assert (cross.setpoint[99], cross.correction[99]) == (10_000_000, 1000)


def test_plane_000_p43_fig13(tmp_path):
    cfg = _machine(tmp_path, 3, comp="000_p43_plane_fig13.lis", select=("crosscomp2",))
    plane = cfg.axes[3].comp.plane
    assert plane.table.shape == (7, 8)  # j: master 2 (last 6), i: master 1 (last 7)
    assert plane.table[0, 0] == 0 and plane.table[6, 7] == 324
    assert (plane.start_position_master1, plane.start_position_master2) == (220000, -160000)
    assert plane.interval1 == plane.interval2 == 100000
    assert (plane.master1_ax_nr, plane.master2_ax_nr) == (1, 2)


def test_plane_000_p49_full(tmp_path):
    # masters 2 and 3, slave 1; no max_points, so each last index is at most 100 (000
    # p.44), and last_index_master2 is 200 (101 x 201 points would not fit the default
    # 10201 either): the printed values are read, and the plane is deactivated with the
    # size rule's ID
    cfg = _machine(tmp_path, 1, comp="000_p49_plane_full.lis", select=("crosscomp2",))
    plane = cfg.axes[1].comp.plane
    assert plane.table.shape == (201, 101)  # [j: master 2 ... 200][i: master 1 ... 100]
    assert plane.table[0, 22] == -99
    assert plane.table[200, 71] == 45
    assert plane.table[200, 100] == 49
    assert not plane.valid
    [d] = cfg.diagnostics
    assert (d.error_id, d.line, d.entry) == (70184, 9, "kw.crosscomp2.last_index_master2")
    assert d.deactivated == CompKind.PLANE
    assert d.message.startswith("last_index_master2 200 > 100: without max_points")


def test_plane_000_p49_max_points(tmp_path):
    # kw.crosscomp2.max_points 50000 reserves room for 1001 x 21 = 21021 points
    cfg = _machine(tmp_path, 1, comp="000_p49_plane_max_points.lis", select=("crosscomp2",))
    plane = cfg.axes[1].comp.plane
    assert plane.table.shape == (21, 1001)
    assert (plane.table[0, 0], plane.table[0, 1]) == (-3, -1)
    assert (plane.table[20, 999], plane.table[20, 1000]) == (58, 49)
    assert plane.table[10, 500] == 0  # elided ("etc."): unassigned points are 0
    # the excerpt prints no masters and no interval: deactivated for that, not for size
    missing = sorted(d.entry for d in cfg.diagnostics if d.error_id == 70182)
    assert missing == [
        "kw.crosscomp2.interval",
        "kw.crosscomp2.master1_ax_nr",
        "kw.crosscomp2.master2_ax_nr",
    ]
    assert len(cfg.diagnostics) == 3 and not plane.valid


def test_lsec_003_s3_3_11(tmp_path):
    # ISG COMP manual: the same bilateral non-equidistant table, `kopf.log_achs_nr` header
    cfg = _machine(tmp_path, 2, comp="003_s3.3.11_lsec_bilateral.lis", select=("ssfk",))
    lsec = cfg.axes[2].comp.lsec
    assert lsec.bilateral and len(lsec.setpoint) == 140
    assert (lsec.setpoint[0], lsec.setpoint[3]) == (-200000, -198001)
    assert (lsec.setpoint[138], lsec.setpoint[139]) == (334488, 335591)
    assert (lsec.pos[0], lsec.pos[1], lsec.pos[139]) == (0, 24, -55)
    assert (lsec.neg[1], lsec.neg[2], lsec.neg[139]) == (67, 80, 114)
    assert lsec.valid


def test_cross_003_s3_1_7(tmp_path):
    cfg = _machine(tmp_path, 3, comp="003_s3.1.7_crosscomp.lis", select=("crosscomp",))
    cross = cfg.axes[3].comp.cross
    assert (cross.master_ax_nr, cross.n_cycles) == (1, 10)
    assert len(cross.setpoint) == 100
    assert (cross.setpoint[1], cross.correction[1]) == (11523, 5)
    assert (cross.setpoint[3], cross.correction[3]) == (215369, 5)
    assert (cross.setpoint[99], cross.correction[99]) == (10_000_000, 1000)
    assert cross.valid


def test_plane_002_s3_2_15(tmp_path):
    cfg = _machine(tmp_path, 1, comp="002_s3.2.15_plane.lis", select=("crosscomp2",))
    plane = cfg.axes[1].comp.plane
    assert plane.table.shape == (101, 101)
    assert plane.table[0, 0] == -3 and plane.table[0, 7] == 53
    assert plane.table[100, 90] == 82 and plane.table[100, 100] == 49
    assert plane.table[50, 50] == 0  # unassigned points are 0
    assert plane.valid


def test_lsec_000_p62(tmp_path):
    cfg = _machine(tmp_path, 2, comp="000_p62_lsec_bilateral.lis", select=("ssfk",))
    lsec = cfg.axes[2].comp.lsec
    assert lsec.bilateral and len(lsec.setpoint) == 140
    assert lsec.setpoint[0] == -200000 and lsec.setpoint[1] == -199306
    assert lsec.setpoint[139] == 335591
    assert (lsec.pos[1], lsec.pos[2], lsec.pos[139]) == (24, -102, -55)
    assert (lsec.neg[1], lsec.neg[2], lsec.neg[139]) == (67, 80, 114)
    assert np.all(np.diff(lsec.setpoint) > 0)
    assert lsec.valid


def test_friction_000_p70(tmp_path):
    cfg = _machine(tmp_path, 1, comp="000_p70_friction.lis", select=("frict_comp",))
    fr = cfg.axes[1].comp.frict
    assert fr.mode == 3
    assert list(fr.vin) == [0, 316, 333]
    assert list(fr.out) == [0, 3722, 3884]
    assert (fr.reversal_lookahead, fr.scaling_factor, fr.delay_cycles) == (4, 10, 9)


def test_crosstalk_mode1_000_p91(tmp_path):
    cfg = _machine(tmp_path, 3, comp="000_p91_crosstalk_mode1.lis", select=("crosstalk",))
    ct = cfg.axes[3].comp.crosstalk
    assert ct.dialect == "new" and ct.mode == 1 and ct.master_dyn_ax_nr == 1
    assert ct.velocity_dependent
    assert ct.acceleration == 10000 and ct.deceleration == -10000
    row = dict(zip(CROSSTALK_COLUMNS, ct.corrections[0], strict=True))
    assert row == {
        "accelerate_dir_pos": 25,
        "decelerate_dir_pos": 25,  # "Kw.crosstalk" lines
        "accelerate_dir_neg": 50,
        "decelerate_dir_neg": 50,
    }


def test_crosstalk_mode2_000_p91(tmp_path):
    cfg = _machine(tmp_path, 3, comp="000_p91_crosstalk_mode2.lis", select=("crosstalk",))
    ct = cfg.axes[3].comp.crosstalk
    assert ct.mode == 2 and ct.acceleration == 1000 and ct.deceleration == -1000
    assert list(ct.ax_1[:3]) == [0, 1000, 2000]
    col = CROSSTALK_COLUMNS.index("accelerate_dir_pos")
    assert list(ct.corrections[:3, col]) == [50, 70, 50]


def test_crosstalk_mode3_000_p92_alternative_names(tmp_path):
    cfg = _machine(tmp_path, 3, comp="000_p92_crosstalk_mode3.lis", select=("crosstalk",))
    ct = cfg.axes[3].comp.crosstalk
    assert ct.mode == 3 and ct.master_dyn_ax_nr == 2
    assert (ct.master_pos1_ax_nr, ct.master_pos2_ax_nr) == (1, 3)
    assert ct.acceleration == 1000 and ct.deceleration == -1000  # acceleration_pos / _neg
    assert len(ct.ax_1) == 9
    assert (ct.ax_1[8], ct.ax_2[8]) == (3000, 3000)
    # 000 p.92, position[0]: acc_pos_vel_pos 60, acc_pos_vel_neg 60, acc_neg_vel_pos 70,
    # acc_neg_vel_neg 70. The names give the signs of acceleration and velocity, and
    # accelerating is a·v > 0 (002 §3.5.13-16: "acceleration/deceleration in positive/
    # negative motion direction"): a > 0, v > 0 accelerates in + (60); a < 0, v > 0
    # decelerates in + (70); a < 0, v < 0 accelerates in − (70); a > 0, v < 0
    # decelerates in − (60). Before, the two − columns were swapped (60 and 70).
    by_hand = {
        "accelerate_dir_pos": 60,
        "decelerate_dir_pos": 70,
        "accelerate_dir_neg": 70,
        "decelerate_dir_neg": 60,
    }
    assert {c: ct.corrections[0, CROSSTALK_COLUMNS.index(c)] for c in by_hand} == by_hand


def test_crosstalk_old_model_001(tmp_path):
    cfg = _machine(tmp_path, 3, comp="001_s4.5.3_crosstalk_old.lis", select=("crosstalk",))
    ct = cfg.axes[3].comp.crosstalk
    assert ct.dialect == "old" and ct.master_dyn_ax_nr == 1
    assert ct.acc_table[0] == -10000 and ct.corr_table[0] == -1000
    assert ct.acc_table[1] == 10000 and ct.corr_table[1] == 1000


# ------------------------------------------------------------------ default machine


@pytest.fixture(scope="module")
def default() -> MachineConfig:
    return load_machine(default_startup_list())


def test_default_machine_loads_without_deactivation(default):
    assert sorted(default.axes) == [1, 2, 3, 4]
    assert not default.deactivated, [str(d) for d in default.deactivated]


def test_default_machine_layout(default):
    x, y, z, c = (default.axes[n] for n in (1, 2, 3, 4))
    assert [a.params.name for a in (x, y, z, c)] == ["X", "Y", "Z", "C"]
    assert c.params.kind == "R" and c.params.modulo and c.params.modulo_period == 3_600_000
    # backlash X (manual example) and Y
    assert (x.params.lose, x.params.anwahl_losekomp, x.params.n_backlash_cyc) == (1000, 1, 10)
    assert y.params.lose != 0
    # temperature on all linear axes; X = manual example
    assert all(a.params.temp_comp for a in (x, y, z))
    assert (x.params.temp_comp_position_0, x.params.temp_comp_offset_0) == (100, 40)
    assert x.params.temp_comp_coefficient == 4000.0 and x.params.temp_comp_n_cycles == 20
    # LSEC: X unilateral equidistant, Y bilateral 140 points, C modulo
    assert not x.comp.lsec.bilateral and x.comp.lsec.interval > 0
    assert y.comp.lsec.bilateral and len(y.comp.lsec.setpoint) == 140
    assert y.comp.lsec.setpoint[0] == -200000 and y.comp.lsec.setpoint[139] == 335591
    assert c.comp.lsec.modulo
    assert c.comp.lsec.setpoint[0] == 0 and c.comp.lsec.setpoint[-1] == 3_600_000
    assert c.comp.lsec.pos[0] == c.comp.lsec.pos[-1]
    # friction on X
    assert x.params.frict_comp and x.comp.frict.mode == 3 and len(x.comp.frict.vin) == 10
    # cross and plane on Z
    assert z.comp.cross.master_ax_nr == 1 and len(z.comp.cross.setpoint) == 100
    assert z.comp.plane.table.shape == (21, 21)
    assert (z.comp.plane.master1_ax_nr, z.comp.plane.master2_ax_nr) == (1, 2)
    # crosstalk: mode 1 on Y (master X), mode 3 on Z (master Y, adaptation X and Y)
    assert y.comp.crosstalk.mode == 1 and y.comp.crosstalk.master_dyn_ax_nr == 1
    assert z.comp.crosstalk.mode == 3 and z.comp.crosstalk.master_dyn_ax_nr == 2
    assert (z.comp.crosstalk.master_pos1_ax_nr, z.comp.crosstalk.master_pos2_ax_nr) == (1, 2)
    assert 9 <= len(z.comp.crosstalk.ax_1) <= 15
    # monitoring, symbolic
    assert y.params.prog_movement_requires_compensations == CompKind.LEAD | CompKind.TEMP
