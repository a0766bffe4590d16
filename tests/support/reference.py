"""Reference compensation kernel: per axis, plain Python floats, one rule at a time.

This is the readable statement of docs/design.md §3 and §6 and the oracle the fast
kernel (`geo_server.kernel.kernel.Kernel`) is tested against. It has the same interface.
It is a test oracle, not product (issue 33): written from the manuals, it shares no code
with the kernel but the list parser's model (`geo_server.model`) and the Delaunay
triangulation of crosstalk mode 3 (`geo_server.kernel.triangulation`); the configuration
rules the kernel keeps in `geo_server.kernel.common` are stated here once more.
Manual references: 000 = TF5200 axis compensation EN v1.51 (PDF page numbers).

Per cycle and axis (docs/design.md §5.1 step 3 order: temperature, cross, plane,
crosstalk, then LSEC, backlash, friction — backlash only depends on the direction, so its
place does not matter):

1. direction: sign of the command velocity, the last one held at standstill;
2. effective flags (selected and preconditions);
3. unfiltered targets (0 when not effective);
4. step events (effective flag changed, reversal for BC / bilateral LSEC, TEMPC write,
   reload) and the sin² filter (`sin2.py`);
5. LSEC after cross and plane, because its lookup position includes their outputs;
6. friction current with the reversal weightings and the output delay.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np

from geo_server.kernel.triangulation import Triangulation, evaluate, triangulate
from geo_server.model import AxisConfig, CompKind, MachineConfig
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM

#: Column of every compensation in the `[n, 7]` arrays (the kernel's interface).
COMP_ORDER: tuple[CompKind, ...] = (
    CompKind.BACKLASH,
    CompKind.TEMP,
    CompKind.CROSS,
    CompKind.PLANE,
    CompKind.LEAD,
    CompKind.FRICT,
    CompKind.CROSSTALK,
)
BC, TEMP, CROSS, PLANE, LEAD, FRICT, CROSSTALK = range(7)
ALL_KINDS = CompKind(sum(COMP_ORDER))  # COMP OFF_ALL (000 §5.1 p.94)
COLUMN: dict[CompKind, int] = {kind: i for i, kind in enumerate(COMP_ORDER)}
#: The TEMPC parameters writable as objects (000 §3.2.3 p.22: coefficient 0x43, offset_0
#: 0x44, position_0 0x45) and the axis-list entries they start from (P-AXIS-00274,
#: -00273, -00272).
TEMPC_FIELDS = ("coefficient", "offset_0", "position_0")
TEMPC_ATTRS = ("temp_comp_coefficient", "temp_comp_offset_0", "temp_comp_position_0")


def hold_columns(kinds: CompKind) -> list[int]:
    """COMP … NO_MOVE holds position offsets only (000 §5.1 p.94): not friction."""
    return [COLUMN[k] for k in COMP_ORDER if kinds & k and k is not CompKind.FRICT]


def initial_direction(anwahl_losekomp: int) -> float:
    """P-AXIS-00021 (000 §2.3.2): 2 = last motion negative, else positive."""
    return -1.0 if anwahl_losekomp == 2 else 1.0


def initial_selection(ax: AxisConfig) -> list[bool]:
    """Selected at start-up: by the axis parameter, unless the list asks for manual
    activation (000 §3.2 p.17, §2.3.2, §4.2–4.6, §5.1 p.94)."""
    p, comp = ax.params, ax.comp

    def manual(part: object) -> bool:
        return bool(part is not None and getattr(part, "manual_activation", False))

    return [
        p.anwahl_losekomp != 0,
        p.temp_comp and not p.temp_comp_manual_activation,
        p.crosscomp and not manual(comp.cross if comp else None),
        p.crosscomp2 and not manual(comp.plane if comp else None),
        p.ssfk and not manual(comp.lsec if comp else None),
        p.frict_comp,
        p.crosstalk and not manual(comp.crosstalk if comp else None),
    ]


def filter_cycles(ax: AxisConfig) -> list[int]:
    """sin² length per column (docs/design.md §3.4): backlash and LSEC n_backlash_cyc
    (P-AXIS-00243), TEMP temp_comp_n_cycles (P-AXIS-00275), cross/plane/crosstalk their
    list's n_cycles, friction 1; N ≤ 1 is a jump."""
    p, comp = ax.params, ax.comp

    def n_of(part: object) -> int:
        return int(getattr(part, "n_cycles", 0)) if part is not None else 0

    ns = [
        p.n_backlash_cyc,
        p.temp_comp_n_cycles,
        n_of(comp.cross if comp else None),
        n_of(comp.plane if comp else None),
        p.n_backlash_cyc,
        1,
        n_of(comp.crosstalk if comp else None),
    ]
    return [max(1, int(n)) for n in ns]


