"""What the manuals allow or require around the compensations, with hand-computed values:

* plane compensation whose master is the compensated axis itself (000 §4.3 p.38, 001
  §4.4: "Eine der Masterachsen kann auch die Slaveachse selbst sein");
* drive enables, a precondition of cross and plane compensation and so of the 70435
  monitoring (000 §5.3 p.97 item 4), switched by `SIM::drive_enable`;
* the drive side's actual position `dig_act_pos` (000 p.19), `SIM::drive_actual_position`;
* the 16 characters of `kopf.log_achs_name` (P-COMP-00002, 002/003 §2.2), a warning.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from support.reference import ReferenceKernel

from geo_server import access
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.kernel.common import COLUMN
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.model import CompKind
from geo_server.service import ObjectService


def _write(folder: Path, name: str, lines: list[str]) -> None:
    (folder / name).write_text("\n".join(lines) + "\n", encoding="utf-8")


def _machine(folder: Path, axis_extra: dict[str, list[str]], comp: dict[str, list[str]]) -> Path:
    """Linear axes X, Y, Z (1, 2, 3); `axis_extra` adds lines to an axis list, `comp` gives
    an axis a compensation value list."""
    folder.mkdir(parents=True, exist_ok=True)
    stup = ["zahl_mds 3"]
    for k, name in enumerate("XYZ"):
        nr = k + 1
        head = [f"kopf.achs_nr {nr}", f"kopf.log_achs_name {name}", "kenngr.achs_typ 1"]
        _write(folder, f"achsmd{nr}.lis", head + axis_extra.get(name, []))
        stup += [f"achs_mds_log_ax_nr[{k}] {nr}", f"achs_mds[{k}] achsmd{nr}.lis"]
    stup.append(f"zahl_kw {len(comp)}")
    for k, (name, lines) in enumerate(comp.items()):
        nr = "XYZ".index(name) + 1
        _write(folder, f"achskw{nr}.lis", [f"kopf.achs_nr {nr}", *lines])
        stup += [f"achs_kw_log_ax_nr[{k}] {nr}", f"achs_kw[{k}] achskw{nr}.lis"]
    _write(folder, "hochlauf.lis", stup)
    return folder / "hochlauf.lis"


# --------------------------------------------------------------------------- plane


#: Z over Z (master 1, the slave itself) and X (master 2): a 2 x 2 QUADRATIC grid of 10 mm,
#: table[j][i] with j along master 2 (X) and i along master 1 (Z) (000 p.43)
PLANE_SELF = [
    "kw.crosscomp2.master1_ax_nr 3",
    "kw.crosscomp2.master2_ax_nr 1",
    "kw.crosscomp2.grid QUADRATIC",
    "kw.crosscomp2.interval 100000",
    "kw.crosscomp2.start_position_master1 0",
    "kw.crosscomp2.start_position_master2 0",
    "kw.crosscomp2.last_index_master1 1",
    "kw.crosscomp2.last_index_master2 1",
    "kw.crosscomp2.n_cycles 0",
    "kw.crosscomp2.unit 1",
    "kw.crosscomp2.table[0][0].correction 0",
    "kw.crosscomp2.table[0][1].correction 100",
    "kw.crosscomp2.table[1][0].correction 200",
    "kw.crosscomp2.table[1][1].correction 400",
]


def test_plane_master_may_be_the_slave_itself(tmp_path):
    """Z = 2.5 mm (u = 0.25 of the Z cell), X = 5 mm (v = 0.5 of the X cell), bilinear:
    0.75·0.5·0 + 0.25·0.5·100 + 0.75·0.5·200 + 0.25·0.5·400 = 12.5 + 75 + 50 = 137.5
    (0.1 µm). Before: refused with 70183 and plane compensation switched off."""
    startup = _machine(tmp_path, {"Z": ["lr_param.crosscomp2 1"]}, {"Z": PLANE_SELF})
    cfg = load_machine(startup)
    assert [d for d in cfg.diagnostics if d.error_id == 70183] == []
    assert cfg.axes[3].comp is not None and cfg.axes[3].comp.plane.valid
    m = Machine(cfg, cycle_s=0.001, homed=True)
    m.apply_write("SIM::set_position", 3, 25_000)  # Z 2.5 mm
    m.apply_write("SIM::set_position", 1, 50_000)  # X 5 mm
    m.step(2)
    z = m.slot(3)
    assert m.kernel.effective[z, COLUMN[CompKind.PLANE]]
    assert m.kernel.actual[z, COLUMN[CompKind.PLANE]] == 137.5
    # the oracle kernel agrees
    ref = ReferenceKernel(cfg)
    pos = m.motion.pos.copy()
    zeros = pos * 0
    for _ in range(2):
        ref.step(pos, zeros, zeros, m.motion.homed.copy(), zeros - 1)
    assert ref.actual[z, COLUMN[CompKind.PLANE]] == 137.5
    # V.A.PLANE_COMP_CURR in mm: 137.5 · 0.1 µm = 0.01375 mm
    assert m.nc_side.current(z, CompKind.PLANE) == pytest.approx(0.01375, abs=1e-12)


def test_plane_masters_still_must_differ(tmp_path):
    lines = [x.replace("master2_ax_nr 1", "master2_ax_nr 3") for x in PLANE_SELF]
    cfg = load_machine(_machine(tmp_path, {"Z": ["lr_param.crosscomp2 1"]}, {"Z": lines}))
    assert [d.error_id for d in cfg.diagnostics] == [70183]


# --------------------------------------------------------------------------- drive enable

#: X is the slave of a cross compensation over Y: 50 at Y = 0, 150 at Y = 100 mm; the
#: monitoring requires it (000 p.98: `prog_movement_requires_compensations LEAD | CROSS`;
#: this machine has no LSEC)
CROSS_X = [
    "kw.crosscomp.master_ax_nr 2",
    "kw.crosscomp.unit 1",
    "kw.crosscomp.n_cycles 0",
    "kw.crosscomp.last_index 1",
    "kw.crosscomp.table[0].setpoint 0",
    "kw.crosscomp.table[0].correction 50",
    "kw.crosscomp.table[1].setpoint 1000000",
    "kw.crosscomp.table[1].correction 150",
]
REQUIRES_CROSS = ["lr_param.crosscomp 1", "lr_param.prog_movement_requires_compensations CROSS"]


def _run(m: Machine, text: str, cycles: int = 3000) -> None:
    m.start_program(text)
    for _ in range(cycles):
        m.step()
        if m.player is not None and not m.player.running:
            return


def test_drive_enable_is_a_precondition_of_cross_and_of_70435(tmp_path):
    """000 p.97: "The drive releases must be set for cross and plane compensation before
    NC program start." Without X's drive enable its cross compensation is not effective,
    so moving X in a program raises P-ERR-70435; with it the program runs."""
    startup = _machine(tmp_path, {"X": REQUIRES_CROSS}, {"X": CROSS_X})
    m = Machine(load_machine(startup), cycle_s=0.001, homed=True)
    svc = ObjectService(m)
    assert access.read_name(svc, "SIM::drive_enable", 1) is True  # on at start-up
    access.step(svc, 2)
    assert access.read_name(svc, "CROSSC::f_is_active", 1) is True
    assert access.read_name(svc, "CROSSC::actual_offset", 1) == 50  # Y = 0: table[0]
    access.write_name(svc, "SIM::drive_enable", 1, False)
    access.step(svc, 2)
    assert access.read_name(svc, "SIM::drive_enable", 1) is False
    assert access.read_name(svc, "CROSSC::activated", 1) is True  # still selected ...
    assert access.read_name(svc, "CROSSC::f_is_active", 1) is False  # ... but not effective
    assert access.read_name(svc, "CROSSC::actual_offset", 1) == 0  # n_cycles 0: at once
    _run(m, "N10 G01 X10 F6000\nM30")
    assert m.player is not None and m.player.error is not None
    assert (m.player.error.error_id, m.player.error.line) == (70435, 1)
    assert m.nc_side.position(0) == 0.0  # X did not move
    # Y's drive is not X's: only the compensated axis' enable counts
    access.write_name(svc, "SIM::drive_enable", 1, True)
    access.write_name(svc, "SIM::drive_enable", 2, False)
    access.step(svc, 2)
    _run(m, "N10 G01 X10 F6000\nM30")
    assert m.player.finished and m.player.error is None
    assert m.nc_side.position(0) == 100_000.0


def test_drive_actual_position_follows_only_an_enabled_drive(tmp_path):
    """dig_act_pos (000 p.19: the compensations can be seen in the drive bus' positions):
    with the drive enabled it is the output (command + compensations); a disabled drive
    holds where it was. X at 10 mm with cross 50 (Y = 0): 100 000 + 50 = 100 050."""
    startup = _machine(tmp_path, {"X": ["lr_param.crosscomp 1"]}, {"X": CROSS_X})
    m = Machine(load_machine(startup), cycle_s=0.001, homed=True)
    svc = ObjectService(m)
    access.write_name(svc, "SIM::set_position", 1, 100_000)
    access.step(svc, 2)
    assert access.read_name(svc, "SIM::output_position", 1) == 100_050
    assert access.read_name(svc, "SIM::drive_actual_position", 1) == 100_050
    access.write_name(svc, "SIM::drive_enable", 1, False)
    access.write_name(svc, "SIM::set_position", 1, 200_000)
    access.step(svc, 2)
    # the output is the command alone now (cross not effective); the drive stayed
    assert access.read_name(svc, "SIM::output_position", 1) == 200_000
    assert access.read_name(svc, "SIM::drive_actual_position", 1) == 100_050
    access.write_name(svc, "SIM::drive_enable", 1, True)
    access.step(svc, 2)  # cross effective again (n_cycles 0): 200 000 + 50
    assert access.read_name(svc, "SIM::drive_actual_position", 1) == 200_050
    with pytest.raises(AdsError) as exc:  # read-only, like SIM::output_position
        access.write_name(svc, "SIM::drive_actual_position", 1, 0)
    assert exc.value.code == AdsErrorCode.DEVICE_INVALIDACCESS


# --------------------------------------------------------------------------- axis name


@pytest.mark.parametrize(("name", "warned"), [("X" * 16, False), ("X_AXIS_OF_TABLE_1", True)])
def test_log_achs_name_longer_than_16_characters_warns(tmp_path, name, warned):
    """P-COMP-00002: "Maximum 16 characters"; a longer name is kept, with a warning that
    names file, line and entry; nothing is switched off."""
    startup = _machine(
        tmp_path,
        {"X": ["lr_param.crosscomp 1"]},
        {"X": [f"kopf.log_achs_name {name}", *CROSS_X]},
    )
    cfg = load_machine(startup)
    found = [d for d in cfg.diagnostics if d.entry == "kopf.log_achs_name"]
    if not warned:
        assert found == []
        return
    assert len(found) == 1
    d = found[0]
    assert (d.severity, d.error_id, d.deactivated, d.line) == ("warning", 0, None, 2)
    assert d.file.endswith("achskw1.lis") and "17 characters, at most 16" in d.message
    assert cfg.axes[1].comp is not None and cfg.axes[1].comp.log_achs_name == name
    assert cfg.axes[1].comp.cross is not None and cfg.axes[1].comp.cross.valid
