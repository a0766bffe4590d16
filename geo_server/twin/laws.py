"""The twin's per-cycle work, compiled (docs/twin.md; docs/design.md §13.3): the rows
of its arrays, the bundles it hands the compiled cycle (`TwinState`, `Geometry`) and the
laws — the thermal update and the sensors' samples of a cycle (`twin_cycle`, steps 1-3 of
`engine`'s docstring), a stretch at rest (`rest_cycles`), the errors at the drive
positions (`errors`, steps 4-5). `TwinEngine` (engine.py) is the Python class that owns
them."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from geo_server.faults import OPEN_CIRCUIT_C
from geo_server.jit import Packed, compiled
from geo_server.kernel.tables import interp
from geo_server.twin.noise import STATE, normal

#: Increments per second to m/s (linear) or to 1000 °/s (rotary).
V_SCALE = 1e-7

# Rows of the compiled cycle's arrays (`TwinEngine.A`, `.N`, `.S`, `.C`; compile-time
# constants of `twin_cycle`). Per axis: the motion heat summed since the last thermal
# update, sign(v) of the last cycle, the direction held, the lost motion's parameters,
# the scatter of the last approach, the error line A·pos + B and its parameters, and
# (as floats) the thermal node of its expansion.
(
    VSUM,
    SIGN_BEFORE,
    DIRECTION,
    REF_DIR,
    HALF_REVERSAL,
    SCATTER_NOW,
    OFFSET,
    LINE_A,
    LINE_B,
    LIN_OFF,
    LIN_SLOPE,
    LIN_REF,
    EXP_COEF,
    EXP_REF,
    EXP_NODE,
    AXIS_SENSOR,  # the sensor shown on the axis (−1: none)
    SENSOR_TEMP,  # TWIN::sensor_temperature: its sensor's value, else the reference
) = range(17)
NA = 17
# per thermal node: temperature, 1 − e^(−dt/τ), motion gain, spindle gain, motion axis
NODE_TEMP, NODE_K, MOTION_GAIN, SPINDLE_GAIN, MOTION_SLOT = range(5)
NN = 5
# per sensor: its node, its noise σ and the σ a "noisy" fault adds, its resolution (and
# 1/resolution when that is a whole number: the decimal it shows), its period, the time
# of its next sample, its value, its fault (`FAULTS`)
S_NODE, S_NOISE, S_EXTRA, S_RES, S_INV_RES, S_PERIOD, S_DUE, S_VALUE, S_FAULT = range(9)
NSN = 9
#: the sensor faults (docs/faults.md), by their code in the row S_FAULT
FAULTS = ("", "stuck", "noisy", "open")
STUCK, OPEN = 1, 3
# scalars: simulated seconds per cycle, the next sample's time, the ambient
# temperature, whether it is held (a climate chamber), the reference temperature, the
# seeded noise's stream (`noise`, its six values from RNG)
DT, NEXT_SAMPLE, AMBIENT, HELD, T_REF, RNG = range(6)
NS = RNG + STATE
CYCLES, EVERY = range(2)  # integer scalars: cycles run, cycles between thermal updates
NC = 2
#: `twin_cycle`'s result: it took a sensor sample; a velocity changed sign (the scatter
#: of an arrival: `TwinEngine.events`, Python's)
SAMPLED, MOTION = 1, 2


class TwinState(NamedTuple):
    """What the compiled cycle takes of the twin (`TwinEngine.state`, `twin_cycle`'s
    arrays): per axis, per node, per sensor, its scalars and counters, the ambient
    profile."""

    A: np.ndarray
    N: np.ndarray
    SN: np.ndarray
    S: np.ndarray
    C: np.ndarray
    amb: np.ndarray


class Geometry(NamedTuple):
    """The twin's geometric errors as `errors` takes them (step 4): squareness [n, n],
    the tables, the curves (integers: table, points, over which axis, onto which; floats:
    period, weight) and the grids over two axes (integers, floats)."""

    square: np.ndarray
    tab: np.ndarray
    curve_i: np.ndarray
    curve_f: np.ndarray
    grid_i: np.ndarray
    grid_f: np.ndarray


@compiled
def grid_error(tab: np.ndarray, off: int, rows: int, cols: int, u: float, v: float) -> float:
    """Bilinear interpolation on a grid of `rows` × `cols` errors at `off`, edges held,
    at the grid coordinates (u, v) = ((p1 − start1)/step1, (p2 − start2)/step2)."""
    u = min(max(u, 0.0), cols - 1.0)
    v = min(max(v, 0.0), rows - 1.0)
    i = min(int(u), cols - 2) if cols > 1 else 0
    j = min(int(v), rows - 2) if rows > 1 else 0
    fu, fv = u - i, v - j
    i1, j1 = min(i + 1, cols - 1), min(j + 1, rows - 1)
    r0, r1 = off + j * cols, off + j1 * cols
    top = tab[r0 + i] + (tab[r0 + i1] - tab[r0 + i]) * fu
    bottom = tab[r1 + i] + (tab[r1 + i1] - tab[r1 + i]) * fu
    return float(top + (bottom - top) * fv)


@compiled
def errors(
    A: np.ndarray,
    E: np.ndarray,
    geometry: Packed,
    output: np.ndarray,
    command: np.ndarray,
    velocity: np.ndarray,
    O: np.ndarray,  # noqa: E741
) -> None:
    """The errors at the drive positions `output` (the module docstring, step 4; the
    geometric ones of `geometry`, a packed `Geometry`) and what follows from them (step
    5), into the rows of `O`: error, true position, residual (true − `command`), friction
    current sign(v)·c + k·v of the drive."""
    g = Geometry(*geometry)
    square, tab, curve_i, curve_f = g.square, g.tab, g.curve_i, g.curve_f
    grid_i, grid_f = g.grid_i, g.grid_f
    n = len(output)
    e = O[0]
    for i in range(n):
        # linear scale error and thermal expansion (A·pos + B, A and B from the
        # temperatures), lost motion and scatter: A·pos + offset; the cyclic error
        x = output[i]
        e[i] = x * A[LINE_A, i] + A[OFFSET, i]
        if E[0, i] != 0.0:
            e[i] += math.sin(x * E[1, i]) * E[0, i]
    for k in range(curve_i.shape[1]):  # pitch (per direction) and straightness curves
        q = output[curve_i[2, k]]
        if curve_f[0, k] > 0.0:
            q = q % curve_f[0, k]
        e[curve_i[3, k]] += interp(tab, curve_i[0, k], curve_i[1, k], q) * curve_f[1, k]
    for k in range(grid_i.shape[1]):  # grids over two axes
        u = (output[grid_i[4, k]] - grid_f[0, k]) / grid_f[1, k]
        v = (output[grid_i[5, k]] - grid_f[2, k]) / grid_f[3, k]
        e[grid_i[3, k]] += grid_error(tab, grid_i[0, k], grid_i[1, k], grid_i[2, k], u, v)
    for i in range(n):  # squareness
        sq = 0.0
        for j in range(n):
            sq += square[i, j] * output[j]
        e[i] += sq
    for i in range(n):
        O[1, i] = output[i] + e[i]
        O[2, i] = O[1, i] - command[i]
        if E[2, i] != 0.0 or E[3, i] != 0.0:  # (else 0, never −0)
            v = velocity[i]
            sign = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
            O[3, i] = sign * E[2, i] + v * E[3, i]


@compiled
def ambient_at(t: float, amb: np.ndarray) -> float:
    """The ambient temperature at simulated time `t` of the profile `amb` ([time s,
    temperature °C] rows; linear, held outside): numpy's `interp` formula for one x
    (slope·(x − xp[j]) + fp[j] inside, with its fallbacks for an infinite slope)."""
    xp, fp = amb[0], amb[1]
    m = len(xp)
    if t < xp[0]:
        return float(fp[0])
    if t >= xp[m - 1]:
        return float(fp[m - 1])
    j = np.searchsorted(xp, t, side="right") - 1
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    y = slope * (t - xp[j]) + fp[j]
    if y != y:  # NaN (an infinite slope): numpy's fallbacks
        y = slope * (t - xp[j + 1]) + fp[j + 1]
        if y != y and fp[j] == fp[j + 1]:
            y = fp[j]
    return float(y)


@compiled
def offsets(A: np.ndarray) -> None:
    """offset = B + lost motion + scatter per axis. Lost motion while moving against the
    reference direction: direction is ±1, so −direction·reversal·[direction ≠
    reference] = −(direction − reference)·reversal/2."""
    for i in range(A.shape[1]):
        o = (A[DIRECTION, i] - A[REF_DIR, i]) * -A[HALF_REVERSAL, i]
        A[OFFSET, i] = o + A[LINE_B, i] + A[SCATTER_NOW, i]


@compiled
def lines(A: np.ndarray, N: np.ndarray, S: np.ndarray) -> None:
    """error = slope·(pos − ref) + offset + coef·ΔT·(pos − exp_ref) = A·pos + B, ΔT the
    temperature of the axis' expansion node over the reference temperature."""
    nodes = N.shape[1]
    for i in range(A.shape[1]):
        dt = N[NODE_TEMP, int(A[EXP_NODE, i])] - S[T_REF] if nodes else 0.0
        c = A[EXP_COEF, i] * dt
        A[LINE_A, i] = A[LIN_SLOPE, i] + c
        A[LINE_B, i] = A[LIN_OFF, i] - (A[LIN_SLOPE, i] * A[LIN_REF, i] + c * A[EXP_REF, i])