def reload_changes(
    old: AxisConfig, new: AxisConfig
) -> tuple[list[tuple[int, bool]], list[tuple[int, float]]]:
    """A reload re-initialises only what the new lists changed (docs/design.md §12)."""
    so, sn = initial_selection(old), initial_selection(new)
    po, pn = old.params, new.params
    return (
        [(c, sn[c]) for c in range(7) if so[c] != sn[c]],
        [
            (row, float(getattr(pn, a)))
            for row, a in enumerate(TEMPC_ATTRS)
            if getattr(po, a) != getattr(pn, a)
        ],
    )


def interp(x: Sequence[float], y: Sequence[float], q: float) -> float:
    """Linear interpolation between table points, edges held (docs/design.md §6.0)."""
    n = len(x)
    if n == 1:
        return float(y[0])
    q = min(max(q, x[0]), x[-1])
    i = bisect.bisect_right(x, q) - 1
    i = min(max(i, 0), n - 2)
    t = (q - x[i]) / (x[i + 1] - x[i])
    return y[i] + t * (y[i + 1] - y[i])


def wrap(q: float, start: float, period: float) -> float:
    """Modulo position in [start, start + period)."""
    return start + (q - start) % period


def _sign(v: float) -> float:
    return 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)


class _Axis:
    """Static configuration of one axis, already resolved to slots and Python lists."""

    def __init__(self, ax: AxisConfig, slot_of: dict[int, int]) -> None:
        p, comp = ax.params, ax.comp
        self.p = p
        self.init_dir = initial_direction(p.anwahl_losekomp)
        self.n_cycles = filter_cycles(ax)
        self.modulo = p.modulo
        self.period = p.modulo_period
        self.cross = comp.cross if comp else None
        self.cross_ok = False
        if self.cross is not None:
            c = self.cross
            self.cross_ok = c.valid and c.master_ax_nr in slot_of and len(c.setpoint) > 0
            self.cross_master = slot_of.get(c.master_ax_nr, 0)
            self.cross_x = [float(v) for v in c.setpoint]
            self.cross_y = [float(v) for v in c.correction]
        self.plane = comp.plane if comp else None
        self.plane_ok = False
        if self.plane is not None:
            pl = self.plane
            self.plane_ok = (
                pl.valid
                and pl.master1_ax_nr in slot_of
                and pl.master2_ax_nr in slot_of
                and pl.table.size > 0
            )
            self.plane_m1 = slot_of.get(pl.master1_ax_nr, 0)
            self.plane_m2 = slot_of.get(pl.master2_ax_nr, 0)
            self.plane_t = [[float(v) for v in row] for row in np.atleast_2d(pl.table)]
        self.lsec = comp.lsec if comp else None
        self.lsec_ok = False
        if self.lsec is not None:
            ls = self.lsec
            self.lsec_ok = ls.valid and len(ls.setpoint) > 0
            self.lsec_x = [float(v) for v in ls.setpoint]
            self.lsec_pos = [float(v) for v in ls.pos]
            self.lsec_neg = [float(v) for v in ls.neg] if ls.bilateral else self.lsec_pos
            span = self.lsec_x[-1] - self.lsec_x[0] if self.lsec_x else 0.0
            # the table's modulo period: the axis period when the axis is modulo, else the
            # distance between first and last point (000 §4.4: they are one period apart)
            self.lsec_period = p.modulo_period if p.modulo else span
        self.frict = comp.frict if comp else None
        self.frict_ok = False
        if self.frict is not None:
            f = self.frict
            self.frict_ok = f.valid and f.mode == 3 and len(f.vin) > 0
            self.frict_x = [float(v) for v in f.vin]
            self.frict_y = [float(v) for v in f.out]
        self.xt = comp.crosstalk if comp else None
        self.xt_ok = False
        if self.xt is not None:
            x = self.xt
            self.xt_ok = x.valid and x.master_dyn_ax_nr in slot_of
            self.xt_dyn = slot_of.get(x.master_dyn_ax_nr, 0)
            self.xt_p1 = slot_of.get(x.master_pos1_ax_nr, 0)
            self.xt_p2 = slot_of.get(x.master_pos2_ax_nr, 0)
            if x.dialect == "old":
                self.xt_ok = self.xt_ok and len(x.acc_table) > 0
                order = sorted(range(len(x.acc_table)), key=lambda i: x.acc_table[i])
                self.xt_acc = [float(x.acc_table[i]) for i in order]
                self.xt_corr = [float(x.corr_table[i]) for i in order]
            else:
                corr = np.atleast_2d(np.asarray(x.corrections, dtype=float))
                self.xt_ok = self.xt_ok and corr.shape[0] > 0
                if x.mode == 2:
                    self.xt_ok = self.xt_ok and x.master_pos1_ax_nr in slot_of
                if x.mode == 3:
                    self.xt_ok = (
                        self.xt_ok
                        and x.master_pos1_ax_nr in slot_of
                        and x.master_pos2_ax_nr in slot_of
                    )
                self.xt_ax1 = [float(v) for v in x.ax_1] or [0.0]
                self.xt_ax2 = [float(v) for v in x.ax_2] or [0.0] * len(self.xt_ax1)
                self.xt_cols = [[float(v) for v in corr[:, c]] for c in range(4)]
                order = sorted(range(len(self.xt_ax1)), key=lambda i: self.xt_ax1[i])
                self.xt_sorted_ax1 = [self.xt_ax1[i] for i in order]
                self.xt_sorted_cols = [[col[i] for i in order] for col in self.xt_cols]
                self.xt_tri: Triangulation | None = None
                if x.mode == 3 and self.xt_ok:
                    n = min(len(self.xt_ax1), len(self.xt_ax2), corr.shape[0])
                    self.xt_tri = triangulate(
                        tuple((self.xt_ax1[i], self.xt_ax2[i]) for i in range(n))
                    )
                self.xt_inv_acc = 1.0 / abs(x.acceleration) if x.acceleration else 0.0
                self.xt_inv_dec = 1.0 / abs(x.deceleration) if x.deceleration else 0.0


