"""The sin² step-event filter (docs/design.md §3.4; 000 §2.3.2 P-AXIS-00243, §3.2 p.18,
Fig. 7).

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


class Sin2Filter:
    """Vectorised sin² filter over the kernel's `[n, 7]` columns.

    The weight cos²(π·k/(2N)), the share of the jump J still left in cycle k, only
    depends on the integers k and N, so it is read from a precomputed table (bit-identical
    to evaluating the cosine) instead of evaluating cos per cycle: each entry keeps
    `kidx = offset(N) + k`, and a cycle is "restart at the offset on an event, step,
    saturate at offset + N, gather" — 3 numpy calls for every column at once. N = 0 marks
    an unfiltered column (weight exactly 0: out = target).

    The filter holds the weights and the jumps; the kernel inlines `advance` and applies
    J ← target − out (where event), out = target − J·w itself, in two passes: LSEC's
    target depends on the filtered cross/plane outputs of the same cycle.
    """

    def __init__(self, n_cycles: np.ndarray) -> None:
        shape = np.shape(n_cycles)
        self.kidx = np.zeros(shape, dtype=np.int64)
        self.jump = np.zeros(shape)
        self.w = np.zeros(shape)
        self.set_n(n_cycles, idle=True)

    def set_n(self, n_cycles: np.ndarray, idle: bool = False) -> None:
        """New filter lengths (reload); a running ramp continues with the new N."""
        n_new = np.asarray(n_cycles, dtype=np.int64)
        k = None if idle else self.kidx - self.off  # the running ramps' k
        lengths = sorted({int(v) for v in n_new.ravel()})
        table, start, succ = [], {}, []
        for m in lengths:
            start[m] = b = len(table)
            if m <= 0:
                table.append(0.0)  # unfiltered column
                succ.append(b)
            else:
                table.extend(math.cos(math.pi * float(j) / (2 * m)) ** 2 for j in range(m + 1))
                succ.extend(b + min(j + 1, m) for j in range(m + 1))
        self.table = np.array(table)
        self.succ = np.array(succ, dtype=np.int64)  # index of the next cycle's weight
        self.off = np.vectorize(start.__getitem__, otypes=[np.int64])(n_new)
        n_eff = np.maximum(n_new, 0)
        self.end = self.off + n_eff
        if k is None:  # idle: every ramp done
            k = n_eff
        np.minimum(self.off + k, self.end, out=self.kidx)

    def advance(self, event: np.ndarray) -> None:
        """k ← 0 where an event happens, then k ← min(k + 1, N); w = cos²(πk/(2N))."""
        np.copyto(self.kidx, self.off, where=event)
        self.succ.take(self.kidx, out=self.kidx)  # buffered (mode "raise"): safe in place
        self.table.take(self.kidx, out=self.w)


def output(
    target: np.ndarray, jump: np.ndarray, w: np.ndarray, tmp: np.ndarray, out: np.ndarray
) -> None:
    """out = target − J·w (docs/design.md §3.4): the filtered output of every column, for a
    single cycle (`Kernel.step`) and a pass of steady cycles (`KernelBatch.run`) alike."""
    np.multiply(jump, w, tmp)
    np.subtract(target, tmp, out)