@compiled
def thermal(
    A: np.ndarray, N: np.ndarray, S: np.ndarray, amb: np.ndarray, t: float, spindle: bool
) -> None:
    """Advance the nodes by `thermal_every` cycles, exactly for a first-order system
    with the mean |v| of those cycles as the motion heat, T += (T_target − T)·(1 −
    e^(−dt/τ)); then the error lines and their offset."""
    nodes = N.shape[1]
    if nodes:
        if not S[HELD]:
            S[AMBIENT] = ambient_at(t, amb)
        ambient = S[AMBIENT]
        for k in range(nodes):
            target = A[VSUM, int(N[MOTION_SLOT, k])] * N[MOTION_GAIN, k] + ambient
            if spindle:
                target = target + N[SPINDLE_GAIN, k]
            N[NODE_TEMP, k] = N[NODE_TEMP, k] + (target - N[NODE_TEMP, k]) * N[NODE_K, k]
    for i in range(A.shape[1]):
        A[VSUM, i] = 0.0
    lines(A, N, S)
    offsets(A)


@compiled
def quantize(value: float, resolution: float, inverse: float) -> float:
    """A sensor's reading of `value`: rounded to its resolution (half to even), shown as
    the decimal k/inverse when 1/resolution is a whole number `inverse` (20.02, not
    20.020000000000003); a resolution ≤ 0 keeps the value."""
    if resolution <= 0.0:
        return value
    k = np.rint(value / resolution)
    return float(k / inverse if inverse > 0.0 else k * resolution)


