"""One GEO cycle of the compensation kernel, compiled (docs/design.md §5.1 step 3, §6, §13.3).

Per axis, in the manual's order: the direction, the effective flags and step events, the
targets of backlash, temperature, cross, plane and crosstalk, their sin² filter, LSEC on
the filtered cross and plane outputs, friction through its delay line, and the total
offset. Each law is its compensation module's (`temperature.offset`, `tables.interp`,
`plane.bilinear`, `crosstalk.value`, `lsec.target`, `friction.base`/`weigh`,
`sin2.output`, called by their plain names: `geo_server.jit`); this module only
orchestrates them over the kernel's arrays
(`layout`). `steps` is the same cycle in a loop: a pass of many cycles gives the
numbers of as many single cycles by construction.
"""

from __future__ import annotations

import numpy as np

from geo_server.jit import Packed, compiled
from geo_server.kernel import temperature
from geo_server.kernel.common import BC, CROSS, CROSSTALK, FRICT, LEAD, PLANE, TEMP
from geo_server.kernel.crosstalk import CrosstalkTable
from geo_server.kernel.crosstalk import value as crosstalk_value
from geo_server.kernel.friction import RING
from geo_server.kernel.friction import base as friction_base
from geo_server.kernel.friction import weigh as friction_weigh
from geo_server.kernel.layout import (
    ACT,
    CONF,
    CR_M,
    CR_N,
    CR_T,
    DELTA,
    DIR,
    DRIVE,
    EFF,
    EVENT,
    FIRST,
    FR_DELAY,
    FR_LOOK,
    FR_N,
    FR_PD,
    FR_SCALE,
    FR_T,
    HELD,
    HIST,
    INIT_DIR,
    JUMP,
    KIDX,
    LOSE,
    LS_CMD,
    LS_N,
    LS_NEG,
    LS_PER,
    LS_POS,
    LS_WRAP,
    LS_X0,
    MODULO,
    NCYC,
    PATH,
    PEND,
    PENDING,
    PERIOD,
    PL_INT1,
    PL_INT2,
    PL_M1,
    PL_M2,
    PL_NI,
    PL_NJ,
    PL_START1,
    PL_START2,
    PL_T,
    POSP,
    PRE,
    PREV,
    REV,
    RING_POS,
    SEL,
    TC_COEF,
    TC_OFF0,
    TC_POS0,
    TGT,
    TOTAL,
    WOFF,
    XT_DYN,
    XT_EDGE,
    XT_INV_ACC,
    XT_INV_DEC,
    XT_KIND,
    XT_N,
    XT_NEDGE,
    XT_NTRI,
    XT_P1,
    XT_P2,
    XT_T,
    XT_TRI,
    XT_VELDEP,
    KernelState,
)
from geo_server.kernel.lsec import target as lsec_target
from geo_server.kernel.plane import bilinear
from geo_server.kernel.sin2 import output as sin2_output
from geo_server.kernel.tables import interp, wrap

_offset = compiled(temperature.offset)


@compiled
def _homed(needs: np.ndarray, count: int, homed: np.ndarray) -> bool:
    """The first `count` axes of `needs` are homed (`layout.KernelState.homing`)."""
    for j in range(count):  # noqa: SIM110 (numba compiles no generator)
        if not homed[needs[j]]:
            return False
    return True


@compiled
def _effective(i: int, k: KernelState, homed: np.ndarray, rev: bool) -> None:
    """Effective = selected ∧ preconditions (docs/design.md §6.8: homing per column, a
    valid table, and for cross and plane the drive enabled, 000 §5.3 p.97 item 4); a
    change is a step event (§3.5), as is a pending TEMPC write, reload or release, and a
    reversal for backlash and bilateral LSEC (P-AXIS-00243; `lsec_bilateral` below)."""
    B7 = k.B7
    drive = k.B1[DRIVE, i]
    for c in range(7):
        pre = B7[CONF, i, c] and _homed(k.homing[i, c], k.homing_n[i, c], homed)
        if c in (CROSS, PLANE):
            pre = pre and drive
        B7[PRE, i, c] = pre
        e = pre and B7[SEL, i, c]
        B7[EVENT, i, c] = (e != B7[EFF, i, c]) or B7[PEND, i, c] or (rev and e and c == BC)
        B7[EFF, i, c] = e
        B7[PEND, i, c] = False


