"""Friction compensation (000 §4.5 p.64–79; docs/design.md §6.6): its law.

The value a cycle writes into the axis' delay line is sign(v)·scaling_factor/1000·
table(|v|) (|v| in µm/s), weighed before a known reversal by r/(lookahead + 1) for the r
cycles left (0 ≤ r ≤ lookahead) and after it, or after a standstill ("the motor current
is built up during start-up", 000 p.76), by min(1, path since the reversal or the
standstill / position_delay); the axis gets the value written `delay_cycles` ago (<
`RING`).
"""

from __future__ import annotations

import numpy as np

from geo_server.jit import compiled
from geo_server.kernel.tables import interp
from geo_server.units import UNITS_PER_UM

RING = 249  # friction delay line length: delay_cycles < 249 (000 p.79)


@compiled
def base(tab: np.ndarray, off: int, m: int, scale: float, vel: float) -> float:
    """sign(v)·scaling_factor/1000·table(|v|) of an axis moving at `vel` (units/s)."""
    sign = 1.0 if vel > 0 else (-1.0 if vel < 0 else 0.0)
    return sign * scale * interp(tab, off, m, abs(vel) / UNITS_PER_UM)


@compiled
def weigh(
    value: float, lookahead: int, reversal_in: int, position_delay: float, path: float
) -> float:
    """`value` weighed `reversal_in` cycles before a known reversal (< 0: none) and
    `path` past the last one: what the cycle writes into the delay line."""
    if lookahead > 0 and 0 <= reversal_in <= lookahead:  # before the zero crossing
        value = value * (reversal_in / (lookahead + 1))
    if position_delay > 0:  # after it
        value *= min(1.0, path / position_delay)
    return value