@compiled
def sample(A: np.ndarray, N: np.ndarray, SN: np.ndarray, S: np.ndarray, t: float) -> None:
    """The sensors due at simulated time `t` take a sample (the module docstring, step 3):
    the node's temperature plus the seeded noise (`noise.normal`; a "noisy" fault widens
    σ, with the same draws), rounded to the resolution; a stuck sensor keeps its reading
    (its draw is taken all the same), an open one reads `OPEN_CIRCUIT_C`. The next sample
    is one period after the one due (never drifting with dt); the axes show their
    sensors' readings."""
    nxt = np.inf
    for k in range(SN.shape[1]):
        due = SN[S_DUE, k]
        if due <= t:
            sigma = math.hypot(SN[S_NOISE, k], SN[S_EXTRA, k])
            raw = N[NODE_TEMP, int(SN[S_NODE, k])] + normal(S, RNG) * sigma
            fault = SN[S_FAULT, k]
            if fault == OPEN:
                SN[S_VALUE, k] = OPEN_CIRCUIT_C
            elif fault != STUCK:
                SN[S_VALUE, k] = quantize(raw, SN[S_RES, k], SN[S_INV_RES, k])
            period = SN[S_PERIOD, k]
            due += period * math.ceil((t - due) / period + 1e-12)
            SN[S_DUE, k] = due
        nxt = min(nxt, due)
    S[NEXT_SAMPLE] = nxt
    for i in range(A.shape[1]):
        k = int(A[AXIS_SENSOR, i])
        if k >= 0:
            A[SENSOR_TEMP, i] = SN[S_VALUE, k]


