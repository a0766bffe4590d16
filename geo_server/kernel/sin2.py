"""The sin² step-event filter (docs/design.md §3.4; 000 §2.3.2 P-AXIS-00243, §3.2 p.18,
Fig. 7).

When a step event makes the target of a compensation jump, the output follows

    out_k = target_k − J·cos²(π·k / (2N)),   k = 1 … N,

with J = target − out at the event (target of the event cycle, output of the previous
cycle) and k = 1 in the event cycle; for k ≥ N the output equals the target. N ≤ 1 is a
jump in the event cycle. A moving target is tracked while the jump J decays; a new event
restarts the ramp from the current output. For the manual's backlash example (lose 1000,
n_backlash_cyc 10, reversal from 0) this is −1000·sin²(πk/20).

The weight cos²(π·k/(2N)) depends on the integers k and N only, so it is read from a
table made when the lists are loaded (`weights`: the same `math.cos` expression, so the
same numbers) — one load per column and cycle instead of a cosine. N = 0 marks an
unfiltered column (the friction column: weight exactly 0, out = target).
"""

from __future__ import annotations

import math

import numpy as np

from geo_server.jit import compiled


def weights(lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weight table of every filter length in `lengths` ([n, 7] ints) and, per
    column, the offset of its length's weights: w(k) = table[offset + k], k = 0 … N."""
    table: list[float] = []
    start: dict[int, int] = {}
    for m in sorted({int(v) for v in np.ravel(lengths)}):
        start[m] = len(table)
        if m <= 0:
            table.append(0.0)
        else:
            table.extend(math.cos(math.pi * float(j) / (2 * m)) ** 2 for j in range(m + 1))
    offsets = np.vectorize(start.__getitem__, otypes=[np.int64])(np.asarray(lengths))
    return np.array(table), offsets


@compiled
def output(
    target: float,
    prev: float,
    event: bool,
    k: int,
    n: int,
    jump: float,
    table: np.ndarray,
    woff: int,
) -> tuple[float, int, float]:
    """One column's filtered output (docs/design.md §3.4) and its new (k, J): an event
    restarts the ramp from the previous output, then k ← min(k + 1, N)."""
    if event:
        jump = target - prev
        k = 0
    k = min(k + 1, n)
    return target - jump * table[woff + k], k, jump
