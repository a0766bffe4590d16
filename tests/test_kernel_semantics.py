"""Compensation kernel semantics (docs/design.md §3, §6) on the manual's own examples.

Expected values are computed by hand here from the manual's formulas; every test runs on
both the fast `Kernel` and the `ReferenceKernel`. 000 = TF5200 axis compensation EN.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from support.reference import ReferenceKernel

from geo_server.kernel import COMP_ORDER, Kernel
from geo_server.model import (
    AxisConfig,
    AxisParams,
    CompKind,
    CompList,
    CrossComp,
    CrosstalkComp,
    FrictComp,
    LsecComp,
    MachineConfig,
    PlaneComp,
)

KERNELS = [Kernel, ReferenceKernel]
BC, TEMP, CROSS, PLANE, LEAD, FRICT, XT = range(7)


def sin2(k: int, n: int) -> float:
    return math.sin(math.pi * k / (2 * n)) ** 2


def cos2(k: int, n: int) -> float:
    return math.cos(math.pi * k / (2 * n)) ** 2


def machine(*axes: AxisConfig) -> MachineConfig:
    return MachineConfig(Path("<test>"), {a.params.log_nr: a for a in axes})


def axis(nr: int, comp: CompList | None = None, **params: object) -> AxisConfig:
    return AxisConfig(AxisParams(log_nr=nr, **params), comp)  # type: ignore[arg-type]


class Drive:
    """Feeds one kernel with explicit per-axis command values."""

    def __init__(self, kernel_cls: type, cfg: MachineConfig) -> None:
        self.k = kernel_cls(cfg)
        n = len(cfg.axes)
        self.pos = np.zeros(n)
        self.vel = np.zeros(n)
        self.acc = np.zeros(n)
        self.homed = np.zeros(n, dtype=bool)
        self.rev = np.full(n, -1, dtype=np.int64)

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.k.step(self.pos, self.vel, self.acc, self.homed, self.rev)


def round_half_away(x: float) -> int:
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


def test_comp_order() -> None:
    assert COMP_ORDER == (
        CompKind.BACKLASH,
        CompKind.TEMP,
        CompKind.CROSS,
        CompKind.PLANE,
        CompKind.LEAD,
        CompKind.FRICT,
        CompKind.CROSSTALK,
    )


# --------------------------------------------------------------------------- temperature


def temp_axis(n_cycles: int = 0, manual: bool = False) -> AxisConfig:
    # 000 §3.2 p.17: position_0 100, offset_0 40, coefficient 4000 µm/m
    return axis(
        1,
        temp_comp=True,
        temp_comp_position_0=100,
        temp_comp_offset_0=40,
        temp_comp_coefficient=4000.0,
        temp_comp_n_cycles=n_cycles,
        temp_comp_manual_activation=manual,
    )


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_temperature_manual_example(kernel_cls: type) -> None:
    d = Drive(kernel_cls, machine(temp_axis()))
    d.homed[0] = True
    d.pos[0] = 1_000_000  # X = 100 mm
    d.step()
    expected = 40 + 4000 * 1e-6 * (1_000_000 - 100)  # 4039.6
    assert expected == pytest.approx(4039.6)
    assert d.k.target[0, TEMP] == pytest.approx(expected, abs=1e-9)
    assert d.k.actual[0, TEMP] == pytest.approx(expected, abs=1e-9)
    assert round_half_away(d.k.actual[0, TEMP]) == 4040
    assert d.k.effective[0, TEMP] and d.k.selected[0, TEMP]
    assert d.k.total_offset[0] == pytest.approx(expected)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_temperature_unhomed_not_effective(kernel_cls: type) -> None:
    d = Drive(kernel_cls, machine(temp_axis(n_cycles=4)))
    d.pos[0] = 1_000_000
    d.step(3)
    assert d.k.selected[0, TEMP] and not d.k.effective[0, TEMP]
    assert d.k.actual[0, TEMP] == 0.0 and d.k.target[0, TEMP] == 0.0
    # homing is an activation: ramps in over temp_comp_n_cycles
    d.homed[0] = True
    value = 40 + 4000 * 1e-6 * (1_000_000 - 100)
    for k in range(1, 5):
        d.step()
        assert d.k.actual[0, TEMP] == pytest.approx(value * sin2(k, 4), abs=1e-9)
    d.step()
    assert d.k.actual[0, TEMP] == pytest.approx(value, abs=1e-9)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_temperature_manual_activation_starts_deselected(kernel_cls: type) -> None:
    d = Drive(kernel_cls, machine(temp_axis(manual=True)))
    d.homed[0] = True
    d.step()
    assert not d.k.selected[0, TEMP] and d.k.actual[0, TEMP] == 0.0
    d.k.set_selected(0, CompKind.TEMP, True)  # COMP ON TEMP / TEMPC::activated write
    d.step()
    assert d.k.actual[0, TEMP] == pytest.approx(40 + 4000e-6 * (0 - 100))


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_temperature_live_write_ramps(kernel_cls: type) -> None:
    n = 5
    d = Drive(kernel_cls, machine(temp_axis(n_cycles=n)))
    d.homed[0] = True
    d.pos[0] = 1_000_000
    d.step(10)
    old = 40 + 4000e-6 * 999_900
    assert d.k.actual[0, TEMP] == pytest.approx(old)
    d.k.write_tempc(0, "coefficient", 2000.0)
    coefficient, offset_0, position_0 = d.k.tempc_params
    assert (coefficient[0], offset_0[0], position_0[0]) == (2000.0, 40.0, 100.0)
    new = 40 + 2000e-6 * 999_900  # 2039.8
    jump = new - old
    prev = old
    for k in range(1, n + 1):
        d.step()
        want = new - jump * cos2(k, n)
        assert d.k.target[0, TEMP] == pytest.approx(new)
        assert d.k.actual[0, TEMP] == pytest.approx(want, abs=1e-9)
        assert d.k.delta[0, TEMP] == pytest.approx(want - prev, abs=1e-9)
        prev = want
    d.step()
    assert d.k.actual[0, TEMP] == pytest.approx(new)
    assert d.k.delta[0, TEMP] == pytest.approx(0.0, abs=1e-9)
    # a moving target is tracked while a jump decays: write offset_0, move the axis
    d.k.write_tempc(0, "offset_0", 140.0)
    d.pos[0] = 1_100_000
    d.step()
    tgt = 140 + 2000e-6 * (1_100_000 - 100)
    j = tgt - new
    assert d.k.actual[0, TEMP] == pytest.approx(tgt - j * cos2(1, n), abs=1e-9)
    d.pos[0] = 1_200_000
    d.step()
    tgt2 = 140 + 2000e-6 * (1_200_000 - 100)
    assert d.k.actual[0, TEMP] == pytest.approx(tgt2 - j * cos2(2, n), abs=1e-9)


# --------------------------------------------------------------------------- backlash


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_backlash_manual_example(kernel_cls: type) -> None:
    # 000 §2.5 p.13: lose 1000, anwahl_losekomp 1, n_backlash_cyc 10
    d = Drive(kernel_cls, machine(axis(1, lose=1000, anwahl_losekomp=1, n_backlash_cyc=10)))
    d.vel[0] = 1000.0
    d.step(3)
    assert d.k.effective[0, BC]  # no homing needed (000 §2.2 p.10)
    assert d.k.actual[0, BC] == 0.0 and d.k.target[0, BC] == 0.0
    d.vel[0] = -1000.0  # reversal to negative
    prev = 0.0
    for k in range(1, 11):
        d.step()
        want = -1000 * sin2(k, 10)
        assert d.k.target[0, BC] == -1000.0
        assert d.k.actual[0, BC] == pytest.approx(want, abs=1e-9)
        assert d.k.delta[0, BC] == pytest.approx(want - prev, abs=1e-9)
        prev = want
    d.vel[0] = 0.0  # standstill: direction held
    d.step(3)
    assert d.k.actual[0, BC] == pytest.approx(-1000.0)
    assert d.k.delta[0, BC] == pytest.approx(0.0, abs=1e-9)
    d.vel[0] = 500.0  # back to the initial direction: ramps to 0
    d.step()
    assert d.k.actual[0, BC] == pytest.approx(-1000 + 1000 * sin2(1, 10), abs=1e-9)
    d.step(9)
    assert d.k.actual[0, BC] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_backlash_initial_negative_and_jump(kernel_cls: type) -> None:
    d = Drive(kernel_cls, machine(axis(1, lose=-300, anwahl_losekomp=2, n_backlash_cyc=0)))
    d.vel[0] = -5.0
    d.step()
    assert d.k.actual[0, BC] == 0.0
    d.vel[0] = 5.0  # reversal to positive: d·lose = −300 in one cycle (N ≤ 1)
    d.step()
    assert d.k.actual[0, BC] == pytest.approx(-300.0)
    # COMP OFF BACKLASH: deactivation is a step event
    d.k.set_selected(0, CompKind.BACKLASH, False)
    d.step()
    assert d.k.actual[0, BC] == pytest.approx(0.0) and not d.k.effective[0, BC]


# --------------------------------------------------------------------------- LSEC

SP = [-200000.0, -199306.0, -198667.0, -198001.0]  # 000 p.62 excerpt
POS = [0.0, 24.0, -102.0, 37.0]  # table[3].pos is our own value
NEG = [0.0, 67.0, 80.0, 90.0]  # table[3].neg is our own value


def lsec_axis(**kw: object) -> AxisConfig:
    ls = LsecComp(setpoint=np.array(SP), pos=np.array(POS), neg=np.array(NEG), bilateral=True, **kw)  # type: ignore[arg-type]
    return axis(2, CompList("", 2, lsec=ls), ssfk=True, n_backlash_cyc=4)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_lsec_bilateral_lookup_and_reversal(kernel_cls: type) -> None:
    d = Drive(kernel_cls, machine(lsec_axis()))
    d.pos[0] = -199000.0
    d.vel[0] = 10.0
    d.step()
    assert not d.k.effective[0, LEAD] and d.k.actual[0, LEAD] == 0.0  # needs homing
    d.homed[0] = True
    d.step(4)  # activation ramp over n_backlash_cyc
    t = (-199000.0 - -199306.0) / (-198667.0 - -199306.0)
    ds_pos = 24 + t * (-102 - 24)
    assert d.k.actual[0, LEAD] == pytest.approx(-ds_pos, abs=1e-9)  # applied −Δs
    assert d.k.target[0, LEAD] == pytest.approx(-ds_pos, abs=1e-9)
    # outside the table: edge values held
    d.pos[0] = -300000.0
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(0.0)
    d.pos[0] = 500000.0
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(-37.0)
    # reversal pos → neg at -199000: the neg table, ramped over n_backlash_cyc = 4
    d.pos[0] = -199000.0
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(-ds_pos)
    ds_neg = 67 + t * (80 - 67)
    d.vel[0] = -10.0
    jump = -ds_neg - -ds_pos
    for k in range(1, 5):
        d.step()
        assert d.k.actual[0, LEAD] == pytest.approx(-ds_neg - jump * cos2(k, 4), abs=1e-9)
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(-ds_neg)
    # between points exactly on a setpoint
    d.pos[0] = -198667.0
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(-80.0)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_lsec_unilateral_ignores_direction(kernel_cls: type) -> None:
    ls = LsecComp(setpoint=np.array(SP), pos=np.array(POS), neg=np.array(NEG), bilateral=False)
    d = Drive(kernel_cls, machine(axis(1, CompList("", 1, lsec=ls), ssfk=True)))
    d.homed[0] = True
    d.pos[0] = -198667.0
    d.vel[0] = -1.0
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(102.0)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_lsec_modulo_rotary(kernel_cls: type) -> None:
    ls = LsecComp(
        setpoint=np.array([0.0, 1_800_000.0, 3_600_000.0]),
        pos=np.array([0.0, 100.0, 0.0]),
        neg=np.array([0.0, 100.0, 0.0]),
        modulo=True,
    )
    ax = axis(1, CompList("", 1, lsec=ls), ssfk=True, kind="R", modulo=True)
    d = Drive(kernel_cls, machine(ax))
    d.homed[0] = True
    d.pos[0] = 3_600_000.0 + 900_000.0  # 450° → 90°
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(-50.0)
    d.pos[0] = -900_000.0  # −90° → 270°
    d.step()
    assert d.k.actual[0, LEAD] == pytest.approx(-50.0)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_lsec_lookup_includes_cross(kernel_cls: type) -> None:
    # cross adds a constant 1000 to axis 2; LSEC of axis 2 looks up at command + 1000
    cross = CrossComp(master_ax_nr=1, setpoint=np.array([0.0]), correction=np.array([1000.0]))
    ls = LsecComp(
        setpoint=np.array([0.0, 10_000.0]), pos=np.array([0.0, 100.0]), neg=np.array([0.0, 100.0])
    )
    for without, want in ((False, -(100 * 3000 / 10_000)), (True, -(100 * 2000 / 10_000))):
        ls.set_pos_without_comp = without
        comp = CompList("", 2, cross=cross, lsec=ls)
        d = Drive(kernel_cls, machine(axis(1), axis(2, comp, crosscomp=True, ssfk=True)))
        d.homed[:] = True
        d.pos[1] = 2000.0
        d.step()
        assert d.k.actual[1, CROSS] == pytest.approx(1000.0)
        assert d.k.actual[1, LEAD] == pytest.approx(want)
        assert d.k.total_offset[1] == pytest.approx(1000.0 + want)


# --------------------------------------------------------------------------- plane


def plane_machine(n_cycles: int = 0) -> MachineConfig:
    # 000 p.43 Fig. 13 grid: interval 100000, last_index 7 / 6, start 220000 / -160000
    table = np.zeros((7, 8))  # table[j][i]: j master 2 (rows), i master 1 (columns)
    table[1][2], table[1][3], table[2][2], table[2][3] = 5.0, 9.0, 20.0, 40.0
    table[6][0] = 77.0
    table[0][7] = -11.0
    pl = PlaneComp(
        master1_ax_nr=1,
        master2_ax_nr=2,
        start_position_master1=220000.0,
        start_position_master2=-160000.0,
        interval1=100000.0,
        interval2=100000.0,
        table=table,
        n_cycles=n_cycles,
    )
    return machine(axis(1), axis(2), axis(3, CompList("", 3, plane=pl), crosscomp2=True))


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_plane_bilinear_and_clamp(kernel_cls: type) -> None:
    d = Drive(kernel_cls, plane_machine())
    d.homed[:] = True
    d.pos[0] = 220000 + 2.5 * 100000  # i = 2.5
    d.pos[1] = -160000 + 1.3 * 100000  # j = 1.3
    d.step()
    fu, fv = 0.5, 0.3
    want = (1 - fu) * (1 - fv) * 5 + fu * (1 - fv) * 9 + (1 - fu) * fv * 20 + fu * fv * 40
    assert want == pytest.approx(13.9)
    assert d.k.actual[2, PLANE] == pytest.approx(want, abs=1e-9)
    # outside the grid the edge values hold: master 1 far below, master 2 far above
    d.pos[0], d.pos[1] = -1e7, 1e7
    d.step()
    assert d.k.actual[2, PLANE] == pytest.approx(77.0)  # table[6][0]
    d.pos[0], d.pos[1] = 1e7, -1e7
    d.step()
    assert d.k.actual[2, PLANE] == pytest.approx(-11.0)  # table[0][7]


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_plane_needs_both_masters_homed(kernel_cls: type) -> None:
    d = Drive(kernel_cls, plane_machine(n_cycles=3))
    d.pos[0], d.pos[1] = 220000 + 200000, -160000 + 100000  # grid point (i 2, j 1) = 5
    d.homed[0] = True
    d.step()
    assert not d.k.effective[2, PLANE] and d.k.actual[2, PLANE] == 0.0
    d.homed[1] = True
    for k in range(1, 4):
        d.step()
        assert d.k.actual[2, PLANE] == pytest.approx(5 * sin2(k, 3), abs=1e-9)


# --------------------------------------------------------------------------- cross


def cross_machine(n_cycles: int = 0, rotary_master: bool = False) -> MachineConfig:
    if rotary_master:
        cc = CrossComp(
            master_ax_nr=1,
            setpoint=np.array([0.0, 1_800_000.0, 3_600_000.0]),
            correction=np.array([0.0, 100.0, 0.0]),
            n_cycles=n_cycles,
        )
        master = axis(1, kind="R", modulo=True)
    else:
        cc = CrossComp(
            master_ax_nr=1,
            setpoint=np.array([0.0, 1000.0, 3000.0]),
            correction=np.array([0.0, 10.0, 30.0]),
            n_cycles=n_cycles,
        )
        master = axis(1)
    return machine(master, axis(2, CompList("", 2, cross=cc), crosscomp=True))


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_cross_value_edges(kernel_cls: type) -> None:
    d = Drive(kernel_cls, cross_machine())
    d.homed[0] = True  # only the master needs homing (000 p.29)
    for p, want in ((2000.0, 20.0), (500.0, 5.0), (5000.0, 30.0), (-50.0, 0.0)):
        d.pos[0] = p
        d.step()
        assert d.k.actual[1, CROSS] == pytest.approx(want)
        assert d.k.effective[1, CROSS]


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_cross_modulo_master(kernel_cls: type) -> None:
    d = Drive(kernel_cls, cross_machine(rotary_master=True))
    d.homed[0] = True
    d.pos[0] = 3_600_000.0 * 2 + 900_000.0
    d.step()
    assert d.k.actual[1, CROSS] == pytest.approx(50.0)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_cross_master_homing_ramp_and_comp_off(kernel_cls: type) -> None:
    n = 4
    d = Drive(kernel_cls, cross_machine(n_cycles=n))
    d.pos[0] = 2000.0
    d.step(2)
    assert not d.k.effective[1, CROSS] and d.k.actual[1, CROSS] == 0.0
    d.homed[0] = True
    for k in range(1, n + 1):
        d.step()
        assert d.k.actual[1, CROSS] == pytest.approx(20 * sin2(k, n), abs=1e-9)
        assert d.k.target[1, CROSS] == 20.0
    d.k.set_selected(1, CompKind.CROSS, False)  # COMP OFF CROSS ramps out
    for k in range(1, n + 1):
        d.step()
        assert d.k.actual[1, CROSS] == pytest.approx(20 * cos2(k, n), abs=1e-9)
    assert not d.k.selected[1, CROSS]


# --------------------------------------------------------------------------- crosstalk

MM = 10_000.0  # internal units per mm: acc/10000 = mm/s²


def xt_machine(xt: CrosstalkComp) -> MachineConfig:
    return machine(axis(1), axis(2, CompList("", 2, crosstalk=xt), crosstalk=True), axis(3))


def mode1(velocity_dependent: bool = True) -> CrosstalkComp:
    # 000 p.91: acceleration 10000, deceleration -10000, corrections 25/25/50/50
    # columns: accelerate_dir_pos, accelerate_dir_neg, decelerate_dir_pos, decelerate_dir_neg
    return CrosstalkComp(
        dialect="new",
        master_dyn_ax_nr=1,
        mode=1,
        acceleration=10000.0,
        deceleration=-10000.0,
        velocity_dependent=velocity_dependent,
        ax_1=np.zeros(1),
        ax_2=np.zeros(1),
        corrections=np.array([[25.0, 50.0, 25.0, 50.0]]),
    )


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_mode1(kernel_cls: type) -> None:
    d = Drive(kernel_cls, xt_machine(mode1()))
    cases = [
        (100.0, 5000 * MM, 25 * 0.5),  # accelerating, positive: 25·5000/10000
        (100.0, -2000 * MM, 25 * 0.2),  # decelerating, positive
        (-100.0, -10000 * MM, 50.0),  # accelerating, negative direction
        (-100.0, 4000 * MM, 50 * 0.4),  # decelerating, negative direction
        (100.0, 20000 * MM, 25.0),  # beyond the reference: clamped
        (0.0, 3000 * MM, 25 * 0.3),  # start from rest counts as accelerating
        (100.0, 0.0, 0.0),
    ]
    for v, a, want in cases:
        d.vel[0], d.acc[0] = v, a
        d.step()
        assert d.k.effective[1, XT]  # no homing needed
        assert d.k.target[1, XT] == pytest.approx(want), (v, a)
        assert d.k.actual[1, XT] == pytest.approx(want), (v, a)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_mode1_direction_independent(kernel_cls: type) -> None:
    d = Drive(kernel_cls, xt_machine(mode1(velocity_dependent=False)))
    d.vel[0], d.acc[0] = -100.0, -10000 * MM
    d.step()
    assert d.k.actual[1, XT] == pytest.approx(25.0)  # dir_pos columns only


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_mode2(kernel_cls: type) -> None:
    # 000 p.91: reference ±1000, ax_1 0/1000/2000 with accelerate_dir_pos 50/70/50
    xt = CrosstalkComp(
        dialect="new",
        master_dyn_ax_nr=1,
        master_pos1_ax_nr=3,
        mode=2,
        acceleration=1000.0,
        deceleration=-1000.0,
        velocity_dependent=True,
        ax_1=np.array([0.0, 1000.0, 2000.0]),
        ax_2=np.zeros(3),
        # the manual lists each record as accelerate_dir_pos, decelerate_dir_pos,
        # accelerate_dir_neg, decelerate_dir_neg = 50, 50, 60, 60 (70, 70, 80, 80 at
        # ax_1 1000); the array columns are accelerate_dir_pos, accelerate_dir_neg,
        # decelerate_dir_pos, decelerate_dir_neg
        corrections=np.array([[50.0, 60, 50, 60], [70, 80, 70, 80], [50, 60, 50, 60]]),
    )
    d = Drive(kernel_cls, xt_machine(xt))
    d.vel[0], d.acc[0] = 10.0, 500 * MM  # accelerating, ratio 0.5
    for p, c_ref in ((500.0, 60.0), (1000.0, 70.0), (1750.0, 55.0), (5000.0, 50.0), (-9.0, 50.0)):
        d.pos[2] = p
        d.step()
        assert d.k.actual[1, XT] == pytest.approx(c_ref * 0.5), p
    d.pos[2] = 500.0
    # (velocity, acceleration, expected): the reference value at ax_1 500 is the mean of
    # the records at 0 and 1000 in the selected column, times |a|/1000 mm/s²
    for v, a, want in (
        (10.0, -1000 * MM, 60.0),  # decelerating, positive: (50 + 70) / 2
        (-10.0, -500 * MM, 35.0),  # accelerating, negative: (60 + 80) / 2 · 0.5
        (-10.0, 1000 * MM, 70.0),  # decelerating, negative: (60 + 80) / 2
    ):
        d.vel[0], d.acc[0] = v, a
        d.step()
        assert d.k.actual[1, XT] == pytest.approx(want), (v, a)


def mode3(points: list[tuple[float, float]], values: list[float]) -> CrosstalkComp:
    corr = np.array([[v, v, v, v] for v in values])
    return CrosstalkComp(
        dialect="new",
        master_dyn_ax_nr=1,
        master_pos1_ax_nr=1,
        master_pos2_ax_nr=3,
        mode=3,
        acceleration=1000.0,
        deceleration=-1000.0,
        ax_1=np.array([p[0] for p in points]),
        ax_2=np.array([p[1] for p in points]),
        corrections=corr,
    )


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_mode3_triangle_and_hull(kernel_cls: type) -> None:
    # A(0,0)=0, B(1000,0)=100, C(0,1000)=40, D(1100,1100)=200. D is outside the
    # circumcircle of ABC (centre (500,500), r² = 500000 < 600²+600²), so the Delaunay
    # diagonal is BC: triangles ABC and BCD.
    xt = mode3([(0, 0), (1000, 0), (0, 1000), (1100, 1100)], [0.0, 100.0, 40.0, 200.0])
    d = Drive(kernel_cls, xt_machine(xt))
    d.vel[0], d.acc[0] = 10.0, 1000 * MM  # ratio 1
    cases = [
        ((250.0, 250.0), 0.5 * 0 + 0.25 * 100 + 0.25 * 40),  # inside ABC: 35
        # (700,700) in BCD: λ_D = (1400−1000)/(2200−1000) = 1/3, rest on BC's midpoint
        ((700.0, 700.0), (100 + 40 + 200) / 3),
        # outside: nearest hull point of (-500, 500) is (0, 500) on A–C: 20
        ((-500.0, 500.0), 20.0),
        # outside beyond A: the vertex A itself
        ((-300.0, -200.0), 0.0),
        # outside below B–... : (500, -700) projects to (500, 0) on A–B: 50
        ((500.0, -700.0), 50.0),
    ]
    for (x, y), want in cases:
        d.pos[0], d.pos[2] = x, y
        d.step()
        assert d.k.actual[1, XT] == pytest.approx(want, abs=1e-9), (x, y)


#: 000 p.92: the manual's 9 mode-3 test points (ax_1 varying fastest) and their
#: acc_pos_vel_pos corrections
P92_POINTS = [(float(x), float(y)) for y in (0, 1500, 3000) for x in (0, 1500, 3000)]
P92_VALUES = [60.0, 58.0, 55.0, 58.0, 63.0, 52.0, 55.0, 52.0, 50.0]


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_mode3_cocircular_tie_break(kernel_cls: type) -> None:
    """docs/design.md §12 "mode 3": the four corners of a grid cell lie on one circle, so
    both diagonals are Delaunay. The record order decides: candidate triangles are tried
    in lexicographic order of their record indices and the first that does not overlap an
    accepted one is kept. With the manual's order (ax_1 fastest) every cell is cut from
    its (ax_1 max, ax_2 min) corner to its (ax_1 min, ax_2 max) corner.

    At a cell centre the value is then the mean of those two corners: (750, 750) →
    (58 + 58)/2 = 58 (the other diagonal would give (60 + 63)/2 = 61.5); (2250, 750) →
    (55 + 63)/2 = 59 (not (58 + 52)/2 = 55). (1000, 1000) lies in the upper triangle
    of the first cell, (1500, 0)–(0, 1500)–(1500, 1500): λ = (1/3, 1/3, 1/3) → 59⅔."""
    d = Drive(kernel_cls, xt_machine(mode3(P92_POINTS, P92_VALUES)))
    d.vel[0], d.acc[0] = 10.0, 1000 * MM  # |a| = a_ref: ratio 1
    cases = [
        ((750.0, 750.0), 58.0),
        ((2250.0, 750.0), 59.0),
        ((750.0, 2250.0), (63 + 55) / 2),  # cell 3, 4, 6, 7: diagonal 4–6, not 3–7 (55)
        ((1000.0, 1000.0), (58 + 58 + 63) / 3),
    ]
    for _ in range(3):  # the same every time
        for (x, y), want in cases:
            d.pos[0], d.pos[2] = x, y
            d.step()
            assert d.k.actual[1, XT] == pytest.approx(want, abs=1e-9), (x, y)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_old_dialect(kernel_cls: type) -> None:
    xt = CrosstalkComp(
        dialect="old",
        master_dyn_ax_nr=1,
        acc_table=np.array([-1000.0, 0.0, 1000.0]),
        corr_table=np.array([-20.0, 0.0, 40.0]),
    )
    d = Drive(kernel_cls, xt_machine(xt))
    for a, want in ((500.0, 20.0), (-2000.0, -20.0), (-250.0, -5.0), (3000.0, 40.0)):
        d.acc[0] = a * MM
        d.vel[0] = 1.0
        d.step()
        assert d.k.actual[1, XT] == pytest.approx(want), a


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_filter_on_activation(kernel_cls: type) -> None:
    xt = mode1()
    xt.n_cycles = 4
    xt.manual_activation = True
    d = Drive(kernel_cls, xt_machine(xt))
    d.vel[0], d.acc[0] = 100.0, 10000 * MM
    d.step()
    assert not d.k.selected[1, XT] and d.k.actual[1, XT] == 0.0
    d.k.set_selected(1, CompKind.CROSSTALK, True)
    for k in range(1, 5):
        d.step()
        assert d.k.target[1, XT] == pytest.approx(25.0)  # end_offset: unfiltered
        assert d.k.actual[1, XT] == pytest.approx(25 * sin2(k, 4), abs=1e-9)


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_crosstalk_values_are_smoothed_while_active(kernel_cls: type) -> None:
    """Issue 45 #4, 000 p.83 ("these compensation values can be smoothed by using a
    sine-square filter", order n_cycles 4): with the compensation on and settled at
    25·0.2 = 5 (a = 2000 mm/s² of the reference 10000), the master's acceleration steps
    to 10000 mm/s²: the output follows 5 + 20·sin²(πk/8), k = 1…4, and does not jump to
    25 (before: only switching on and off was smoothed). A ramp of the target is the
    sum of the steps it makes: at k = 1…3 the target 5 + 5k gives the output
    5 + Σ_j 5·sin²(π(k − j)/8), j = 0…k−1."""
    xt = mode1()
    xt.n_cycles = 4
    d = Drive(kernel_cls, xt_machine(xt))
    d.vel[0], d.acc[0] = 100.0, 2000 * MM
    d.step(6)  # switched on at the first cycle, settled after 4
    assert d.k.actual[1, XT] == pytest.approx(5.0)
    d.acc[0] = 10000 * MM
    for k in range(1, 6):
        d.step()
        assert d.k.target[1, XT] == pytest.approx(25.0)
        assert d.k.actual[1, XT] == pytest.approx(5 + 20 * sin2(min(k, 4), 4), abs=1e-9), k
    d.acc[0] = 2000 * MM
    d.step(4)
    assert d.k.actual[1, XT] == pytest.approx(5.0)
    for k in range(1, 4):
        d.acc[0] = (2000 + 2000 * k) * MM  # the target 25·a/10000 = 5 + 5k
        d.step()
        want = 5 + sum(5 * sin2(k - j, 4) for j in range(k))
        assert d.k.actual[1, XT] == pytest.approx(want, abs=1e-9), k


# --------------------------------------------------------------------------- friction


def frict_machine(**kw: object) -> MachineConfig:
    # 000 p.70 table: in 0/316/333 µm/s, out 0/3722/3884
    f = FrictComp(vin=np.array([0.0, 316.0, 333.0]), out=np.array([0.0, 3722.0, 3884.0]), **kw)  # type: ignore[arg-type]
    return machine(axis(1, CompList("", 1, frict=f), frict_comp=True))


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_friction_value_and_hold(kernel_cls: type) -> None:
    d = Drive(kernel_cls, frict_machine())
    for v, want in (
        (3160.0, 3722.0),  # 316 µm/s
        (-3245.0, -(3722 + (324.5 - 316) / 17 * 162)),  # 324.5 µm/s, sign of v
        (100_000.0, 3884.0),  # above the table: last value held
        (0.0, 0.0),
    ):
        d.vel[0] = v
        d.step()
        assert d.k.effective[0, FRICT]  # no homing
        assert d.k.friction_current[0] == pytest.approx(want)
        assert d.k.actual[0, FRICT] == pytest.approx(want)
        assert d.k.total_offset[0] == 0.0  # a current, not a position offset


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_friction_scaling_and_mode(kernel_cls: type) -> None:
    d = Drive(kernel_cls, frict_machine(scaling_factor=10))  # 1 %
    d.vel[0] = 3160.0
    d.step()
    assert d.k.friction_current[0] == pytest.approx(37.22)
    d = Drive(kernel_cls, frict_machine(mode=0))
    d.vel[0] = 3160.0
    d.step()
    assert not d.k.effective[0, FRICT] and d.k.friction_current[0] == 0.0


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_friction_lookahead_decay(kernel_cls: type) -> None:
    d = Drive(kernel_cls, frict_machine(reversal_lookahead=4))
    d.vel[0] = 3160.0
    for r, w in ((-1, 1.0), (6, 1.0), (4, 4 / 5), (3, 3 / 5), (2, 2 / 5), (1, 1 / 5)):
        d.rev[0] = r
        d.step()
        assert d.k.friction_current[0] == pytest.approx(3722.0 * w), r


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_friction_position_delay_buildup(kernel_cls: type) -> None:
    d = Drive(kernel_cls, frict_machine(position_delay=30))
    d.vel[0] = 3160.0
    d.step()
    assert d.k.friction_current[0] == pytest.approx(3722.0)  # no reversal yet: no weight
    d.vel[0] = -3160.0  # reversal; then 10 units of path per cycle
    for k, w in ((1, 10 / 30), (2, 20 / 30), (3, 1.0), (4, 1.0)):
        d.pos[0] -= 10.0
        d.step()
        assert d.k.friction_current[0] == pytest.approx(-3722.0 * w), k


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_friction_builds_up_from_standstill(kernel_cls: type) -> None:
    """Issue 45 #3, 000 p.76 (P-COMP-00043 "distance over which the motor current is
    built up during start-up"): after a standstill, a start in the same direction (no
    reversal) builds the current up over position_delay 30 like a reversal does, 10
    units of path per cycle: 1/3, 2/3, then all of 3722 (before: all of it at once)."""
    d = Drive(kernel_cls, frict_machine(position_delay=30))
    d.vel[0] = 3160.0
    d.step()
    assert d.k.friction_current[0] == pytest.approx(3722.0)
    d.vel[0] = 0.0  # standstill: no current
    d.step()
    assert d.k.friction_current[0] == 0.0
    d.vel[0] = 3160.0  # the same direction again
    for k, w in ((1, 10 / 30), (2, 20 / 30), (3, 1.0), (4, 1.0)):
        d.pos[0] += 10.0
        d.step()
        assert d.k.friction_current[0] == pytest.approx(3722.0 * w), k


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_friction_delay_cycles(kernel_cls: type) -> None:
    d = Drive(kernel_cls, frict_machine(delay_cycles=3))
    values = [3160.0, 3160.0, -3160.0, 0.0, 3160.0, 3160.0, 3160.0, 0.0]
    expected = [3722.0 * (v > 0) - 3722.0 * (v < 0) for v in values]
    seen = []
    for v in values:
        d.vel[0] = v
        d.step()
        seen.append(d.k.friction_current[0])
        assert d.k.target[0, FRICT] == pytest.approx(expected[len(seen) - 1])
    assert seen == pytest.approx([0.0, 0.0, 0.0, *expected[:5]])


# --------------------------------------------------------------------------- general


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_unconfigured_axis_reads_zero(kernel_cls: type) -> None:
    d = Drive(kernel_cls, machine(axis(1), axis(5)))
    d.homed[:] = True
    d.vel[:] = 100.0
    d.pos[:] = 12345.0
    d.step(3)
    assert list(d.k.axis_numbers) == [1, 5] and d.k.slot_of(5) == 1
    for name in ("target", "actual", "delta", "friction_current", "total_offset"):
        assert not getattr(d.k, name).any()
    assert not d.k.effective.any() and not d.k.selected.any()


@pytest.mark.parametrize("kernel_cls", KERNELS)
def test_reload_ramps_to_new_table(kernel_cls: type) -> None:
    d = Drive(kernel_cls, cross_machine(n_cycles=4))
    d.homed[0] = True
    d.pos[0] = 2000.0
    d.step(10)
    assert d.k.actual[1, CROSS] == pytest.approx(20.0)
    new = cross_machine(n_cycles=4)
    new.axes[2].comp.cross.correction = np.array([0.0, 20.0, 60.0])  # 40 at 2000
    d.k.reload(new)
    for k in range(1, 5):
        d.step()
        assert d.k.actual[1, CROSS] == pytest.approx(40 - 20 * cos2(k, 4), abs=1e-9)
