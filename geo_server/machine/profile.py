"""The motion's per-cycle work, compiled (docs/design.md §5 "Motion", §13.3): the rows of
its arrays, the bundle it hands the compiled cycle (`MotionState`) and the laws — a
cycle of every axis' profile (`profile_step`), the cycles until a known reversal
(`reversal_in`) and the displayed positions (`display`). `Motion` (motion.py) is the
Python class that owns them; the profile model is its docstring's."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from geo_server.jit import compiled

# Rows of the motion's arrays (`Motion.F`, `Motion.I`, `Motion.B`; compile-time
# constants of `profile_step`). Floats: the commands, the limits, the profile of each
# axis' move (start, signed distance, acceleration time, start of deceleration, total
# time, normalised peak velocity and jerk, u at the end of phase A), the directions and
# the queued move.
(
    POS,
    VEL,
    ACC,
    TARGET,
    FEED,
    V_MAX,
    A_MAX,
    PERIOD,
    P0,
    DIST,
    TA,
    TD,
    TT,
    W,
    J,
    UB0,
    DIR,
    NEXT_DIR,
    Q_TARGET,
    Q_FEED,
) = range(20)
NF = 20
K, NC = range(2)  # integers: steps taken, duration in cycles
NI = 2
HOMED, MODULO, MOVING, QUEUED, DONE = range(5)  # booleans
NB = 5
#: `profile_step`'s result: an axis arrived this cycle; one of them has a queued move
ARRIVED, START_QUEUED = 1, 2


class MotionState(NamedTuple):
    """What the compiled cycle takes of the motion (`Motion.state`): its arrays (rows
    above) and the cycle time."""

    F: np.ndarray
    I: np.ndarray  # noqa: E741
    B: np.ndarray
    dt: float


@compiled
def profile_step(F: np.ndarray, I: np.ndarray, B: np.ndarray, dt: float) -> int:  # noqa: E741
    """One cycle of every moving axis (see the module docstring): the profile sampled at
    t = k·dt after k steps, phases A, B, C; in the cycle a move reaches its duration the
    axis snaps to its target with vel = acc = 0. Returns `ARRIVED` | `START_QUEUED`
    (an arrived axis has a queued move: `Motion.start_queued`)."""
    flags = 0
    for s in range(F.shape[1]):
        B[DONE, s] = False
        if not B[MOVING, s]:
            continue
        k = I[K, s] + 1
        I[K, s] = k
        t = k * dt
        j = F[J, s]
        u = t * t * 0.5 * j  # phase A
        du = j * t
        ddu = j
        if t >= F[TA, s]:  # phase B
            u = (t - F[TA, s]) * F[W, s] + F[UB0, s]
            du = F[W, s]
            ddu = 0.0
        if t >= F[TD, s]:  # phase C
            r = F[TT, s] - t
            u = r * r * j * -0.5 + 1.0
            du = j * r
            ddu = -j
        if k >= I[NC, s]:
            F[POS, s] = F[TARGET, s]
            F[VEL, s] = 0.0
            F[ACC, s] = 0.0
            B[MOVING, s] = False
            B[DONE, s] = True
            flags |= ARRIVED | (START_QUEUED if B[QUEUED, s] else 0)
        else:
            dist = F[DIST, s]
            F[POS, s] = dist * u + F[P0, s]
            F[VEL, s] = dist * du
            F[ACC, s] = dist * ddu
    return flags


@compiled
def reversal_in(F: np.ndarray, I: np.ndarray, out: np.ndarray) -> None:  # noqa: E741
    """Cycles until the planned velocity changes sign, per axis (−1 if none known).

    A reversal is known when the next move (queued with `queue_next` or announced with
    `announce_next`) goes against the current/last move direction. The value is the
    number of `step()` calls until the current move arrives at rest, 0 when the axis
    already rests and the next move will reverse it, else −1."""
    for s in range(F.shape[1]):
        out[s] = I[NC, s] - I[K, s] if F[NEXT_DIR, s] * F[DIR, s] < 0.0 else -1


@compiled
def display(F: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    """The command positions with modulo axes wrapped into [0, period) (docs/design.md
    §3.8): what objects and HMIs show (the motion and the kernel keep them unwrapped)."""
    for s in range(F.shape[1]):
        x = F[POS, s]
        if B[MODULO, s]:
            x = x % F[PERIOD, s]
            if x >= F[PERIOD, s]:  # (a tiny negative position gives the period itself)
                x -= F[PERIOD, s]
        out[s] = x
