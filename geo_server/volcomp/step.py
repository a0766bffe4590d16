"""One GEO cycle of a machine's volumetric compensations, compiled (004 §4, docs/
volumetric.md §2, §5; docs/design.md §13.3).

Per active compensation, in the order of the start-up list: its ramp of `filter_steps`
advanced by one cycle (004 p.22), its correction at the command positions
(`law.correction`) for the tool point at the current tool length (004 p.15), weighed by
the `CFACT_*` of its activation (p.21), the ramp and `negate`/`set_to_zero` (p.16),
added up per axis into the offset the drives get; then the `s_limit` watch (p.14) over
the sum. `geo_server.machine.cycle.cycles` runs it inside the compiled cycle, so a pass
of many cycles computes it as single cycles do; `VolKernel` is its Python face and does
what needs Python: switching, automatic activation, the faults, the reports.

A switch without movement (`NO_MOVE`, the reset, M30, UPDATE, the error case and the
s_limit watch, 004 p.21-24) holds what the drive of each X, Y, Z it concerns gets, as the
axis compensations' NO_MOVE does (000 p.94, docs/volumetric.md §5): the difference
between that and the new correction is kept at rest and ramped out over `filter_steps`
cycles from the axis' next motion (`_hold`).

The arrays (`VolKernel.arrays`): `tf`, `ti` the packed models of every available
compensation (`law.pack`, at the bases in `H`); `H` [compensations, NH] integers: where
each model starts and which machine slots its chain and its X, Y, Z are; `S`
[compensations, NS] floats: the run-time state of each; `X` [NX, axes] floats per
machine axis: the sum (`SUM`, increments, `VOLC::correction`) and the held difference
(`DIFF`, `VOLC::held`) the drive gets on top of it, with its state.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from geo_server.jit import compiled
from geo_server.units import UNITS_PER_MM
from geo_server.volcomp.law import MAXARGS, N0, P0, correction

#: increments per mm (a literal: the compiled code's constant, keyed by this file's stamp)
UNITS = 10_000.0
assert UNITS == UNITS_PER_MM

# ---- H: per compensation, integers
FB, IB, NCH = range(3)  # model bases in tf, ti; chain length (0: not available)
SLOT = 3  # machine slots of the chain axes, chain order (MAXARGS)
LS = SLOT + MAXARGS  # machine slots of X, Y, Z (3)
NH = LS + 3

# ---- S: per compensation, floats
(
    FACTOR,  # the ramp: 0 off … 1 fully on
    STEP,  # its change per cycle
    TARGET,  # 0 or 1
    WANT,  # wanted (switched on, or automatic activation waiting): 1.0 / 0.0
    WAS,  # active at the start of the last cycle (scratch)
    OVER,  # the axis (0 X, 1 Y, 2 Z) whose sum exceeded its s_limit, −1 none
    OVERSUM,  # that sum (increments)
) = range(7)
CF = 7  # CFACT_X/Y/Z of the activation (3)
MOD = CF + 3  # +1, −1 (negate), 0 (set_to_zero) per X, Y, Z (3)
LIM = MOD + 3  # s_limit of X, Y, Z (increments, 0: not defined) (3)
VAL = LIM + 3  # the weighed correction (increments, 3)
RAW = VAL + 3  # the correction (mm, 3)
FSTEPS = RAW + 3  # filter_steps of its configuration (a held difference's ramp)
NS = FSTEPS + 1

# ---- X: per machine axis, floats
(
    SUM,  # the sum of the corrections (increments): VOLC::correction
    DIFF,  # held: what the drive gets minus SUM (increments): VOLC::held
    MODE,  # FOLLOW, HELD (until the axis moves) or RELEASE (ramp DIFF out from now)
    KEEP,  # HELD: what the drive keeps getting (SUM + DIFF when it was held)
    RATE,  # DIFF's change per cycle while it ramps out
    STEPS,  # the cycles of that ramp (filter_steps of the compensation switched)
    PREV,  # scratch: what the drive got in the cycle before
) = range(7)
NX = 7
FOLLOW, HELD, RELEASE = 0.0, 1.0, 2.0

#: `step`'s flags: a compensation was switched off for its s_limit (its `OVER` says
#: why); a compensation's ramp ended at 0 (it is no longer active); and `VolKernel.
#: prepare`'s: one was switched off for an axis fault
OFF, ENDED, FAULT = 1, 2, 4


class VolState(NamedTuple):
    """What the compiled cycle takes of the volumetric compensations
    (`VolKernel.state`): the models' floats and integers (`law.py`'s layout), the
    compensations' headers `H` and states `S`, the result `X` (`SUM`, `DIFF`) and the
    tool length in mm."""

    tf: np.ndarray
    ti: np.ndarray
    H: np.ndarray
    S: np.ndarray
    X: np.ndarray
    tool_length: float


@compiled
def _active(S: np.ndarray, c: int) -> bool:
    return S[c, TARGET] > 0.0 or S[c, FACTOR] > 0.0


@compiled
def _ramp(S: np.ndarray, c: int) -> None:
    """Compensation c's ramp one cycle on towards its target (004 p.22)."""
    if S[c, FACTOR] != S[c, TARGET]:
        d = S[c, TARGET] - S[c, FACTOR]
        if abs(d) <= S[c, STEP]:
            S[c, FACTOR] = S[c, TARGET]
        else:
            S[c, FACTOR] = S[c, FACTOR] + math.copysign(S[c, STEP], d)