@compiled
def _targets(
    i: int,
    F7: np.ndarray,
    F1: np.ndarray,
    P: np.ndarray,
    IP: np.ndarray,
    B7: np.ndarray,
    tab: np.ndarray,
    pos: np.ndarray,
    vel: np.ndarray,
    acc: np.ndarray,
) -> None:
    """The unfiltered targets of backlash, temperature, cross, plane and crosstalk (0
    when not effective) into F7[TGT]."""
    tgt = F7[TGT, i]
    for c in range(7):
        tgt[c] = 0.0
    if B7[EFF, i, BC]:  # 0 in the start-up direction, d·lose after a reversal (000 §2)
        d = F1[DIR, i]
        tgt[BC] = 0.0 if d == P[INIT_DIR, i] else d * P[LOSE, i]
    if B7[EFF, i, TEMP]:  # 000 §3.1 p.15
        s = wrap(pos[i], 0.0, P[PERIOD, i]) if IP[MODULO, i] else pos[i]
        tgt[TEMP] = _offset(F1[TC_OFF0, i], F1[TC_COEF, i], F1[TC_POS0, i], s)
    if B7[EFF, i, CROSS]:  # 000 §4.2; a modulo master wraps the table (000 p.31)
        m = IP[CR_M, i]
        q = wrap(pos[m], 0.0, P[PERIOD, m]) if IP[MODULO, m] else pos[m]
        tgt[CROSS] = interp(tab, IP[CR_T, i], IP[CR_N, i], q)
    if B7[EFF, i, PLANE]:  # 000 §4.3
        m1, m2 = IP[PL_M1, i], IP[PL_M2, i]
        q1 = wrap(pos[m1], 0.0, P[PERIOD, m1]) if IP[MODULO, m1] else pos[m1]
        q2 = wrap(pos[m2], 0.0, P[PERIOD, m2]) if IP[MODULO, m2] else pos[m2]
        tgt[PLANE] = bilinear(
            tab,
            IP[PL_T, i],
            IP[PL_NI, i],
            IP[PL_NJ, i],
            q1,
            q2,
            P[PL_START1, i],
            P[PL_START2, i],
            P[PL_INT1, i],
            P[PL_INT2, i],
        )
    if B7[EFF, i, CROSSTALK]:  # 000 §4.6
        m = IP[XT_DYN, i]
        table = CrosstalkTable(
            IP[XT_KIND, i],
            IP[XT_T, i],
            IP[XT_N, i],
            IP[XT_TRI, i],
            IP[XT_NTRI, i],
            IP[XT_EDGE, i],
            IP[XT_NEDGE, i],
            IP[XT_VELDEP, i] != 0,
            P[XT_INV_ACC, i],
            P[XT_INV_DEC, i],
        )
        x, y = pos[IP[XT_P1, i]], pos[IP[XT_P2, i]]
        tgt[CROSSTALK] = crosstalk_value(tab, table, acc[m], vel[m], x, y)


@compiled
def _filter(
    i: int, c: int, F7: np.ndarray, B7: np.ndarray, I7: np.ndarray, weights: np.ndarray
) -> None:
    """The sin² filter of column `c` (`sin2.output`) from F7[TGT] into F7[ACT]; a held
    column (COMP … NO_MOVE) keeps its previous output."""
    out, k, jump = sin2_output(
        F7[TGT, i, c],
        F7[PREV, i, c],
        B7[EVENT, i, c],
        I7[KIDX, i, c],
        I7[NCYC, i, c],
        F7[JUMP, i, c],
        weights,
        I7[WOFF, i, c],
    )
    I7[KIDX, i, c] = k
    F7[JUMP, i, c] = jump
    F7[ACT, i, c] = F7[PREV, i, c] if B7[HELD, i, c] else out


@compiled
def _smooth(i: int, F7: np.ndarray, B7: np.ndarray, I7: np.ndarray, weights: np.ndarray) -> None:
    """Crosstalk's sin² filter of order N = n_cycles (000 p.83: "these compensation
    values can be smoothed by using a sine-square filter"; P-COMP-00064 p.87): the last
    N targets weighed by the steps of the sin² ramp, w(j) − w(j+1) with w(j) =
    cos²(π·j/(2N)). A step of the target, as at switching on or off, becomes the ramp
    A·sin²(π·k/(2N)) of the other columns' filter; every later change of the values is
    smoothed the same way (before, only switching was). k counts the cycles since the
    target last changed (N: settled, the machine may rest). A held column (COMP …
    NO_MOVE) keeps its previous output, and the filter sees that output: released, it
    ramps from there to the target."""
    c = CROSSTALK
    n = I7[NCYC, i, c]  # (<= XT_ORDER_MAX: the kernel clamps it when the lists load)
    target = F7[PREV, i, c] if B7[HELD, i, c] else F7[TGT, i, c]
    if B7[EVENT, i, c] or target != F7[HIST, i, c]:
        I7[KIDX, i, c] = 0
    I7[KIDX, i, c] = min(I7[KIDX, i, c] + 1, n)
    for j in range(n - 1, 0, -1):
        F7[HIST + j, i, c] = F7[HIST + j - 1, i, c]
    F7[HIST, i, c] = target
    out = target  # settled (the last n targets are this one): exactly it, no rounding
    if n > 1 and I7[KIDX, i, c] < n:
        w = I7[WOFF, i, c]
        out = 0.0
        for j in range(n):
            out += (weights[w + j] - weights[w + j + 1]) * F7[HIST + j, i, c]
    F7[ACT, i, c] = F7[PREV, i, c] if B7[HELD, i, c] else out


