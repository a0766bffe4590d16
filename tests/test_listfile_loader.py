"""Loading the fixture machine `tests/data/lists/machine/` into the typed configuration.

Expected values are typed from the fixture lists (which copy 000 p.13, p.24, p.35, p.62,
p.70 and p.92 values), never computed by the code under test.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from geo_server.listfile import ListFileError, compare_max_points, load_machine
from geo_server.model import CompKind, MachineConfig, Source

MACHINE = Path(__file__).parent / "data" / "lists" / "machine"


@pytest.fixture(scope="module")
def cfg() -> MachineConfig:
    return load_machine(MACHINE / "hochlauf.lis")


def test_axes_in_ascending_order(cfg: MachineConfig) -> None:
    assert list(cfg.axes) == [1, 2, 3, 4]
    assert [a.params.name for a in cfg.axes.values()] == ["X", "Y AXIS", "Z", "C"]
    assert cfg.startup_path == MACHINE / "hochlauf.lis"


def test_no_compensation_deactivated(cfg: MachineConfig) -> None:
    assert cfg.deactivated == []
    assert all(d.severity == "warning" for d in cfg.diagnostics)


def test_expected_warnings(cfg: MachineConfig) -> None:
    got = {(Path(d.file).name, d.line, d.entry) for d in cfg.diagnostics}
    assert got == {
        ("hochlauf.lis", 23, "vol_comp[0].max_records"),
        ("achsmd1.lis", 11, "lr_param.n_backlash_cyc"),
        ("achskw2.lis", 2, "kopf.log_achs_nr"),
        ("achskw2.lis", 23, "frict_comp.position_delay"),
    }


def test_axis_x_parameters(cfg: MachineConfig) -> None:
    p = cfg.axes[1].params
    assert (p.kind, p.v_max, p.a_max, p.homed, p.start_position) == (
        "T",
        5_000_000.0,
        2000.0,
        True,
        100000.0,
    )
    assert (p.lose, p.anwahl_losekomp, p.n_backlash_cyc) == (1000, 1, 10)
    assert p.temp_comp is True
    assert (p.temp_comp_position_0, p.temp_comp_offset_0, p.temp_comp_n_cycles) == (100, 40, 20)
    assert p.temp_comp_coefficient == 4000.0
    assert p.crosscomp2 is True and p.ssfk is False
    assert p.prog_movement_requires_compensations == CompKind.LEAD | CompKind.CROSS


def test_sources_and_path(cfg: MachineConfig) -> None:
    p = cfg.axes[1].params
    assert p.path == str(MACHINE / "achsmd1.lis")
    assert p.sources["lr_param.temp_comp_coefficient"] == Source(str(MACHINE / "achsmd1.lis"), 15)
    assert p.sources["getriebe[0].lose"].line == 9
    assert p.sources["lr_param.n_backlash_cyc"].line == 11


def test_axis_y_quoted_name_hex_mask_and_true(cfg: MachineConfig) -> None:
    p = cfg.axes[2].params
    assert (p.lose, p.anwahl_losekomp, p.ssfk, p.frict_comp) == (-500, 2, True, True)
    assert p.prog_movement_requires_compensations == CompKind.LEAD | CompKind.CROSS | CompKind.PLANE


def test_crlf_axis_list(cfg: MachineConfig) -> None:
    p = cfg.axes[3].params
    assert (p.name, p.crosscomp, p.crosstalk) == ("Z", True, True)
    assert p.sources["lr_param.crosstalk"].line == 5


def test_rotary_modulo_axis_in_subfolder(cfg: MachineConfig) -> None:
    p = cfg.axes[4].params
    assert (p.kind, p.modulo, p.modulo_period) == ("R", True, 3600000.0)
    assert Path(p.path) == MACHINE / "sub" / "achsmd4.lis"


def test_plane_rectangular_table(cfg: MachineConfig) -> None:
    pl = cfg.axes[1].comp.plane
    assert pl.valid and pl.grid == "RECTANGULAR"
    assert (pl.master1_ax_nr, pl.master2_ax_nr, pl.interval1, pl.interval2) == (
        2,
        3,
        100000.0,
        50000.0,
    )
    assert (pl.start_position_master1, pl.start_position_master2) == (-400000.0, -700000.0)
    assert (pl.n_cycles, pl.max_points) == (10, 10201)
    assert pl.table.shape == (2, 3)
    assert pl.table.dtype == np.float64
    assert pl.table[0, 0] == -3 and pl.table[0, 2] == 4 and pl.table[1, 0] == 9
    assert pl.table[1, 2] == 13  # written `table[ 1][ 2]` without `.correction`
    assert pl.table[1, 1] == 0  # unassigned (the line after `End` is not read)


def test_lsec_bilateral_non_equidistant(cfg: MachineConfig) -> None:
    comp = cfg.axes[2].comp
    assert comp.achs_nr == 2 and comp.log_achs_name == "Y AXIS"
    ls = comp.lsec
    assert ls.valid and ls.bilateral and not ls.modulo
    np.testing.assert_array_equal(ls.setpoint, [-200000, -199306, -198667, -198001])
    np.testing.assert_array_equal(ls.pos, [0, 24, -102, -55])
    np.testing.assert_array_equal(ls.neg, [0, 67, 80, 114])
    assert (ls.interval, ls.kw_startpos, ls.max_points) == (0, -200000, 1500)


def test_friction_000_example(cfg: MachineConfig) -> None:
    fr = cfg.axes[2].comp.frict
    assert fr.valid
    np.testing.assert_array_equal(fr.vin, [0, 316, 333])
    np.testing.assert_array_equal(fr.out, [0, 3722, 3884])
    assert (fr.mode, fr.position_delay, fr.reversal_lookahead) == (3, 30, 4)
    assert (fr.scaling_factor, fr.delay_cycles, fr.max_points) == (10, 9, 20)


def test_cross_table(cfg: MachineConfig) -> None:
    cr = cfg.axes[3].comp.cross
    assert cr.valid and cr.master_ax_nr == 1
    np.testing.assert_array_equal(cr.setpoint, [10735, 11523, 10000000])
    np.testing.assert_array_equal(cr.correction, [3, 5, 1000])
    assert (cr.n_cycles, cr.unit, cr.max_points) == (20, 1, 1001)


def test_crosstalk_mode3_alternative_names(cfg: MachineConfig) -> None:
    ct = cfg.axes[3].comp.crosstalk
    assert ct.valid and ct.dialect == "new" and ct.mode == 3
    assert (ct.master_dyn_ax_nr, ct.master_pos1_ax_nr, ct.master_pos2_ax_nr) == (2, 1, 2)
    assert (ct.acceleration, ct.deceleration, ct.velocity_dependent) == (1000.0, -1000.0, True)
    assert ct.max_points == 4
    np.testing.assert_array_equal(ct.ax_1, [0, 3000, 0, 3000])
    np.testing.assert_array_equal(ct.ax_2, [0, 0, 3000, 3000])
    # columns: accelerate_dir_pos, accelerate_dir_neg, decelerate_dir_pos, decelerate_dir_neg;
    # acc_neg_vel_neg (71) accelerates in − (a < 0, v < 0), acc_pos_vel_neg (61) decelerates
    np.testing.assert_array_equal(ct.corrections[0], [60, 71, 70, 61])
    np.testing.assert_array_equal(ct.corrections[1], [50, 0, 0, 0])
    np.testing.assert_array_equal(ct.corrections[2], [0, 0, 0, 40])


def test_modulo_lsec_equidistant(cfg: MachineConfig) -> None:
    ls = cfg.axes[4].comp.lsec
    assert ls.valid and ls.modulo and not ls.bilateral
    np.testing.assert_array_equal(ls.setpoint, [0, 900000, 1800000, 2700000, 3600000])
    np.testing.assert_array_equal(ls.pos, [0, 10, 20, 10, 0])
    np.testing.assert_array_equal(ls.neg, ls.pos)


def test_old_crosstalk_dialect(tmp_path: Path) -> None:
    (tmp_path / "md1.lis").write_text("kopf.achs_nr 1\n")
    (tmp_path / "md3.lis").write_text("kopf.achs_nr 3\nlr_param.crosstalk 1\n")
    (tmp_path / "kw3.lis").write_text(
        "kopf.achs_nr 3\n"
        "kw.crosstalk.last_index 2\n"
        "kw.crosstalk.master_ax_nr 1\n"
        "kw.crosstalk.n_cycles 20\n"
        "kw.crosstalk.table[0].acceleration -10000\n"
        "kw.crosstalk.table[0].correction -1000\n"
        "kw.crosstalk.table[1].acceleration 0\n"
        "kw.crosstalk.table[1].correction 0\n"
        "kw.crosstalk.table[2].acceleration 10000\n"
        "kw.crosstalk.table[2].correction 1000\n"
    )
    (tmp_path / "h.lis").write_text(
        "achs_mds[0] md1.lis\nachs_mds[1] md3.lis\nzahl_kw 1\nachs_kw[0] kw3.lis\n"
    )
    cfg = load_machine(tmp_path / "h.lis")
    ct = cfg.axes[3].comp.crosstalk
    assert cfg.diagnostics == []
    assert ct.valid and ct.dialect == "old" and ct.master_dyn_ax_nr == 1 and ct.n_cycles == 20
    np.testing.assert_array_equal(ct.acc_table, [-10000, 0, 10000])
    np.testing.assert_array_equal(ct.corr_table, [-1000, 0, 1000])


def test_compensation_lists_only_give_default_axes(tmp_path: Path) -> None:
    (tmp_path / "kw1.lis").write_text("kopf.achs_nr 1\n")
    (tmp_path / "kw2.lis").write_text(
        "kw.ssfk.interval 10\nkw.ssfk.kw_nr_max 1\nkw.ssfk.table[0].pos 5\n"
    )
    (tmp_path / "h.lis").write_text(
        "zahl_kw 2\nachs_kw[0] kw1.lis\nachs_kw[1] kw2.lis\nachs_kw_log_ax_nr[1] 2\n"
    )
    cfg = load_machine(tmp_path / "h.lis")
    assert list(cfg.axes) == [1, 2]
    assert cfg.axes[2].comp.lsec.pos.tolist() == [5.0]


@pytest.mark.parametrize(
    ("startup", "files", "message"),
    [
        ("missing.lis", {}, "start-up list not found"),
        ("h.lis", {"h.lis": "achs_mds[0] nothere.lis\n"}, "axis parameter list not found"),
        (
            "h.lis",
            {"h.lis": "zahl_kw 1\nachs_kw[0] ..\\x\\kw.lis\n"},
            "compensation value list not found",
        ),
        ("h.lis", {"h.lis": "# nothing\n"}, "no axes"),
    ],
)
def test_list_file_error(tmp_path: Path, startup: str, files: dict[str, str], message: str) -> None:
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(ListFileError, match=message) as info:
        load_machine(tmp_path / startup)
    assert isinstance(info.value.path, str) and isinstance(info.value.line, int)


def test_compare_max_points(cfg: MachineConfig, tmp_path: Path) -> None:
    assert compare_max_points(cfg, cfg) == []
    shutil.copytree(MACHINE, tmp_path / "machine")
    kw2 = tmp_path / "machine" / "achskw2.lis"
    kw2.write_text(kw2.read_text() + "kw.ssfk.max_points 2000\nfrict_comp.max_points 30\n")
    kw3 = tmp_path / "machine" / "achskw3.lis"
    kw3.write_text(kw3.read_text() + "kw.crosscomp.max_points 1001\n")  # = default: no change
    new = load_machine(tmp_path / "machine" / "hochlauf.lis")
    got = sorted((d.axis, d.error_id, d.entry, d.deactivated) for d in compare_max_points(cfg, new))
    assert got == [
        (2, 110638, "kw.ssfk.max_points", CompKind.LEAD),
        (2, 110641, "frict_comp.max_points", CompKind.FRICT),
    ]
    kw1 = tmp_path / "machine" / "achskw1.lis"
    kw1.write_text(
        kw1.read_text().replace("kw.crosscomp2.n_cycles 10", "kw.crosscomp2.max_points 6")
    )
    kw3.write_text(kw3.read_text().replace("max_points 1001", "max_points 500"))
    new = load_machine(tmp_path / "machine" / "hochlauf.lis")
    ids = sorted(d.error_id for d in compare_max_points(cfg, new))
    assert ids == [110638, 110639, 110640, 110641]
