"""Leadscrew error compensation LSEC (000 §4.4 p.50–63; docs/design.md §6.5): its law.

The table holds measured errors Δs = s_actual − s_programmed, so the compensation applies
−Δs, looked up at the command position plus this cycle's filtered cross and plane outputs
(the command position alone with `set_pos_without_comp`) — after the sin² filter of the
other columns, with its own filter column. Bilateral: the negative table while the axis
moves (or last moved) negative. A modulo table wraps the position into [first setpoint,
first setpoint + period): the axis' period on a modulo axis, else the distance between
the first and the last setpoint (000 §4.4: they are one period apart).
"""

from __future__ import annotations

import numpy as np

from geo_server.jit import compiled
from geo_server.kernel.tables import interp


@compiled
def target(
    tab: np.ndarray,
    pos_table: int,
    neg_table: int,
    m: int,
    direction: float,
    q: float,
    wrap: bool,
    x0: float,
    period: float,
) -> float:
    """−Δs at the lookup position `q` for the axis moving in `direction` (±1); the
    tables at `pos_table` and `neg_table` (the same one when unilateral)."""
    if wrap:
        q = x0 + (q - x0) % period
    return -interp(tab, neg_table if direction < 0 else pos_table, m, q)