@compiled
def _lsec(
    i: int,
    F7: np.ndarray,
    B7: np.ndarray,
    F1: np.ndarray,
    P: np.ndarray,
    IP: np.ndarray,
    tab: np.ndarray,
    pos: np.ndarray,
) -> None:
    """LSEC's target (000 §4.4): at the command position plus this cycle's filtered
    cross and plane outputs (or the command position alone)."""
    if not B7[EFF, i, LEAD]:
        F7[TGT, i, LEAD] = 0.0
        return
    q = pos[i] if IP[LS_CMD, i] else pos[i] + F7[ACT, i, CROSS] + F7[ACT, i, PLANE]
    F7[TGT, i, LEAD] = lsec_target(
        tab,
        IP[LS_POS, i],
        IP[LS_NEG, i],
        IP[LS_N, i],
        F1[DIR, i],
        q,
        IP[LS_WRAP, i] != 0,
        P[LS_X0, i],
        P[LS_PER, i],
    )


@compiled
def _friction(i: int, k: KernelState, wpos: int, vel: float, rev_in: int) -> None:
    """Friction (000 §4.5): this cycle's value into the axis' delay line, the value
    written `delay_cycles` ago out (0 while not effective)."""
    F7, B7, F1, P, IP, ring, tab = k.F7, k.B7, k.F1, k.P, k.IP, k.ring, k.tab
    cur = 0.0
    tgt = 0.0
    eff = B7[EFF, i, FRICT]
    if eff:
        tgt = friction_base(tab, IP[FR_T, i], IP[FR_N, i], P[FR_SCALE, i], vel)
        cur = friction_weigh(tgt, IP[FR_LOOK, i], rev_in, P[FR_PD, i], F1[PATH, i])
    F7[TGT, i, FRICT] = tgt
    ring[wpos, i] = cur
    if eff:
        F7[ACT, i, FRICT] = ring[(wpos - IP[FR_DELAY, i]) % RING, i]
    else:
        F7[ACT, i, FRICT] = 0.0


@compiled
def step(
    kernel: Packed,
    pos: np.ndarray,
    vel: np.ndarray,
    acc: np.ndarray,
    homed: np.ndarray,
    rev_in: np.ndarray,
) -> None:
    """One GEO cycle for every axis of `kernel` (a packed `KernelState`; the module
    docstring; docs/design.md §5.1 step 3) with the command position, velocity and
    acceleration, the homing flags and the cycles until a known reversal (< 0: none) of
    every axis."""
    k = KernelState(*kernel)
    F7, B7, I7, F1, B1, P, IP, G, tab, weights = (
        k.F7, k.B7, k.I7, k.F1, k.B1, k.P, k.IP, k.G, k.tab, k.weights,
    )  # fmt: skip
    n = F7.shape[1]
    first = G[FIRST] != 0
    wpos = G[RING_POS]
    for i in range(n):
        # direction: the sign of the command velocity, the last one held at standstill
        # (docs/design.md §3.6)
        v = vel[i]
        s = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
        rev = s != 0.0 and s != F1[DIR, i]
        if s != 0.0:
            F1[DIR, i] = s
        B1[REV, i] = rev
        for c in range(7):
            F7[PREV, i, c] = F7[ACT, i, c]
        _effective(i, k, homed, rev)
        _targets(i, F7, F1, P, IP, B7, tab, pos, vel, acc)
        for c in (BC, TEMP, CROSS, PLANE):
            _filter(i, c, F7, B7, I7, weights)
        _smooth(i, F7, B7, I7, weights)
        _lsec(i, F7, B7, F1, P, IP, tab, pos)
        if rev and B7[EFF, i, LEAD] and IP[LS_NEG, i] != IP[LS_POS, i]:
            # a bilateral LSEC (its own table per direction) reverses (P-AXIS-00243)
            B7[EVENT, i, LEAD] = True
        _filter(i, LEAD, F7, B7, I7, weights)
        # friction's path since the last reversal or standstill: its current builds up
        # over position_delay after either ("during start-up", 000 p.76-77)
        if rev or s == 0.0:
            F1[PATH, i] = 0.0
        F1[PATH, i] += abs(pos[i] - (pos[i] if first else F1[POSP, i]))
        _friction(i, k, wpos, v, rev_in[i])
        total = 0.0
        for c in (BC, TEMP, CROSS, PLANE, LEAD, CROSSTALK):
            F7[DELTA, i, c] = F7[ACT, i, c] - F7[PREV, i, c]
            total += F7[ACT, i, c]
        F7[DELTA, i, FRICT] = F7[ACT, i, FRICT] - F7[PREV, i, FRICT]
        F1[TOTAL, i] = total
        F1[POSP, i] = pos[i]
    G[RING_POS] = wpos + 1 if wpos < RING - 1 else 0
    G[FIRST] = 0
    G[PENDING] = 0


@compiled
def steps(
    kernel: Packed,
    pos: np.ndarray,
    vel: np.ndarray,
    acc: np.ndarray,
    homed: np.ndarray,
    rev_in: np.ndarray,
    total: np.ndarray,
) -> None:
    """`step` for each row of the commands ([b, n]: a pass of b cycles), every cycle's
    total offset into `total` ([b, n])."""
    F1 = KernelState(*kernel).F1
    for b in range(pos.shape[0]):
        step(kernel, pos[b], vel[b], acc[b], homed, rev_in[b])
        total[b] = F1[TOTAL]


__all__ = ["step", "steps"]
