"""The compensation kernel of a machine (docs/design.md §3, §5.1, §6, §13.3).

Same semantics as `ReferenceKernel` (the readable statement and the test oracle, in
tests/support/reference.py). The cycle itself is compiled (`kernel.step`: each
compensation's law in its module, orchestrated in the manual's order); this class is its
Python face: it interprets the lists once per load (`_setup`: which compensation each
axis has, its parameters and tables, packed into the arrays of `layout`), takes the
commands between cycles (COMP switches, TEMPC writes, reloads) and shows the state as
named arrays — views of the compiled cycle's arrays, updated in place, which the machine
keeps references to.

Column order (`COMP_ORDER`): BACKLASH, TEMP, CROSS, PLANE, LEAD, FRICT, CROSSTALK.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geo_server.jit import Packed
from geo_server.kernel import crosstalk, layout, sin2, step, temperature
from geo_server.kernel.common import (
    ALL_KINDS,
    BC,
    COLUMN,
    CROSS,
    CROSSTALK,
    FRICT,
    LEAD,
    PLANE,
    TEMP,
    filter_cycles,
    hold_columns,
    initial_direction,
    initial_selection,
    reload_changes,
)
from geo_server.kernel.friction import RING
from geo_server.kernel.layout import (
    ACT,
    CONF,
    DELTA,
    DIR,
    DRIVE,
    EFF,
    FIRST,
    HELD,
    HIST,
    HOMING_MAX,
    KIDX,
    NCYC,
    PATH,
    PEND,
    PENDING,
    PRE,
    PREV,
    RING_POS,
    SEL,
    TEMPC_ROWS,
    TGT,
    TOTAL,
    WOFF,
    XT_ORDER_MAX,
    KernelState,
)
from geo_server.kernel.tables import Packer
from geo_server.model import AxisConfig, CompKind, MachineConfig


@dataclass(slots=True)
class Rows:
    """Slots of the axes on which each compensation is configured: a valid list whose
    masters are axes of this machine (docs/design.md §6.0)."""

    cross: list[int] = field(default_factory=list)
    plane: list[int] = field(default_factory=list)
    lsec: list[int] = field(default_factory=list)
    frict: list[int] = field(default_factory=list)  # mode 3 (000 §4.5 p.77)
    lin: list[int] = field(default_factory=list)  # crosstalk new model, modes 1, 2 (000 §4.6)
    tri: list[int] = field(default_factory=list)  # crosstalk new model, mode 3
    old: list[int] = field(default_factory=list)  # crosstalk old model (001 §4.5, 003 §3.5)

    @classmethod
    def of(cls, axes: list[AxisConfig], slot: dict[int, int]) -> Rows:
        r = cls()
        for i, ax in enumerate(axes):
            comp = ax.comp
            if comp is None:
                continue
            c = comp.cross
            if c is not None and c.valid and c.master_ax_nr in slot and len(c.setpoint):
                r.cross.append(i)
            pl = comp.plane
            if (
                pl is not None
                and pl.valid
                and pl.master1_ax_nr in slot
                and pl.master2_ax_nr in slot
                and pl.table.size
            ):
                r.plane.append(i)
            ls = comp.lsec
            if ls is not None and ls.valid and len(ls.setpoint):
                r.lsec.append(i)
            fr = comp.frict
            if fr is not None and fr.valid and fr.mode == 3 and len(fr.vin):
                r.frict.append(i)
            x = comp.crosstalk
            if x is None or not x.valid or x.master_dyn_ax_nr not in slot:
                continue
            if x.dialect == "old":
                if len(x.acc_table):
                    r.old.append(i)
            elif np.atleast_2d(np.asarray(x.corrections, dtype=float)).shape[0]:
                if x.mode == 3:
                    if x.master_pos1_ax_nr in slot and x.master_pos2_ax_nr in slot:
                        r.tri.append(i)
                elif x.mode != 2 or x.master_pos1_ax_nr in slot:
                    r.lin.append(i)
        return r


class Kernel:
    """The compensation kernel of a whole machine (interface: see the module docstring)."""

    def __init__(self, cfg: MachineConfig, tempc: temperature.Bindings | None = None) -> None:
        #: the TEMPC parameter objects of the machine's dictionary (`write_tempc`)
        self.tempc = tempc or temperature.default_bindings()
        self.axis_numbers = np.array(sorted(cfg.axes), dtype=np.int64)
        n = len(self.axis_numbers)
        self.n = n
        self._slot = {int(a): i for i, a in enumerate(self.axis_numbers)}
        axes = [cfg.axes[int(a)] for a in self.axis_numbers]
        # the compiled cycle's arrays (`layout`), allocated once: the views below stay
        self.F7 = np.zeros((layout.NF7, n, 7))
        self.B7 = np.zeros((layout.NB7, n, 7), dtype=bool)
        self.I7 = np.zeros((layout.NI7, n, 7), dtype=np.int64)
        self.F1 = np.zeros((layout.NF1, n))
        self.B1 = np.zeros((layout.NB1, n), dtype=bool)
        self.P = np.zeros((layout.NP, n))
        self.IP = np.zeros((layout.NIP, n), dtype=np.int64)
        self.G = np.zeros(layout.NG, dtype=np.int64)
        self.ring = np.zeros((RING, n))  # the friction delay line, a row per cycle
        self.tab = np.zeros(1)  # the tables of the load (`_setup`)
        self.weights = np.zeros(1)  # the sin² weights of its filter lengths
        # outputs and state, as named views (updated in place)
        self.target = self.F7[TGT]
        self.actual = self.F7[ACT]
        self.delta = self.F7[DELTA]
        self.effective = self.B7[EFF]
        self.selected = self.B7[SEL]
        #: columns whose output is held at its last value (`hold`, COMP … NO_MOVE)
        self.held = self.B7[HELD]
        #: what besides the selection makes each column effective, as of the last step
        #: (homing, valid tables): the NC's 70435 check combines it with the selection
        self.preconditions = self.B7[PRE]
        #: compensations whose configuration is valid, per axis (`Rows`; TEMP needs
        #: none): with the axis list's selection, what `V.A.*_COMP_INIT` reports
        self.configured = self.B7[CONF]
        self.friction_current = self.actual[:, FRICT]  # the friction column, as a vector
        self.total_offset = self.F1[TOTAL]
        #: the drives' enables (`SIM::drive_enable`): cross and plane compensation of an
        #: axis are effective only with its drive enabled (000 §5.3 p.97 item 4)
        self.drive_enabled = self.B1[DRIVE]
        self.drive_enabled[:] = True
        self.selected[:] = [initial_selection(ax) for ax in axes]
        self.F1[DIR] = [initial_direction(ax.params.anwahl_losekomp) for ax in axes]
        self.F1[PATH] = np.inf  # no reversal yet: the post-reversal weight is 1
        for row, attr in enumerate(self.tempc.attrs):
            self.F1[TEMPC_ROWS[row]] = [getattr(ax.params, attr) for ax in axes]
        self.G[FIRST] = 1
        self._setup(cfg, idle=True)

    # ------------------------------------------------------------------ configuration

    def _setup(self, cfg: MachineConfig, idle: bool = False) -> None:
        """Interpret `cfg` for the compiled cycle (construction and reload): every
        compensation's parameters and tables, the homing each column needs, the sin²
        lengths (a running ramp goes on with the new length; `idle`: none runs)."""
        if sorted(cfg.axes) != [int(a) for a in self.axis_numbers]:
            raise ValueError("the set of axes cannot change on reload")
        self.cfg = cfg
        axes = [cfg.axes[int(a)] for a in self.axis_numbers]
        rows = Rows.of(axes, self._slot)
        self._configured(axes, rows)
        self.P.fill(0.0)
        self.IP.fill(0)
        tab = Packer()
        _axis_params(axes, self.P, self.IP)
        _cross(axes, rows.cross, self._slot, self.IP, tab)
        _plane(axes, rows.plane, self._slot, self.P, self.IP, tab)
        _lsec(axes, rows.lsec, self.P, self.IP, tab)
        _friction(axes, rows.frict, self.P, self.IP, tab)
        _crosstalk(axes, rows.lin + rows.tri + rows.old, self._slot, self.P, self.IP, tab)
        self.tab = tab.done()
        self.homing, self.homing_n = _homing(axes, rows, self._slot)
        ncyc = np.array([filter_cycles(ax) for ax in axes], dtype=np.int64).reshape(self.n, 7)
        ncyc[:, FRICT] = 0  # friction is not sin²-filtered: its output is the delay line
        # crosstalk keeps that many targets: a list's larger n_cycles deactivates the
        # compensation (70631), and the filter of its zero output never reads beyond
        np.minimum(ncyc[:, CROSSTALK], XT_ORDER_MAX, out=ncyc[:, CROSSTALK])
        self.weights, self.I7[WOFF] = sin2.weights(ncyc)
        self.I7[NCYC] = ncyc
        k = self.I7[KIDX]
        np.copyto(k, ncyc) if idle else np.minimum(k, ncyc, out=k)
        # crosstalk's filter goes on from its present output (a new order reads no
        # targets an older load left behind)
        self.F7[HIST:, :, CROSSTALK] = self.F7[ACT, :, CROSSTALK]
        self._state: Packed = tuple(
            KernelState(
                self.F7,
                self.B7,
                self.I7,
                self.F1,
                self.B1,
                self.P,
                self.IP,
                self.G,
                self.ring,
                self.tab,
                self.weights,
                self.homing,
                self.homing_n,
            )
        )

    def _configured(self, axes: list[AxisConfig], rows: Rows) -> None:
        c = self.configured
        c.fill(False)
        c[:, TEMP] = True
        for i, ax in enumerate(axes):
            c[i, BC] = ax.params.anwahl_losekomp != 0 and ax.params.lose != 0
        for col, slots in (
            (CROSS, rows.cross),
            (PLANE, rows.plane),
            (LEAD, rows.lsec),
            (FRICT, rows.frict),
            (CROSSTALK, rows.lin + rows.tri + rows.old),
        ):
            c[slots, col] = True

    # ------------------------------------------------------------------ interface

    def set_drive_enabled(self, slot: int, on: bool) -> None:
        """`SIM::drive_enable`: a precondition of cross and plane compensation (000 §5.3
        p.97 item 4), taken into the effective flags at the next step (a change is a
        step event, like homing)."""
        self.drive_enabled[slot] = bool(on)

    def slot_of(self, axis_number: int) -> int:
        return self._slot[int(axis_number)]

    def ramping(self, slot: int) -> bool:
        """True while a sin² ramp of the axis has cycles left or an event is pending."""
        i7 = self.I7
        return bool(np.any(i7[KIDX, slot] != i7[NCYC, slot]) or self.B7[PEND, slot].any())

    @property
    def previous(self) -> np.ndarray:
        """The actual values of the cycle before the last step ([n, 7])."""
        return self.F7[PREV]

    def at_rest(self) -> bool:
        """True when a step with unchanged inputs would change nothing but the delay
        line's write position: no sin² ramp under way, no step event pending, and the
        friction delay line holds only zeros (so every position in it is alike)."""
        return (
            not self.G[PENDING]
            and np.array_equal(self.I7[KIDX], self.I7[NCYC])
            and not np.count_nonzero(self.ring)
        )

    def skip(self, n: int) -> None:
        """`n` steps of a kernel `at_rest` with unchanged inputs (docs/design.md §13)."""
        self.G[RING_POS] = (int(self.G[RING_POS]) + n) % RING

    def set_selected(self, slot: int, kind: CompKind, on: bool) -> None:
        """COMP ON/OFF or a `TEMPC::activated` write (000 §5.1 p.94, §3.2 p.15)."""
        self.selected[slot, COLUMN[kind]] = bool(on)

    def hold(self, slot: int, kinds: CompKind) -> None:
        """`COMP … NO_MOVE` (000 §5.1 p.94): the selection has changed, but the offset it
        causes is only executed at the axis' next motion, so the output of these columns
        stays at its present value until `release`."""
        for c in hold_columns(kinds):
            self.held[slot, c] = True

    def release(self, slot: int, kinds: CompKind = ALL_KINDS) -> None:
        """The axis' next motion (or a switch without NO_MOVE): held columns ramp from
        their held output to the present target with their sin² length (a step event)."""
        for c in hold_columns(kinds):
            if self.held[slot, c]:
                self.held[slot, c] = False
                self._event(slot, c)

    def _event(self, slot: int, column: int) -> None:
        """A step event of the column at the next step (docs/design.md §3.5)."""
        self.B7[PEND, slot, column] = True
        self.G[PENDING] = 1

    @property
    def tempc_params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Live coefficient, offset_0, position_0 (views, 000 §3.2.3 objects 0x43–0x45)."""
        f = self.F1
        coef, off0, pos0 = (f[row] for row in TEMPC_ROWS)
        return coef, off0, pos0

    def write_tempc(self, slot: int, field: str, value: float) -> None:
        """TEMPC parameter write: a step event with temp_comp_n_cycles (docs/design.md
        §3.5)."""
        self.F1[TEMPC_ROWS[self.tempc.fields.index(field)], slot] = float(value)
        self._event(slot, TEMP)

    def reload(self, cfg: MachineConfig) -> None:
        """Swap tables at this cycle boundary: a step event on every column
        (docs/design.md §4.4).

        Selection and live TEMPC values follow the new lists only where the lists
        changed them (docs/design.md §12 "reload").
        """
        old = self.cfg
        self._setup(cfg)
        for i, a in enumerate(self.axis_numbers):
            selection, values = reload_changes(old.axes[int(a)], cfg.axes[int(a)], self.tempc.attrs)
            for c, on in selection:
                self.selected[i, c] = on
            for row, value in values:
                self.F1[TEMPC_ROWS[row], i] = value
        self.B7[PEND] = True
        self.G[PENDING] = 1

    # ------------------------------------------------------------------ the cycle

    def state(self) -> Packed:
        """What the compiled cycle takes of the kernel, a packed `KernelState` (`step.step`;
        made by each load of the lists, whose tables are new arrays: ask again after a
        reload)."""
        return self._state

    def step(
        self,
        cmd_pos: np.ndarray,
        cmd_vel: np.ndarray,
        cmd_acc: np.ndarray,
        homed: np.ndarray,
        reversal_in: np.ndarray,
    ) -> None:
        """One GEO cycle for every axis (docs/design.md §5.1 step 3; `step.step`) with the
        commands of this cycle and the cycles until a known reversal (< 0: none; a float
        count is truncated towards 0, as `int()` does)."""
        step.step(
            self.state(),
            _floats(cmd_pos),
            _floats(cmd_vel),
            _floats(cmd_acc),
            np.ascontiguousarray(homed, dtype=bool),
            _ints(reversal_in),
        )

    def steps(
        self,
        pos: np.ndarray,
        vel: np.ndarray,
        acc: np.ndarray,
        homed: np.ndarray,
        reversal_in: np.ndarray,
        total: np.ndarray,
    ) -> None:
        """A pass of b cycles ([b, n] commands, the homing flags unchanged): `step` for
        each row, every cycle's total offset into `total` ([b, n])."""
        step.steps(self.state(), pos, vel, acc, homed, reversal_in, total)


