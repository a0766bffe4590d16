"""The volumetric compensations of one machine in the GEO cycle (004 §4, docs/volumetric.md §5).

Per compensation: whether it is wanted (automatic activation, `#VOLCOMP ON/OFF`, the
enable/disable CNC objects), whether it can act (available, every axis referenced and
its drive enabled, s_limit defined), the ramp of `filter_steps` (004 p.22), the
`CFACT_*` weights of the activation (004 p.21), `negate`/`set_to_zero` (004 p.16) and
the `s_limit` watch (004 p.14). `offset` is what the drives get added, per machine axis
slot, in increments. The error case and the program end of 004 p.24 (an axis in error
state marks the compensation incorrect; M30 reduces one linked to the channel):
docs/volumetric.md §5.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from geo_server.jit import Packed
from geo_server.listfile.checks import EMU_VOLC_ERROR
from geo_server.model import AxisParams
from geo_server.volcomp import step as vs
from geo_server.volcomp.config import VolComp
from geo_server.volcomp.evaluator import Evaluator

#: error reported when the volumetric compensation cannot act (the checks' ID)
VOLC_ERROR = EMU_VOLC_ERROR


def _float_row(index: int) -> property:
    def get(self: CompState) -> float:
        return float(self.row[index])

    def put(self: CompState, value: float) -> None:
        self.row[index] = value

    return property(get, put)


def _vector_row(index: int) -> property:
    def get(self: CompState) -> np.ndarray:
        return self.row[index : index + 3]

    def put(self: CompState, value: Sequence[float] | np.ndarray) -> None:
        self.row[index : index + 3] = value

    return property(get, put)


class CompState:
    """One compensation: its configuration and packed model (`evaluator`), and its
    run-time state — a row of the compiled cycle's state array (`step.S`), which
    `VolKernel` binds it to (`row`)."""

    factor = _float_row(vs.FACTOR)  # the ramp: 0 off … 1 fully on
    step = _float_row(vs.STEP)  # ramp change per cycle
    target = _float_row(vs.TARGET)
    cfact = _vector_row(vs.CF)
    modify = _vector_row(vs.MOD)  # +1, −1 (negate), 0 (set_to_zero) per X, Y, Z
    limits = _vector_row(vs.LIM)  # s_limit of X, Y, Z (increments, 0 = not defined)
    value = _vector_row(vs.VAL)  # increments, X Y Z
    raw = _vector_row(vs.RAW)  # mm before weights

    def __init__(
        self,
        comp: VolComp,
        evaluator: Evaluator | None,
        slots: np.ndarray,
        limits: np.ndarray,
        modify: np.ndarray,
    ) -> None:
        self.comp = comp
        self.evaluator = evaluator
        self.slots = slots  # machine slots of the chain axes, chain order
        self.slot_list: list[int] = slots.tolist()
        self.linear_list: list[int] = []  # machine slots of X, Y, Z
        self.row = np.zeros(vs.NS)
        self.row[vs.STEP] = 1.0
        self.row[vs.OVER] = -1.0
        self.cfact = (1.0, 1.0, 1.0)
        self.limits = limits
        self.modify = modify
        #: marked incorrect (004 p.24): an axis of its chain went into error state while
        #: it was active; cleared by the CNC reset and by the next ON (VOLC::incorrect)
        self.incorrect = False

    @property
    def wanted(self) -> bool:
        """Switched on, or waiting for its automatic activation."""
        return bool(self.row[vs.WANT])

    @wanted.setter
    def wanted(self, on: bool) -> None:
        self.row[vs.WANT] = 1.0 if on else 0.0

    @property
    def active(self) -> bool:
        """On or ramping (V.G.VOLCOMP[i].ACTIVE, 004 p.18)."""
        return self.target > 0.0 or self.factor > 0.0


class VolKernel:
    """All volumetric compensations of a machine."""

    def __init__(
        self,
        comps: Sequence[VolComp],
        axes: Sequence[int],
        params: Sequence[AxisParams],
        report: Callable[[int, str], None] | None = None,
    ) -> None:
        self.slot_of = {a: i for i, a in enumerate(axes)}
        self.params = list(params)
        self.n = len(axes)
        #: per machine axis: the sum, the held difference and its state (`step.X`)
        self.X = np.zeros((vs.NX, self.n))
        self.tool_length = 0.0  # mm: VOLC::tool_length (the tool table's, 004 p.15)
        self.report = report or (lambda _id, _msg: None)
        self.states: dict[int, CompState] = {}
        for c in comps:
            self.states[c.id] = self._state(c)
        #: the compiled cycle's state: a row per compensation (`step.S`)
        self.S = np.zeros((len(self.states), vs.NS))
        self._row = {ident: r for r, ident in enumerate(self.states)}
        for ident, st in self.states.items():
            self._bind(ident, st)
        self._active: list[CompState] = []
        self._pack()

    def _bind(self, ident: int, st: CompState) -> None:
        """Move `st`'s state into its row of `S`."""
        row = self.S[self._row[ident]]
        row[:] = st.row
        st.row = row

    def _pack(self) -> None:
        """The packed models of every available compensation in one pair of arrays
        (`tf`, `ti`) and where each starts (`H`): what the compiled cycle reads."""
        fs: list[np.ndarray] = []
        its: list[np.ndarray] = []
        nf = ni = 0
        H = np.zeros((len(self.states), vs.NH), dtype=np.int64)
        for r, st in enumerate(self.states.values()):
            ev = st.evaluator
            if ev is None:
                continue
            H[r, vs.FB], H[r, vs.IB], H[r, vs.NCH] = nf, ni, len(st.slot_list)
            H[r, vs.SLOT : vs.SLOT + len(st.slot_list)] = st.slot_list
            H[r, vs.LS : vs.LS + 3] = st.linear_list
            fs.append(ev.tf)
            its.append(ev.ti)
            nf += len(ev.tf)
            ni += len(ev.ti)
        self.tf = np.concatenate(fs) if fs else np.zeros(1)
        self.ti = np.concatenate(its) if its else np.zeros(1, dtype=np.int64)
        self.H = H

    def state(self) -> Packed:
        """What the compiled cycle takes, a packed `VolState` (the models change on an
        update, the tool length on a write: ask again before each pass)."""
        return tuple(vs.VolState(self.tf, self.ti, self.H, self.S, self.X, self.tool_length))

    @property
    def offset(self) -> np.ndarray:
        """VOLC::correction per machine axis (increments): the sum of the corrections."""
        return self.X[vs.SUM]

    @property
    def held(self) -> np.ndarray:
        """VOLC::held per machine axis (increments): what its drive gets on top of the
        sum since a switch without movement, until ramped out (`step._hold`)."""
        return self.X[vs.DIFF]

    def _hold(self, st: CompState, mode: float = vs.HELD, only: np.ndarray | None = None) -> None:
        """A switch of `st` without movement (004 p.21-24): its X, Y, Z (where `only`
        is True, if given) keep what their drives get now."""
        steps = float(st.row[vs.FSTEPS])
        for s in st.linear_list:
            if only is None or only[s]:
                vs.hold(self.X, s, mode, steps, float(self.X[vs.SUM, s] + self.X[vs.DIFF, s]))

    def _state(self, c: VolComp) -> CompState:
        if c.model is None or c.config is None:
            empty = np.zeros(0, dtype=np.intp)
            return CompState(c, None, empty, np.zeros(3), np.ones(3))
        cfg = c.config
        slots = np.array([self.slot_of[cfg.axes[a]] for a in cfg.chain], dtype=np.intp)
        lin = np.array([self.slot_of[cfg.axes[a]] for a in "XYZ"], dtype=np.intp)
        limits = np.array([float(self.params[s].vol_comp_s_limit) for s in lin])
        modify = np.array(
            [0.0 if a in cfg.set_to_zero else -1.0 if a in cfg.negate else 1.0 for a in "XYZ"]
        )
        st = CompState(c, Evaluator(c.model), slots, limits, modify)
        st.linear_list = lin.tolist()
        st.wanted = not cfg.manual_activation  # automatic activation (004 p.20)
        st.row[vs.FSTEPS] = float(cfg.filter_steps)
        return st

    # ------------------------------------------------------------------ switching

    def get(self, ident: int) -> CompState:
        st = self.states.get(ident)
        if st is None:
            raise KeyError(f"volumetric compensation {ident} is not configured")
        return st

    def switch(
        self,
        ident: int,
        on: bool,
        no_move: bool = False,
        cfact: tuple[float, float, float] | None = None,
        homed: np.ndarray | None = None,
        drive: np.ndarray | None = None,
    ) -> None:
        """`#VOLCOMP ON/OFF [ID=.. NO_MOVE CFACT_*]` or the enable/disable objects: ramp
        over `filter_steps` (004 p.22), at once with NO_MOVE. CFACT_* are non-modal:
        every ON without them weighs 1 (004 p.21). ON needs every axis of the chain
        referenced (`homed`) and error-free (its `drive` enabled, 004 p.20) and s_limit
        defined (p.14); it clears the mark "incorrect" (p.24)."""
        st = self.get(ident)
        if on and st.evaluator is None:
            raise ValueError(f"volumetric compensation {ident} is not available: {st.comp.problem}")
        if on and homed is not None and not homed[st.slots].all():
            raise ValueError(
                f"volumetric compensation {ident}: every axis of the chain must be "
                "referenced (004 p.20)"
            )
        if on and drive is not None and not drive[st.slots].all():
            raise ValueError(
                f"volumetric compensation {ident}: every axis of the chain must be "
                f"error-free, the drive of {self._names(st, drive)} is not enabled (004 p.20)"
            )
        if on:
            missing = [a for a, lim in zip("XYZ", st.limits, strict=True) if lim <= 0]
            if missing:
                raise ValueError(
                    f"volumetric compensation {ident}: lr_param.vol_comp.s_limit (P-AXIS-00525) "
                    f"not defined for {', '.join(missing)} (004 p.14)"
                )
            st.cfact = cfact if cfact is not None else (1.0, 1.0, 1.0)
            st.incorrect = False
        st.wanted = on
        steps = st.comp.config.filter_steps if st.comp.config else 0
        st.step = 1.0 if no_move or steps <= 1 else 1.0 / steps
        st.target = 1.0 if on else 0.0
        if no_move:
            self._hold(st)
            st.factor = st.target
        else:  # a switch with movement also executes what an earlier one held back
            held = self.X[vs.MODE] == vs.HELD
            self._hold(st, vs.RELEASE, held)
        self._refresh()

    def reset(self) -> None:
        """Controller reset: every compensation off without axis movement (004 p.24)."""
        for st in self.states.values():
            if st.active:
                self._hold(st)
            st.wanted = False
            st.target = st.factor = 0.0
            st.value = [0.0, 0.0, 0.0]
            st.incorrect = False
        self._refresh()

    def program_end(self) -> list[int]:
        """M30 (004 p.24: "If compensations are still active at program end (M30) and
        they are linked to the current channel, an error is output and the compensation
        values of the affected axes are reduced without any additional movement"): every
        active compensation with `associate_to_channel 1` is switched off at once, as the
        reset does; the IDs returned, the caller reports the error with the M30's line.
        The others stay as they are (docs/volumetric.md §5)."""
        ended = []
        for st in self._active:
            cfg = st.comp.config
            if cfg is not None and cfg.associate_to_channel and st.active:
                self._hold(st)
                st.wanted = False
                st.target = st.factor = 0.0
                st.value = [0.0, 0.0, 0.0]
                ended.append(st.comp.id)
        if ended:
            self._refresh()
        return ended

    def update(self, ident: int, comp: VolComp) -> None:
        """`#VOLCOMP [ID.. UPDATE]` or the CNC objects: the new configuration replaces
        the old one, which is switched off first without movement (004 p.23 policy,
        docs/volumetric.md §7); automatic activation applies again. A configuration that
        did not load (`comp.available` False) changes nothing: the caller reports it."""
        old = self.get(ident)
        if not comp.available:
            return
        if old.active:
            self._hold(old)
        old.target = old.factor = 0.0
        new = self.states[ident] = self._state(comp)
        self._bind(ident, new)
        self._pack()
        self._refresh()

    def carry_over(self, old: VolKernel) -> None:
        """After a reload: the tool length, and the switching state of every compensation
        that is still available (its corrections follow the new files at once)."""
        self.tool_length = old.tool_length
        if old.X.shape == self.X.shape and self.H.shape[0] > 0:
            self.X[:] = old.X  # (what the drives get goes on; the sums are recomputed)
        for ident, st in old.states.items():
            new = self.states.get(ident)
            if new is None or new.evaluator is None:
                continue
            new.incorrect = st.incorrect  # (a reload is no reset)
            if not st.active:
                continue
            new.wanted, new.factor, new.target = st.wanted, st.factor, st.target
            new.step, new.cfact = st.step, st.cfact
        self._refresh()

    @property
    def busy(self) -> bool:
        """A compensation acts: the machine computes cycles one by one."""
        return bool(self._active)

    @property
    def active_mask(self) -> int:
        """VOLC::active: bit i for compensation i active or ramping."""
        return sum(1 << i for i, s in self.states.items() if s.active)

    @property
    def incorrect_mask(self) -> int:
        """VOLC::incorrect: bit i for compensation i marked incorrect (004 p.24)."""
        return sum(1 << i for i, s in self.states.items() if s.incorrect)

    @property
    def available_mask(self) -> int:
        return sum(1 << i for i, s in self.states.items() if s.evaluator is not None)

    def file_of(self, ident: int) -> str:
        st = self.states.get(ident)
        return st.comp.path if st is not None else ""

    def _refresh(self) -> None:
        self._active = [s for s in self.states.values() if s.active]

    @property
    def at_rest(self) -> bool:
        """No ramp running (a quiescent machine keeps its corrections), no held
        difference ramping out."""
        return all(s.factor == s.target for s in self._active) and not vs.releasing(self.X)

    # ------------------------------------------------------------------ the cycle

    def auto_activate(self, homed: np.ndarray, drive: np.ndarray | None = None) -> None:
        """Automatic activation (004 p.20: "as soon as all participating axes allow it
        (error-free, referenced, etc.)"): a wanted, available compensation whose axes
        are all referenced with their drives enabled starts — checked every cycle, so
        one waiting for an axis starts while others act."""
        for st in self.states.values():
            if not st.wanted or st.target > 0 or st.evaluator is None:
                continue
            if not homed[st.slots].all() or (drive is not None and not drive[st.slots].all()):
                continue
            try:
                self.switch(st.comp.id, True, homed=homed, drive=drive)
            except ValueError as exc:
                st.wanted = False
                self.report(VOLC_ERROR, str(exc))

    def _names(self, st: CompState, ok: np.ndarray) -> str:
        """The chain axes of `st` whose entry in `ok` is False, by their names."""
        bad = [s for s in st.slot_list if not ok[s]]
        return ", ".join(self.params[s].name or f"#{s}" for s in bad)

    def _fault(self, st: CompState, homed: np.ndarray, drive: np.ndarray | None) -> str:
        """Why an axis of `st`'s chain is in error state (004 p.24), "" if none: it lost
        its reference, or its drive is no longer enabled (`SIM::drive_enable`)."""
        if not homed[st.slots].all():
            return f"axis {self._names(st, homed)} lost its reference"
        if drive is not None and not drive[st.slots].all():
            return f"the drive of axis {self._names(st, drive)} is not enabled"
        return ""

    def _off(self, st: CompState, why: str, faulty: np.ndarray) -> None:
        """Switch `st` off in the error case and say why (004 p.24: "Compensation values
        are removed from the axis without causing an additional axis movement [...] the
        other participating axes are stopped in a controlled fashion and their
        compensation values are reduced"): the `faulty` axes hold what their drives get,
        the others' values ramp out over filter_steps from now (the machine stops
        them)."""
        self.report(VOLC_ERROR, f"volumetric compensation {st.comp.id}: {why}")
        self._hold(st, vs.HELD, faulty)
        self._hold(st, vs.RELEASE, ~faulty)
        st.wanted = False
        st.target = st.factor = 0.0
        st.value = [0.0, 0.0, 0.0]

    def attention(self, homed: np.ndarray, drive: np.ndarray) -> bool:
        """Whether the next cycle needs `prepare` (compiled: `step.attention`): a
        compensation to switch on automatically or to switch off for an axis in error
        state. Only operations change the homing and the drives, so a pass of many
        cycles needs it at most before its first."""
        return bool(vs.attention(self.H, self.S, homed, drive))

    def prepare(self, homed: np.ndarray, drive: np.ndarray | None = None) -> bool:
        """What a cycle needs Python for before its volumetric step: the automatic
        activation, and switching off an active compensation one of whose chain axes is
        in error state — no longer referenced or its `drive` no longer enabled (004
        p.20/p.24): marked incorrect, reported. False if one was (the caller stops the
        program after the cycle)."""
        self.auto_activate(homed, drive)
        ok = True
        for st in self._active:
            fault = self._fault(st, homed, drive)
            if fault:
                faulty = ~homed if drive is None else ~(homed & drive)
                self._off(
                    st,
                    f"{fault}: marked incorrect, switched off without movement (004 p.24)",
                    faulty.astype(bool),
                )
                st.incorrect = True
                ok = False
        if not ok:
            self._refresh()
        return ok

    def settle(self, flags: int) -> bool:
        """After compiled cycles whose last step returned `flags` (`step.OFF`,
        `step.ENDED`; `step.FAULT` from `prepare`): report the compensations the s_limit
        watch switched off in it (004 p.14) and refresh the list of active ones. False if
        one was switched off, here or by `prepare` (the caller stops the program)."""
        ok = not flags & vs.FAULT
        if flags & vs.OFF:
            for st in self.states.values():
                k = int(st.row[vs.OVER])
                if k < 0:
                    continue
                st.row[vs.OVER] = -1.0
                ok = False
                self.report(
                    VOLC_ERROR,
                    f"volumetric compensation {st.comp.id}: correction of {'XYZ'[k]} "
                    f"{st.row[vs.OVERSUM]:.0f} exceeds lr_param.vol_comp.s_limit "
                    f"{st.limits[k]:.0f} (P-AXIS-00525, 004 p.14): switched off",
                )
        self._refresh()
        return ok

    def step(
        self,
        pos: np.ndarray,
        homed: np.ndarray,
        drive: np.ndarray | None = None,
        vel: np.ndarray | None = None,
    ) -> bool:
        """One cycle of the volumetric compensations alone: `prepare`, the compiled step
        (`step.step`: `offset` for command positions `pos`, increments, and velocities
        `vel`, none moving if not given), `settle`. False when a compensation had to be
        switched off in this cycle (reported; the caller stops the program). The
        machine runs the compiled step inside its cycle instead
        (`geo_server.machine.cycle.cycles`)."""
        ok = self.prepare(homed, drive)
        v = np.zeros(self.n) if vel is None else vel
        X, tl = self.X, self.tool_length
        flags = vs.step(self.tf, self.ti, self.H, self.S, X, tl, pos, v)
        return self.settle(flags) and ok


__all__ = ["VOLC_ERROR", "CompState", "VolKernel"]
