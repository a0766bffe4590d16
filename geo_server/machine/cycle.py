"""The computed part of a GEO cycle, compiled (docs/design.md §5.1 steps 2–3, §13.3).

`cycles` runs the motion's profiles (`profile.profile_step`), the compensation kernel
(`kernel.step.step`), the volumetric compensations (`volcomp.step.step`), the output to
the drives and the twin's state (`twin.laws.twin_cycle`) for one cycle or a pass of many —
the same function in a loop, so a pass gives the numbers of as many single cycles by
construction. It stops after a cycle that needs Python (its flags): an axis arrived (the
NC program, the twin's scatter draw), a velocity changed sign, a
volumetric compensation was switched off for its s_limit (`VOLC_OFF`: the report and the
program stop); before the first cycle when the volumetric compensations need Python
(`VOLC_PREPARE`: automatic activation, an axis fault); and in the middle of a cycle
when an arrived axis has a queued move to plan (`PLAN`: the caller plans it and resumes
the cycle). A volumetric ramp that ended on the way is said by `VOLC_ENDED` in the
flags returned.
"""

from __future__ import annotations

from enum import IntFlag
from typing import NamedTuple

import numpy as np

from geo_server.jit import Packed, compiled
from geo_server.kernel.layout import ACT, DRIVE, PREV, TOTAL, KernelState
from geo_server.kernel.step import step
from geo_server.machine.profile import (
    ACC,
    ARRIVED,
    FEED,
    HOMED,
    POS,
    START_QUEUED,
    VEL,
    MotionState,
    display,
    profile_step,
    reversal_in,
)
from geo_server.twin.laws import MOTION, TwinState, twin_cycle
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM
from geo_server.volcomp.step import DIFF as VDIFF
from geo_server.volcomp.step import ENDED, FAULT, OFF, VolState
from geo_server.volcomp.step import SUM as VSUM
from geo_server.volcomp.step import attention as volc_attention
from geo_server.volcomp.step import step as volc_step

#: the twin's flags, shifted above the motion's
TWIN_SHIFT = 4
#: the volumetric step's flags (`volcomp.step.OFF`, `ENDED`), shifted above `PLAN`
VOLC_SHIFT = 9


class CycleFlag(IntFlag):
    """The flags `cycles` returns with its count, as Python reads them (`CycleFlag(raw)`);
    the compiled code sets the same bits as the plain ints below."""

    #: an axis arrived / a queued move waits to start (the motion's own flags)
    ARRIVED = ARRIVED
    START_QUEUED = START_QUEUED
    #: the twin: a velocity changed sign (`twin.laws.MOTION`, shifted)
    TWIN_MOTION = MOTION << TWIN_SHIFT
    #: the cycle stopped after its motion, to plan a queued move
    PLAN = 1 << 8
    #: a volumetric compensation switched off for its s_limit / a ramp ended
    VOLC_OFF = OFF << VOLC_SHIFT
    VOLC_ENDED = ENDED << VOLC_SHIFT
    #: (Python's: `VolKernel.prepare` switched a compensation off for an axis fault)
    VOLC_FAULT = FAULT << VOLC_SHIFT
    #: nothing computed: the volumetric compensations need `VolKernel.prepare`
    VOLC_PREPARE = 1 << 12


# the compiled code's constants (numba reads plain ints)
PLAN = int(CycleFlag.PLAN)
VOLC_OFF = int(CycleFlag.VOLC_OFF)
VOLC_ENDED = int(CycleFlag.VOLC_ENDED)
VOLC_PREPARE = int(CycleFlag.VOLC_PREPARE)
assert not (PLAN & (ARRIVED | START_QUEUED)) and CycleFlag.TWIN_MOTION < PLAN
assert PLAN < VOLC_OFF and CycleFlag.VOLC_FAULT < VOLC_PREPARE
# Rows of the machine's per-cycle buffer (`Machine._mbuf`, its [n, NROWS] view): the
# published deltas of the seven compensation columns (rows 0–6), then what `derived`
# computes for a snapshot, the output to the drives (`cycles`) and the configured backlash
DISPLAY, VELOCITY, ACCELERATION, FEED_UM, OUTPUT, LOSE = range(7, 13)
NROWS = 13