@compiled
def twin_cycle(
    A: np.ndarray,
    N: np.ndarray,
    SN: np.ndarray,
    S: np.ndarray,
    C: np.ndarray,
    amb: np.ndarray,
    velocity: np.ndarray,
    spindle: bool,
) -> int:
    """One cycle of the twin's state (the module docstring, steps 1–3): the time, the
    motion heat |v|, the thermal update when due, the sensor samples due. Returns
    `SAMPLED` | `MOTION` (a velocity changed sign: `TwinEngine.events`)."""
    c = C[CYCLES] + 1
    C[CYCLES] = c
    flags = 0
    for i in range(A.shape[1]):
        v = velocity[i]
        A[VSUM, i] += abs(v)
        s = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
        if s != A[SIGN_BEFORE, i]:
            flags |= MOTION
    t = c * S[DT]
    if c % C[EVERY] == 0:
        thermal(A, N, S, amb, t, spindle)
    if t >= S[NEXT_SAMPLE]:
        sample(A, N, SN, S, t)
        flags |= SAMPLED
    return flags


#: `first_sample` when no sample is due (no sensors)
NEVER = 1 << 62


@compiled
def first_sample(cycles: int, dt: float, due: float) -> int:
    """The first cycle after `cycles` at which `twin_cycle` flags a sample due at `due`
    (s): the first c with c·dt ≥ due — the product `twin_cycle` compares, so the same
    cycle exactly."""
    if not due < np.inf or dt <= 0.0:
        return NEVER
    c = max(cycles + 1, math.ceil(due / dt))
    while c - 1 > cycles and (c - 1) * dt >= due:
        c -= 1
    while c * dt < due:
        c += 1
    return c


@compiled
def rest_cycles(
    end: int,
    A: np.ndarray,
    N: np.ndarray,
    SN: np.ndarray,
    S: np.ndarray,
    C: np.ndarray,
    amb: np.ndarray,
    still: np.ndarray,
    spindle: bool,
) -> tuple[int, int]:
    """`twin_cycle` at rest (`still`: every velocity 0) until cycle `end` or a cycle
    that needs Python (`MOTION`): (thermal updates and samples run, the flags of the
    cycle it stopped at).
    At rest a cycle changes nothing but the counter (|v| adds 0, no sign changes) unless
    a thermal update or a sample falls in it, so the loop goes from one such cycle to
    the next — the numbers of every cycle run, at the cost of the events."""
    events = 0
    every = C[EVERY]
    resting = True
    for i in range(A.shape[1]):
        resting = resting and A[SIGN_BEFORE, i] == 0.0
    while C[CYCLES] < end:
        c = C[CYCLES]
        if resting:
            nxt = min((c // every + 1) * every, first_sample(c, S[DT], S[NEXT_SAMPLE]), end)
            C[CYCLES] = nxt - 1
        flags = twin_cycle(A, N, SN, S, C, amb, still, spindle)
        if C[CYCLES] % every == 0 or flags & SAMPLED:
            events += 1
        if flags & MOTION:
            return events, flags
    return events, 0
