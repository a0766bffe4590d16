"""The machine as the NC player sees it (`nc.MachinePort`): positions, moves, homing,
COMP and #VOLCOMP switches, the compensation states the V.A variables read (000 §5).

One role, one class: `Machine` is what the object service and the cycle drive;
this is what an NC program drives, over the same machine (its motion, kernel and
volumetric compensation), on the cycle's thread (the player runs in the cycle).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future
from time import monotonic
from typing import TYPE_CHECKING, Any

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.kernel import COMP_ORDER
from geo_server.kernel.common import ALL_KINDS, COLUMN, listed_kinds, mask_of
from geo_server.listfile.values import Reporter
from geo_server.machine.nc import VolcompCommand
from geo_server.model import CompKind, Diagnostic
from geo_server.units import UNITS_PER_MM
from geo_server.volcomp.config import reload_compensation
from geo_server.volcomp.kernel import VOLC_ERROR

if TYPE_CHECKING:
    from geo_server.machine.machine import Machine

#: seconds a #VOLCOMP UPDATE may take to read its files before it is given up
VOLC_LOAD_TIMEOUT = 30.0
#: the longest name `V.G.VOLCOMP[i].FILE[j] = "…"` takes (a STRING of 255, as the CNC's)
MAX_VOLC_FILE_NAME = 255


def _in_worker(fn: Callable[[], Any]) -> Future[Any]:
    """Run `fn` in a daemon thread of its own (reading files off the cycle: one that
    never delivers, a FIFO or a dead share, holds up neither other machines nor the
    interpreter's exit)."""
    fut: Future[Any] = Future()

    def run() -> None:
        try:
            fut.set_result(fn())
        except BaseException as exc:  # handed to the cycle, which reports it
            fut.set_exception(exc)

    threading.Thread(target=run, name="volcomp-load", daemon=True).start()
    return fut


class NcSide:
    """`nc.MachinePort` over one machine (`Machine.nc_side`)."""

    def __init__(self, machine: Machine) -> None:
        self._m = machine

    def position(self, slot: int) -> float:
        return float(self._m.motion.pos[slot])

    def modulo_period(self, slot: int) -> float:
        return float(self._m._period[slot]) if self._m._modulo[slot] else 0.0

    def move_linear(
        self,
        targets: dict[int, float],
        feed: float | None,
        rapid: bool,
        next_dirs: dict[int, int],
    ) -> None:
        moving = [slot for slot, target in targets.items() if target != self._m.motion.pos[slot]]
        self._m.motion.move_linear(targets, feed, rapid)
        for slot in moving:
            self._m.kernel.release(slot)  # the axis' next motion (COMP … NO_MOVE)
        for slot, direction in next_dirs.items():
            self._m.motion.announce_next(slot, direction)

    def home(self, slots: Sequence[int]) -> None:
        for slot in slots:
            self._m.motion.home(slot)

    def in_position(self, slots: Iterable[int]) -> bool:
        return self._m.motion.all_in_position(slots)

    def stop_axes(self, slots: Iterable[int]) -> None:
        for s in slots:
            self._m.motion.stop(s)

    def comp(self, slot: int, on: bool, kinds: CompKind, no_move: bool) -> int:
        return self._switch(slot, kinds, on, no_move)

    def comp_off_all(self, slot: int, no_move: bool) -> int:
        return self._switch(slot, ALL_KINDS, False, no_move)

    def _switch(self, slot: int, kinds: CompKind, on: bool, no_move: bool) -> int:
        """COMP ON/OFF (000 §5.1 p.94). Without NO_MOVE the offset is executed now (the
        program waits for it), together with any offset an earlier NO_MOVE held back; with
        NO_MOVE it is held until the axis' next motion."""
        before = self._m.kernel.selected[slot].copy()
        err = self._m.set_comp(slot, kinds, on)
        if err:
            return err
        # only a switch that changes the selection has an offset to hold; an axis in
        # motion executes it with that motion
        changed = mask_of(
            k for k in COMP_ORDER if before[COLUMN[k]] != self._m.kernel.selected[slot, COLUMN[k]]
        )
        if no_move and self._m.motion.all_in_position([slot]):
            self._m.kernel.hold(slot, changed)
        else:
            self._m.kernel.release(slot)
        return 0

    def volcomp(self, cmd: VolcompCommand) -> tuple[int, str]:
        """`#VOLCOMP …` (004 p.21-23): switch, or start reading the files of an UPDATE
        in a worker thread (the cycle never waits for a disk); ALL switches every
        available compensation."""
        volc = self._m.volc
        ids = cmd.ids
        if ids is None:
            ids = tuple(
                i for i, st in volc.states.items() if st.evaluator is not None or not cmd.on
            )
        try:
            for ident in ids:
                if cmd.update:
                    self._volc_update(ident)
                else:
                    volc.switch(
                        ident,
                        cmd.on,
                        cmd.no_move,
                        cmd.cfact,
                        self._m.motion.homed,
                        self._m.kernel.drive_enabled,
                    )
        except (KeyError, ValueError) as exc:
            return VOLC_ERROR, str(exc.args[0]) if exc.args else str(exc)
        return 0, ""

    def _volc_update(self, ident: int) -> None:
        """Read compensation `ident` again from its VOLC list (004 p.23)."""
        comp = self._m.volc.get(ident).comp
        cfg = self._m.cfg

        written = dict(self._m._volc_files.get(ident, {}))

        def load() -> tuple[Any, list[Diagnostic]]:
            diags: list[Diagnostic] = []
            path = comp.path or comp.file_name
            new = reload_compensation(cfg, ident, path, Reporter(diags), written)
            return new, diags

        self._m._volc_loading.append((ident, monotonic(), _in_worker(load)))

    def volcomp_active(self, ident: int) -> bool:
        st = self._m.volc.states.get(ident)
        return st is not None and st.active

    def volcomp_file(self, ident: int, index: int) -> str:
        written = self._m._volc_files.get(ident, {})
        if index in written:
            return written[index]
        st = self._m.volc.states.get(ident)
        cfg = st.comp.config if st is not None else None
        if cfg is None:
            return ""
        by_slot = dict(zip(cfg.file_slots, (name for name, _, _ in cfg.files), strict=True))
        return by_slot.get(index, "")

    def set_volcomp_file(self, ident: int, index: int, name: str) -> tuple[int, str]:
        if ident not in self._m.volc.states:
            return VOLC_ERROR, (
                f"V.G.VOLCOMP[{ident}].FILE[{index}]: no volumetric compensation {ident} "
                f"(vol_comp[{ident}] in the start-up list, 004 p.12)"
            )
        if not name.strip() or len(name) > MAX_VOLC_FILE_NAME:
            return VOLC_ERROR, (
                f"V.G.VOLCOMP[{ident}].FILE[{index}]: a file name of 1 … "
                f"{MAX_VOLC_FILE_NAME} characters"
            )
        self._m._volc_files.setdefault(ident, {})[index] = name.strip()
        return 0, ""

    def volcomp_settled(self) -> bool:
        """The #VOLCOMP ramps are over and the updates read and applied. An update
        whose files did not load keeps the compensation as it was (like the CNC object,
        docs/volumetric.md §7) and ends the program with its error; one still reading
        after `VOLC_LOAD_TIMEOUT` s (a file that never delivers) is given up."""
        while self._m._volc_loading:
            ident, since, fut = self._m._volc_loading[0]
            if not fut.done():
                if monotonic() - since < VOLC_LOAD_TIMEOUT:
                    break
                self._m._volc_loading.pop(0)
                raise AdsError(
                    AdsErrorCode.DEVICE_TIMEOUT,
                    f"#VOLCOMP [ID{ident} UPDATE]: its files were not read within "
                    f"{VOLC_LOAD_TIMEOUT:.0f} s",
                )
            self._m._volc_loading.pop(0)
            new, diags = fut.result()
            for d in diags:
                self._m._record(d)
            if new is None or not new.available:
                why = new.problem if new is not None else "not configured"
                raise AdsError(
                    AdsErrorCode.DEVICE_SYNTAX,
                    f"#VOLCOMP [ID{ident} UPDATE] failed, compensation unchanged: {why}",
                )
            self._m.volc.update(ident, new)
            self._m._volc_files.pop(ident, None)  # (the loaded list carries the names given)
        return not self._m._volc_loading and self._m.volc.at_rest

    def comp_settled(self, slots: Iterable[int]) -> bool:
        """000 §5.1: the offset of a COMP switch is travelled before the program goes
        on, i.e. the program waits until the axis' sin² ramps have ended (NO_MOVE
        blocks do not wait: their offset is held until the axis' next motion)."""
        return not any(self._m.kernel.ramping(s) for s in slots)

    def effective(self, slot: int) -> CompKind:
        """Effective now: the present selection (a COMP of this cycle included) with the
        preconditions of the last cycle (000 §5.3; docs/design.md §6.8)."""
        k = self._m.kernel
        return mask_of(
            kind
            for i, kind in enumerate(COMP_ORDER)
            if k.selected[slot, i] and k.preconditions[slot, i]
        )

    def required(self, slot: int) -> CompKind:
        """`prog_movement_requires_compensations` ∩ compensations selected in the axis
        list: errors only for compensations also enabled there (000 §5.3, p.97)."""
        p = self._m.cfg.axes[self._m.axes[slot]].params
        monitored = ~(CompKind.FRICT | CompKind.CROSSTALK)  # no bit in 000 p.98
        return p.prog_movement_requires_compensations & listed_kinds(p) & monitored

    def initialised(self, slot: int) -> CompKind:
        """`V.A.<name>_COMP_INIT` (000 §5.2 p.95): enabled in the axis list and validly
        configured (a valid table whose masters are axes of the machine), whether or not
        it is selected (manual activation) or effective yet."""
        p = self._m.cfg.axes[self._m.axes[slot]].params
        on = self._m.kernel.configured[slot]
        configured = mask_of(k for i, k in enumerate(COMP_ORDER) if on[i])
        return listed_kinds(p) & configured

    def current(self, slot: int, kind: CompKind) -> float:
        """`V.A.<name>_COMP_CURR` (000 §5.2 p.96): the output in mm (° on rotary axes);
        friction, which has no position offset here, gives its additive current."""
        value = float(self._m.kernel.actual[slot, COLUMN[kind]])
        return value if kind == CompKind.FRICT else value / UNITS_PER_MM

    def program_end(self) -> None:
        """M30 (`Machine.program_end`: it shares the deselection with a reset)."""
        self._m.program_end()

    def release_axis(self, slot: int) -> None:
        """`#PUT AX` (`Machine.release_axis`)."""
        self._m.release_axis(slot)

    def report(self, error_id: int, message: str, line: int) -> None:
        """An error of the program, at its line, in the machine's errors list."""
        self._m.report(error_id, message, line)

    def message(self, text: str, line: int) -> None:
        """`#MSG` (`Machine.message`)."""
        self._m.message(text, line)
