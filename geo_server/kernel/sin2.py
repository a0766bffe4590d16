"""The sin² step-event filter (SPEC §3; 000 §2.3.2 P-AXIS-00243, §3.2 p.18, Fig. 7).

When a step event makes the target of a compensation jump, the output follows

    out_k = target_k − J·cos²(π·k / (2N)),   k = 1 … N,

with J = target − out at the event (target of the event cycle, output of the previous
cycle) and k = 1 in the event cycle; for k ≥ N the output equals the target. N ≤ 1 is a
jump in the event cycle. A moving target is tracked while the jump J decays; a new event
restarts the ramp from the current output. For the manual's backlash example (lose 1000,
n_backlash_cyc 10, reversal from 0) this is −1000·sin²(πk/20).
"""

from __future__ import annotations

import math

import numpy as np


def sin2_weight(k: int, n: int) -> float:
    """cos²(π·min(k, N)/(2N)): the share of the jump J still left in cycle k."""
    n = max(1, n)
    return math.cos(math.pi * min(k, n) / (2 * n)) ** 2


class Sin2Filter:
    """Vectorised sin² filter over an `[n, m]` block of compensation columns.

    State per entry: the jump `J` of the last event, the cycle counter `k` (saturating at
    N) and N (≥ 1). Works on views (e.g. columns 0:4 of the kernel's [n, 7] arrays).
    """

    def __init__(self, n_cycles: np.ndarray) -> None:
        self.n = np.maximum(np.asarray(n_cycles, dtype=float), 1.0)
        self.half_pi_over_n = (math.pi / 2) / self.n
        self.jump = np.zeros_like(self.n)
        self.k = self.n.copy()  # idle: ramp finished
        self._w = np.zeros_like(self.n)

    def set_n(self, n_cycles: np.ndarray) -> None:
        """New filter lengths (reload); a running ramp continues with the new N."""
        np.maximum(np.asarray(n_cycles, dtype=float), 1.0, out=self.n)
        np.divide(math.pi / 2, self.n, out=self.half_pi_over_n)
        np.minimum(self.k, self.n, out=self.k)

    def step(
        self, target: np.ndarray, prev_out: np.ndarray, event: np.ndarray, out: np.ndarray
    ) -> None:
        """out = filtered target; `event` marks entries with a step event this cycle."""
        w = self._w
        # J = target − previous output where an event happens; restart k at 0
        np.subtract(target, prev_out, out=w)
        np.copyto(self.jump, w, where=event)
        np.copyto(self.k, 0.0, where=event)
        self.k += 1.0
        np.minimum(self.k, self.n, out=self.k)
        np.multiply(self.k, self.half_pi_over_n, out=w)
        np.cos(w, out=w)
        np.multiply(w, w, out=w)
        np.multiply(w, self.jump, out=w)
        np.subtract(target, w, out=out)