@compiled
def hold(X: np.ndarray, slot: int, mode: float, steps: float, now: float) -> None:
    """Hold `now`, what the drive of `slot` gets now (`HELD`: until the axis moves;
    `RELEASE`: ramped out from the next step on) over `steps` cycles: a switch without
    movement. An axis already held keeps what it holds and the ramp it holds it with
    (a second switch without movement changes neither); a release ramps out over the
    releasing switch's `steps`."""
    if X[MODE, slot] != HELD:
        X[KEEP, slot] = now
    if X[MODE, slot] != HELD or mode == RELEASE:
        X[MODE, slot] = mode
        X[STEPS, slot] = max(steps, 1.0)


@compiled
def _limits(H: np.ndarray, S: np.ndarray, X: np.ndarray) -> bool:
    """The s_limit watch (004 p.14) over the sum `X[SUM]`: a compensation (active since
    the start of the cycle and still) with an axis beyond its limit is switched off
    without movement (its X, Y, Z held), `OVER` and `OVERSUM` saying why (`VolKernel`
    reports it). Whether one was."""
    over = False
    for c in range(H.shape[0]):
        if S[c, WAS] == 0.0 or not _active(S, c):
            continue
        for k in range(3):
            v = X[SUM, H[c, LS + k]]
            if abs(v) > S[c, LIM + k]:
                S[c, OVER], S[c, OVERSUM] = k, v
                S[c, TARGET] = S[c, FACTOR] = S[c, WANT] = 0.0
                S[c, VAL] = S[c, VAL + 1] = S[c, VAL + 2] = 0.0
                for j in range(3):
                    a = H[c, LS + j]
                    hold(X, a, HELD, S[c, FSTEPS], X[PREV, a])
                over = True
                break
    return over