def _floats(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=np.float64)


def _ints(x: np.ndarray) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype.kind != "i":
        a = np.trunc(a)  # the reference's int(): −0.5 → 0
    return np.ascontiguousarray(a, dtype=np.int64)


# ---------------------------------------------------------------------- packing


def _axis_params(axes: list[AxisConfig], P: np.ndarray, IP: np.ndarray) -> None:
    """Backlash (000 §2), the start-up direction (P-AXIS-00021) and the modulo period."""
    for i, ax in enumerate(axes):
        p = ax.params
        P[layout.INIT_DIR, i] = initial_direction(p.anwahl_losekomp)
        P[layout.LOSE, i] = p.lose
        IP[layout.MODULO, i] = bool(p.modulo)
        P[layout.PERIOD, i] = p.modulo_period if p.modulo else 1.0


def _cross(
    axes: list[AxisConfig], rows: list[int], slot: dict[int, int], IP: np.ndarray, tab: Packer
) -> None:
    """Cross compensation (000 §4.2): the master and the table."""
    for i in rows:
        c = axes[i].comp.cross
        IP[layout.CR_M, i] = slot[c.master_ax_nr]
        IP[layout.CR_T, i] = tab.table(c.setpoint, c.correction)
        IP[layout.CR_N, i] = len(c.setpoint)