class ReferenceKernel:
    """Per-axis pure-Python compensation kernel (the oracle). Interface as `Kernel`."""

    def __init__(self, cfg: MachineConfig) -> None:
        self.axis_numbers = np.array(sorted(cfg.axes), dtype=np.int64)
        n = len(self.axis_numbers)
        self.n = n
        self._slot = {int(a): i for i, a in enumerate(self.axis_numbers)}
        self._setup(cfg)
        self.selected = np.array([initial_selection(cfg.axes[int(a)]) for a in self.axis_numbers])
        self.selected = self.selected.reshape(n, 7).astype(bool)
        self.target = np.zeros((n, 7))
        self.actual = np.zeros((n, 7))
        self.delta = np.zeros((n, 7))
        self.effective = np.zeros((n, 7), dtype=bool)
        self.friction_current = np.zeros(n)
        self.total_offset = np.zeros(n)
        self._dir = [ax.init_dir for ax in self._axes]
        self._jump = [[0.0] * 7 for _ in range(n)]
        self._k = [list(map(float, ax.n_cycles)) for ax in self._axes]
        self._event = [[False] * 7 for _ in range(n)]
        self.held = np.zeros((n, 7), dtype=bool)
        #: what besides the selection makes each column effective, as of the last step
        self.preconditions = np.zeros((n, 7), dtype=bool)
        #: the drives' enables: a precondition of cross and plane (000 §5.3 p.97 item 4)
        self.drive_enabled = np.ones(n, dtype=bool)
        self._tempc = [[float(getattr(ax.p, a)) for a in TEMPC_ATTRS] for ax in self._axes]
        self._path = [math.inf] * n  # path travelled since the last reversal (friction)
        self._hist: list[list[float]] = [[] for _ in range(n)]  # crosstalk's last targets
        self._prev_pos: list[float] | None = None
        self._ring = [[0.0] * 249 for _ in range(n)]  # friction delay line (delay < 249)
        self._ring_pos = 0

    def _setup(self, cfg: MachineConfig) -> None:
        if sorted(cfg.axes) != [int(a) for a in self.axis_numbers]:
            raise ValueError("the set of axes cannot change on reload")
        self.cfg = cfg
        self._axes = [_Axis(cfg.axes[int(a)], self._slot) for a in self.axis_numbers]

    # ------------------------------------------------------------------ interface

    def slot_of(self, axis_number: int) -> int:
        return self._slot[int(axis_number)]

    def set_selected(self, slot: int, kind: CompKind, on: bool) -> None:
        """COMP ON/OFF or a `TEMPC::activated` write (000 §5.1, §3.2)."""
        self.selected[slot, COLUMN[kind]] = bool(on)

    def set_drive_enabled(self, slot: int, on: bool) -> None:
        """`SIM::drive_enable` (000 §5.3 p.97 item 4: cross and plane need it)."""
        self.drive_enabled[slot] = bool(on)

    def hold(self, slot: int, kinds: CompKind) -> None:
        """`COMP … NO_MOVE` (000 §5.1 p.94): the offset of the switch is only executed at
        the axis' next motion; until then these columns keep their output."""
        for c in hold_columns(kinds):
            self.held[slot, c] = True

    def release(self, slot: int, kinds: CompKind = ALL_KINDS) -> None:
        """The axis' next motion: every held column ramps from its held output to its
        target (a step event)."""
        for c in hold_columns(kinds):
            if self.held[slot, c]:
                self.held[slot, c] = False
                self._event[slot][c] = True

    @property
    def tempc_params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Live TEMPC coefficient, offset_0, position_0 (000 §3.2.3 objects 0x43–0x45)."""
        t = np.array(self._tempc, dtype=float).reshape(self.n, 3)
        return t[:, 0].copy(), t[:, 1].copy(), t[:, 2].copy()

    def write_tempc(self, slot: int, field: str, value: float) -> None:
        """A TEMPC parameter write: a step event with temp_comp_n_cycles
        (docs/design.md §3.5)."""
        self._tempc[slot][TEMPC_FIELDS.index(field)] = float(value)
        self._event[slot][TEMP] = True

    def reload(self, cfg: MachineConfig) -> None:
        """Swap the tables at this cycle boundary; every column gets a step event, so an
        active compensation ramps from its current output to the new value
        (docs/design.md §4.4).

        Selection and live TEMPC values are re-initialised from the new parameters only
        where the new lists changed them, so a COMP OFF or a live TEMPC write survives a
        reload that does not touch it.
        """
        old = self.cfg
        self._setup(cfg)
        for i, a in enumerate(self.axis_numbers):
            selection, values = reload_changes(old.axes[int(a)], cfg.axes[int(a)])
            for c, on in selection:
                self.selected[i, c] = on
            for f, value in values:
                self._tempc[i][f] = value
            self._event[i] = [True] * 7
            # crosstalk's filter goes on from its present output
            self._hist[i] = [float(self.actual[i, CROSSTALK])] * 20

    # ------------------------------------------------------------------ the cycle

    def step(
        self,
        cmd_pos: np.ndarray,
        cmd_vel: np.ndarray,
        cmd_acc: np.ndarray,
        homed: np.ndarray,
        reversal_in: np.ndarray,
    ) -> None:
        pos = [float(v) for v in cmd_pos]
        vel = [float(v) for v in cmd_vel]
        acc = [float(v) for v in cmd_acc]
        hom = [bool(v) for v in homed]
        rev_in = [int(v) for v in reversal_in]
        prev_pos = self._prev_pos if self._prev_pos is not None else pos
        for i, ax in enumerate(self._axes):
            self._step_axis(i, ax, pos, vel, acc, hom, rev_in[i], prev_pos[i])
        self._prev_pos = pos
        self._ring_pos = (self._ring_pos + 1) % len(self._ring[0])

    def _step_axis(
        self,
        i: int,
        ax: _Axis,
        pos: list[float],
        vel: list[float],
        acc: list[float],
        hom: list[bool],
        rev_in: int,
        prev_pos: float,
    ) -> None:
        p = ax.p
        sel = [bool(v) for v in self.selected[i]]
        prev_eff = [bool(v) for v in self.effective[i]]
        prev_out = [float(v) for v in self.actual[i]]

        # 1. direction (docs/design.md §3.6): sign of the command velocity, held at standstill
        s = _sign(vel[i])
        reversal = s != 0.0 and s != self._dir[i]
        if s != 0.0:
            self._dir[i] = s
        d = self._dir[i]

        # 2. effective = selected and preconditions (docs/design.md §6.8)
        pre = [False] * 7
        # backlash: active from start-up, no homing (000 §2.2 p.10)
        pre[BC] = p.anwahl_losekomp != 0 and p.lose != 0
        # temperature: homed (000 §3.2 p.17, P-AXIS-00482)
        pre[TEMP] = hom[i]
        # cross: table valid and master referenced (000 §4.2 p.29)
        # and the axis' drive enabled (000 §5.3 p.97 item 4)
        drive = bool(self.drive_enabled[i])
        pre[CROSS] = ax.cross_ok and hom[ax.cross_master] and drive
        # plane: both masters referenced (000 §5.3 p.97 item 3), the drive enabled (item 4)
        pre[PLANE] = ax.plane_ok and hom[ax.plane_m1] and hom[ax.plane_m2] and drive
        # LSEC: axis referenced (000 §5.3 p.97 item 2)
        pre[LEAD] = ax.lsec_ok and hom[i]
        # friction: P-AXIS-00522 and mode 3, no homing (000 §4.5 p.77)
        pre[FRICT] = ax.frict_ok
        # crosstalk: list provided, no homing (000 §4.6 p.82)
        pre[CROSSTALK] = ax.xt_ok
        eff = [sel[c] and pre[c] for c in range(7)]

        # 3. unfiltered targets
        tgt = [0.0] * 7
        if eff[BC]:
            # 0 while moving in the start-up direction, d·lose after a reversal
            # (docs/design.md §6.1)
            tgt[BC] = 0.0 if d == ax.init_dir else d * p.lose
        if eff[TEMP]:
            coef, off0, pos0 = self._tempc[i]
            s_t = wrap(pos[i], 0.0, ax.period) if ax.modulo else pos[i]
            # Δs = offset_0 + coefficient[µm/m]·1e-6·(s − s0)  (000 §3.1, p.15)
            tgt[TEMP] = off0 + coef * 1e-6 * (s_t - pos0)
        if eff[CROSS]:
            m = ax.cross_master
            q = pos[m]
            mp = self._axes[m].p
            if mp.modulo:  # modulo master: the table wraps with the master (000 p.31)
                q = wrap(q, 0.0, mp.modulo_period)
            tgt[CROSS] = interp(ax.cross_x, ax.cross_y, q)
        if eff[PLANE]:
            tgt[PLANE] = self._plane(ax, pos)
        if eff[CROSSTALK]:
            tgt[CROSSTALK] = self._crosstalk(ax, pos, vel, acc)

        # 4. events and sin² filter for BC, TEMP, CROSS, PLANE, CROSSTALK
        ev = self._event[i]
        for c in (BC, TEMP, CROSS, PLANE, CROSSTALK):
            if eff[c] != prev_eff[c]:
                ev[c] = True
        if reversal and eff[BC]:
            ev[BC] = True  # reversal: backlash spread over n_backlash_cyc (P-AXIS-00243)
        out = [0.0] * 7
        held = [bool(v) for v in self.held[i]]
        for c in (BC, TEMP, CROSS, PLANE, CROSSTALK):
            if c == CROSSTALK:  # (held: the filter sees the held output)
                seen = prev_out[c] if held[c] else tgt[c]
                out[c] = self._smooth(i, ax.n_cycles[c], seen)
            else:
                out[c] = self._filter(i, c, ax.n_cycles[c], tgt[c], prev_out[c], ev[c])
            if held[c]:  # COMP … NO_MOVE: the offset waits for the axis' next motion
                out[c] = prev_out[c]

        # 5. LSEC (000 §4.4): lookup at command + cross + plane unless set_pos_without_comp
        if eff[LEAD]:
            ls = ax.lsec
            q = pos[i] if ls.set_pos_without_comp else pos[i] + out[CROSS] + out[PLANE]
            if ls.modulo and ax.lsec_period > 0:
                q = wrap(q, ax.lsec_x[0], ax.lsec_period)
            table = ax.lsec_neg if (ls.bilateral and d < 0) else ax.lsec_pos
            # the table holds measured errors Δs = s_actual − s_programmed: apply −Δs
            tgt[LEAD] = -interp(ax.lsec_x, table, q)
            if reversal and ls.bilateral:
                ev[LEAD] = True
        if eff[LEAD] != prev_eff[LEAD]:
            ev[LEAD] = True
        out[LEAD] = self._filter(i, LEAD, ax.n_cycles[LEAD], tgt[LEAD], prev_out[LEAD], ev[LEAD])
        if held[LEAD]:
            out[LEAD] = prev_out[LEAD]

        # 6. friction (000 §4.5 p.64–79)
        cur = 0.0
        if eff[FRICT]:
            f = ax.frict
            v = vel[i]
            base = (
                _sign(v)
                * (f.scaling_factor / 1000.0)
                * interp(ax.frict_x, ax.frict_y, abs(v) / UNITS_PER_UM)
            )
            tgt[FRICT] = base
            # before the zero crossing: weighted by time (reversal_lookahead cycles)
            w_pre = 1.0
            look = f.reversal_lookahead
            if look > 0 and 0 <= rev_in <= look:
                w_pre = rev_in / (look + 1)
            cur = base * w_pre
        # after the zero crossing, and from standstill ("built up during start-up", 000
        # p.76): weighted by the path since the reversal or the standstill
        if reversal or vel[i] == 0.0:
            self._path[i] = 0.0
        self._path[i] += abs(pos[i] - prev_pos)
        if eff[FRICT] and ax.frict.position_delay > 0:
            cur *= min(1.0, self._path[i] / ax.frict.position_delay)
        ring = self._ring[i]
        ring[self._ring_pos] = cur
        delay = ax.frict.delay_cycles if eff[FRICT] else 0
        out[FRICT] = ring[(self._ring_pos - delay) % len(ring)] if eff[FRICT] else 0.0

        for c in range(7):
            ev[c] = False
            self.delta[i, c] = out[c] - prev_out[c]
            self.actual[i, c] = out[c]
            self.target[i, c] = tgt[c]
            self.effective[i, c] = eff[c]
            self.preconditions[i, c] = pre[c]
        self.friction_current[i] = out[FRICT]
        self.total_offset[i] = (
            out[BC] + out[TEMP] + out[CROSS] + out[PLANE] + out[LEAD] + out[CROSSTALK]
        )

    def _filter(self, i: int, c: int, n: int, target: float, prev: float, event: bool) -> float:
        """sin² filter (docs/design.md §3.4): out_k = target_k − J·cos²(π·k/(2N))."""
        if event:
            self._jump[i][c] = target - prev
            self._k[i][c] = 0.0
        self._k[i][c] = min(self._k[i][c] + 1.0, float(n))
        k = self._k[i][c]
        return target - self._jump[i][c] * math.cos(math.pi * k / (2 * n)) ** 2

    def _smooth(self, i: int, n: int, target: float) -> float:
        """Crosstalk's values through a sin² filter of order n (000 p.83): the last n
        targets (none before the first cycle: 0; the held output while the column is
        held) weighed by the steps of the sin² ramp, cos²(πj/(2n)) − cos²(π(j+1)/(2n))."""
        n = min(n, 20)  # (a larger n_cycles deactivates it: 70631)
        hist = self._hist[i]
        hist.insert(0, target)
        del hist[max(n, 1) :]
        seen = hist + [0.0] * (n - len(hist))
        if n <= 1 or all(h == target for h in seen):  # settled: exactly the target
            return target
        w = [math.cos(math.pi * j / (2 * n)) ** 2 for j in range(n + 1)]
        return sum((w[j] - w[j + 1]) * seen[j] for j in range(n))

    def _plane(self, ax: _Axis, pos: list[float]) -> float:
        """Bilinear over table[j][i], j = master 2, i = master 1; clamp outside
        (000 §4.3 p.38–43)."""
        pl = ax.plane
        t = ax.plane_t
        last2, last1 = len(t) - 1, len(t[0]) - 1
        q1, q2 = pos[ax.plane_m1], pos[ax.plane_m2]
        p1, p2 = self._axes[ax.plane_m1].p, self._axes[ax.plane_m2].p
        if p1.modulo:
            q1 = wrap(q1, 0.0, p1.modulo_period)
        if p2.modulo:
            q2 = wrap(q2, 0.0, p2.modulo_period)
        u = min(max((q1 - pl.start_position_master1) / pl.interval1, 0.0), float(last1))
        v = min(max((q2 - pl.start_position_master2) / pl.interval2, 0.0), float(last2))
        i0 = min(math.floor(u), max(last1 - 1, 0))
        j0 = min(math.floor(v), max(last2 - 1, 0))
        fu, fv = u - i0, v - j0
        i1 = i0 + (1 if last1 > 0 else 0)
        j1 = j0 + (1 if last2 > 0 else 0)
        return (
            (1.0 - fu) * (1.0 - fv) * t[j0][i0]
            + fu * (1.0 - fv) * t[j0][i1]
            + (1.0 - fu) * fv * t[j1][i0]
            + fu * fv * t[j1][i1]
        )

    def _crosstalk(self, ax: _Axis, pos: list[float], vel: list[float], acc: list[float]) -> float:
        """Slave offset from the master's acceleration (000 §4.6 p.80–93)."""
        x = ax.xt
        a = acc[ax.xt_dyn] / UNITS_PER_MM  # mm/s² (rotary °/s²)
        v = vel[ax.xt_dyn]
        if x.dialect == "old":
            # old model (001 §4.5, 003 §3.5): table over the signed acceleration
            return interp(ax.xt_acc, ax.xt_corr, a)
        # accelerating when |v| grows or the axis starts from rest: a·v ≥ 0
        accelerating = a * v >= 0.0
        neg = v < 0.0 or (v == 0.0 and a < 0.0)
        col = (0 if accelerating else 2) + (1 if (neg and x.velocity_dependent) else 0)
        inv = ax.xt_inv_acc if accelerating else ax.xt_inv_dec
        ratio = min(abs(a) * inv, 1.0)  # clamped beyond a_ref (docs/design.md §12)
        if x.mode == 1:
            c_ref = ax.xt_cols[col][0]
        elif x.mode == 2:
            c_ref = interp(ax.xt_sorted_ax1, ax.xt_sorted_cols[col], pos[ax.xt_p1])
        else:
            assert ax.xt_tri is not None
            c_ref = evaluate(ax.xt_tri, ax.xt_cols[col], pos[ax.xt_p1], pos[ax.xt_p2])
        return c_ref * ratio