class CycleOut(NamedTuple):
    """Where `cycles` writes: the cycles until a known reversal per axis (`reversal_in`),
    the output to the drives, and the drives' actual position where enabled."""

    reversal: np.ndarray
    output: np.ndarray
    drive_act: np.ndarray


@compiled
def cycles(
    count: int,
    resume: bool,
    check: bool,
    motion: Packed,
    kernel: Packed,
    vol: Packed,
    twin: Packed,
    spindle: bool,
    out: Packed,
) -> tuple[int, int]:
    """Up to `count` cycles of the parts' states (packed: `MotionState`, `KernelState`,
    `VolState`, `TwinState`, and `CycleOut` where it writes); (cycles completed, flags of
    the last one). `resume`: the first cycle's motion has run already (after `PLAN`). `check`:
    first ask whether the volumetric compensations need Python
    (`volcomp.step.attention`; then nothing is computed and the flags say
    `VOLC_PREPARE`) — only operations change what it looks at, so once before a pass is
    enough. Writes into `out` the cycles until a known reversal, the output to the drives
    (command + total offset + the volumetric offset — sum and held difference,
    `volcomp.step.X` — where the machine has volumetric compensations) and, where the
    drive is enabled, the drive's actual position."""
    mo, k, vo, tw, o = (
        MotionState(*motion), KernelState(*kernel), VolState(*vol), TwinState(*twin),
        CycleOut(*out),
    )  # fmt: skip
    MF, MI, MB, dt = mo.F, mo.I, mo.B, mo.dt
    K1, B1, VX = k.F1, k.B1, vo.X
    rev, output, drive_act = o.reversal, o.output, o.drive_act
    n = MF.shape[1]
    has_vol = vo.H.shape[0] > 0
    if has_vol and check and not resume and volc_attention(vo.H, vo.S, MB[HOMED], B1[DRIVE]):
        return 0, VOLC_PREPARE
    ended = 0
    for done in range(count):
        flags = 0
        if not (resume and done == 0):
            flags = profile_step(MF, MI, MB, dt)
            if flags & START_QUEUED:
                return done, flags | PLAN
        reversal_in(MF, MI, rev)
        step(kernel, MF[POS], MF[VEL], MF[ACC], MB[HOMED], rev)
        if has_vol:
            vflags = volc_step(vo.tf, vo.ti, vo.H, vo.S, VX, vo.tool_length, MF[POS], MF[VEL])
            vflags <<= VOLC_SHIFT
            flags |= vflags & VOLC_OFF
            ended |= vflags & VOLC_ENDED
        for i in range(n):
            x = MF[POS, i] + K1[TOTAL, i]
            if has_vol:
                x = x + VX[VSUM, i] + VX[VDIFF, i]
            output[i] = x
            if B1[DRIVE, i]:
                drive_act[i] = x
        twin_flags = twin_cycle(tw.A, tw.N, tw.SN, tw.S, tw.C, tw.amb, MF[VEL], spindle)
        flags |= (twin_flags & MOTION) << TWIN_SHIFT
        if flags:
            return done + 1, flags | ended
    return count, ended


@compiled
def _round_half_away(x: float) -> float:
    """Round half away from zero (docs/design.md §3.2): what an integer object shows."""
    return float(np.copysign(np.floor(abs(x) + 0.5), x))


@compiled
def derived(F7: np.ndarray, MF: np.ndarray, MB: np.ndarray, rows: np.ndarray) -> None:
    """The values a snapshot derives from the cycle's state, into the machine's rows
    (`Machine._mbuf`): the published deltas of the seven columns — differences of the
    rounded values of this cycle and the one before, so that the deltas of a ramp add up
    to its value — the displayed positions, and velocity, acceleration and feed in the
    objects' units (µm/s, mm/s², µm/s)."""
    n = MF.shape[1]
    for i in range(n):
        for c in range(7):
            rows[c, i] = _round_half_away(F7[ACT, i, c]) - _round_half_away(F7[PREV, i, c])
        rows[VELOCITY, i] = MF[VEL, i] / UNITS_PER_UM
        rows[ACCELERATION, i] = MF[ACC, i] / UNITS_PER_MM
        rows[FEED_UM, i] = MF[FEED, i] / UNITS_PER_UM
    display(MF, MB, rows[DISPLAY])