def _plane(
    axes: list[AxisConfig],
    rows: list[int],
    slot: dict[int, int],
    P: np.ndarray,
    IP: np.ndarray,
    tab: Packer,
) -> None:
    """Plane compensation (000 §4.3): the masters, the grid and the table."""
    for i in rows:
        pl = axes[i].comp.plane
        t = np.atleast_2d(np.asarray(pl.table, dtype=float))
        IP[layout.PL_M1, i] = slot[pl.master1_ax_nr]
        IP[layout.PL_M2, i] = slot[pl.master2_ax_nr]
        IP[layout.PL_T, i] = tab.add(t)
        IP[layout.PL_NI, i], IP[layout.PL_NJ, i] = t.shape[1], t.shape[0]
        P[layout.PL_START1, i] = pl.start_position_master1
        P[layout.PL_START2, i] = pl.start_position_master2
        P[layout.PL_INT1, i] = pl.interval1
        P[layout.PL_INT2, i] = pl.interval2


def _lsec(
    axes: list[AxisConfig], rows: list[int], P: np.ndarray, IP: np.ndarray, tab: Packer
) -> None:
    """LSEC (000 §4.4): the tables per direction, the modulo wrap."""
    for i in rows:
        ls = axes[i].comp.lsec
        p = axes[i].params
        x = np.asarray(ls.setpoint, dtype=float)
        IP[layout.LS_POS, i] = tab.table(x, ls.pos)
        IP[layout.LS_NEG, i] = tab.table(x, ls.neg) if ls.bilateral else IP[layout.LS_POS, i]
        IP[layout.LS_N, i] = len(x)
        period = p.modulo_period if p.modulo else float(x[-1] - x[0])
        IP[layout.LS_WRAP, i] = bool(ls.modulo and period > 0)
        IP[layout.LS_CMD, i] = bool(ls.set_pos_without_comp)
        P[layout.LS_X0, i] = x[0]
        P[layout.LS_PER, i] = period