@compiled
def _hold(X: np.ndarray, vel: np.ndarray) -> None:
    """What the drives get on top of the sum: a held axis keeps `KEEP` until it moves
    (000 p.94's rule for NO_MOVE, "executed at the next axis motion"); from that cycle
    on — or at once for `RELEASE` — the difference ramps out linearly in `STEPS`
    cycles, as the compensations' own filter does (004 p.22)."""
    for i in range(X.shape[1]):
        mode = X[MODE, i]
        if mode == HELD and vel[i] == 0.0:
            X[DIFF, i] = X[KEEP, i] - X[SUM, i]
            continue
        if mode != FOLLOW:  # the ramp starts: its size
            X[MODE, i] = FOLLOW
            X[DIFF, i] = X[KEEP, i] - X[SUM, i]
            X[RATE, i] = abs(X[DIFF, i]) / X[STEPS, i]
        d = X[DIFF, i]
        if d != 0.0:
            X[DIFF, i] = 0.0 if abs(d) <= X[RATE, i] else d - math.copysign(X[RATE, i], d)


@compiled
def step(
    tf: np.ndarray,
    ti: np.ndarray,
    H: np.ndarray,
    S: np.ndarray,
    X: np.ndarray,
    length: float,
    pos: np.ndarray,
    vel: np.ndarray,
) -> int:
    """`X[SUM]` and `X[DIFF]` for the command positions `pos` (increments) and
    velocities `vel` and a tool of `length` mm; the flags `OFF`, `ENDED`. Without
    compensations `X` is left alone."""
    nc = H.shape[0]
    if nc == 0:
        return 0
    off = X[SUM]
    for i in range(X.shape[1]):
        X[PREV, i] = off[i] + X[DIFF, i]
        off[i] = 0.0
    q = np.empty(MAXARGS)
    d = np.empty(3)
    flags = 0
    for c in range(nc):
        if not _active(S, c):
            S[c, WAS] = 0.0
            continue
        S[c, WAS] = 1.0
        _ramp(S, c)
        fb, ib = H[c, FB], H[c, IB]
        for i in range(H[c, NCH]):
            q[i] = pos[H[c, SLOT + i]] / UNITS
        correction(
            tf, ti, fb, ib, q,
            tf[fb + P0] + length * tf[fb + N0],
            tf[fb + P0 + 1] + length * tf[fb + N0 + 1],
            tf[fb + P0 + 2] + length * tf[fb + N0 + 2],
            d,
        )  # fmt: skip
        w = S[c, FACTOR] * UNITS
        for k in range(3):
            S[c, RAW + k] = d[k]
            S[c, VAL + k] = d[k] * S[c, CF + k] * S[c, MOD + k] * w
            off[H[c, LS + k]] += S[c, VAL + k]
        if not _active(S, c):
            flags |= ENDED
    if _limits(H, S, X):
        flags |= OFF
        off[:] = 0.0
        for c in range(nc):
            if S[c, WAS] != 0.0 and _active(S, c):
                for k in range(3):
                    off[H[c, LS + k]] += S[c, VAL + k]
    _hold(X, vel)
    return flags


@compiled
def releasing(X: np.ndarray) -> bool:
    """Whether a held difference is ramping out or about to (not at rest)."""
    for i in range(X.shape[1]):
        if X[MODE, i] == RELEASE or (X[MODE, i] == FOLLOW and X[DIFF, i] != 0.0):
            return True
    return False


@compiled
def attention(H: np.ndarray, S: np.ndarray, homed: np.ndarray, drive: np.ndarray) -> bool:
    """Whether the next cycle needs Python before its volumetric step: a wanted
    compensation that is not on yet has every chain axis referenced with its drive
    enabled (automatic activation, 004 p.20), or an active one has an axis that is not
    (the error case, p.24)."""
    for c in range(H.shape[0]):
        n = H[c, NCH]
        if n == 0:
            continue
        ready = True
        for i in range(n):
            s = H[c, SLOT + i]
            if not (homed[s] and drive[s]):
                ready = False
        if _active(S, c) and not ready:
            return True
        if S[c, WANT] != 0.0 and S[c, TARGET] <= 0.0 and ready:
            return True
    return False


__all__ = [
    "ENDED", "FAULT", "HELD", "NH", "NS", "NX", "OFF", "RELEASE", "SUM", "attention", "hold",
    "releasing", "step",
]  # fmt: skip
