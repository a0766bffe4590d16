"""The twin's seeded noise: sensor noise and the scatter of each approach (docs/twin.md).

A Gaussian stream from the twin file's `seed`, drawn inside the compiled cycle (a sensor
sample) and from Python (a scatter draw at an arrival) alike, so both take their numbers
from one stream in the order the cycles ask for them. The generator is L'Ecuyer's
MRG32k3a (P. L'Ecuyer, "Good parameters and implementations for combined multiple
recursive random number generators", Operations Research 47(1), 1999), in its floating-
point form: six state values below 2³², every product below 2⁵³, so every step is exact in
IEEE double arithmetic — the compiled and the interpreted law give the same numbers. A
normal deviate is Box–Muller's cos branch of two uniform draws.
"""

from __future__ import annotations

import math

import numpy as np

from geo_server.jit import compiled

_M1 = 4294967087.0
_M2 = 4294944443.0
_A12, _A13N = 1403580.0, 810728.0
_A21, _A23N = 527612.0, 1370589.0
_NORM = 2.328306549295728e-10  # 1/(m1 + 1)
#: state values of the stream (`seed`)
STATE = 6


def seed(value: int) -> np.ndarray:
    """The six state values of the stream of `value` (a twin file's seed): drawn from
    numpy's generator of that seed, in [1, m) each (never all zero)."""
    rng = np.random.default_rng(value)
    s1 = rng.integers(1, int(_M1), size=3)
    s2 = rng.integers(1, int(_M2), size=3)
    return np.concatenate([s1, s2]).astype(float)


@compiled
def uniform(state: np.ndarray, at: int) -> float:
    """The next uniform deviate in (0, 1) of the stream whose six values start at
    `state[at]` (advanced in place)."""
    s = at
    p1 = _A12 * state[s + 1] - _A13N * state[s]
    p1 -= int(p1 / _M1) * _M1
    if p1 < 0.0:
        p1 += _M1
    state[s] = state[s + 1]
    state[s + 1] = state[s + 2]
    state[s + 2] = p1
    p2 = _A21 * state[s + 5] - _A23N * state[s + 3]
    p2 -= int(p2 / _M2) * _M2
    if p2 < 0.0:
        p2 += _M2
    state[s + 3] = state[s + 4]
    state[s + 4] = state[s + 5]
    state[s + 5] = p2
    if p1 > p2:
        return float((p1 - p2) * _NORM)
    return float((p1 - p2 + _M1) * _NORM)


@compiled
def normal(state: np.ndarray, at: int) -> float:
    """The next standard normal deviate of the stream at `state[at]` (Box–Muller)."""
    u1 = uniform(state, at)
    u2 = uniform(state, at)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