def _friction(
    axes: list[AxisConfig], rows: list[int], P: np.ndarray, IP: np.ndarray, tab: Packer
) -> None:
    """Friction (000 §4.5, mode 3): the table over |v|, the weights, the delay."""
    for i in rows:
        fr = axes[i].comp.frict
        IP[layout.FR_T, i] = tab.table(fr.vin, fr.out)
        IP[layout.FR_N, i] = len(fr.vin)
        IP[layout.FR_DELAY, i] = int(fr.delay_cycles)
        IP[layout.FR_LOOK, i] = int(fr.reversal_lookahead)
        P[layout.FR_SCALE, i] = fr.scaling_factor / 1000.0
        P[layout.FR_PD, i] = float(fr.position_delay)


def _crosstalk(
    axes: list[AxisConfig],
    rows: list[int],
    slot: dict[int, int],
    P: np.ndarray,
    IP: np.ndarray,
    tab: Packer,
) -> None:
    """Crosstalk (000 §4.6, old model 001 §4.5): the masters and `crosstalk.pack`."""
    for i in rows:
        x = axes[i].comp.crosstalk
        packed = crosstalk.pack(x, tab)
        for row, value in zip(
            (
                layout.XT_KIND,
                layout.XT_T,
                layout.XT_N,
                layout.XT_TRI,
                layout.XT_NTRI,
                layout.XT_EDGE,
                layout.XT_NEDGE,
            ),
            packed,
            strict=True,
        ):
            IP[row, i] = value
        IP[layout.XT_DYN, i] = slot[x.master_dyn_ax_nr]
        IP[layout.XT_P1, i] = slot.get(x.master_pos1_ax_nr, 0)
        IP[layout.XT_P2, i] = slot.get(x.master_pos2_ax_nr, 0)
        IP[layout.XT_VELDEP, i] = bool(x.velocity_dependent)
        P[layout.XT_INV_ACC, i] = 1.0 / abs(x.acceleration) if x.acceleration else 0.0
        P[layout.XT_INV_DEC, i] = 1.0 / abs(x.deceleration) if x.deceleration else 0.0


def _homing(
    axes: list[AxisConfig], rows: Rows, slot: dict[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Which axes must be homed for each column of each axis to act (docs/design.md
    §6.0, §6.8): [n, 7, HOMING_MAX] slots and [n, 7] how many — temperature needs the axis
    homed (000 §3.2 p.17), LSEC too (000 §5.3 item 2), cross its master (000 p.29), plane
    both masters (000 §5.3 item 3); backlash (000 p.10), friction and crosstalk none.
    Whether a column is configured at all is `B7[CONF]` (`Kernel._configured`)."""
    n = len(axes)
    needs = np.zeros((n, 7, HOMING_MAX), dtype=np.int64)
    count = np.zeros((n, 7), dtype=np.int64)

    def need(i: int, c: int, *slots: int) -> None:
        needs[i, c, : len(slots)] = slots
        count[i, c] = len(slots)

    for i in range(n):
        need(i, TEMP, i)
        need(i, LEAD, i)
    for i in rows.cross:
        need(i, CROSS, slot[axes[i].comp.cross.master_ax_nr])
    for i in rows.plane:
        plane = axes[i].comp.plane
        need(i, PLANE, slot[plane.master1_ax_nr], slot[plane.master2_ax_nr])
    return needs, count
