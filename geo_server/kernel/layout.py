"""Where the kernel keeps its state and its tables (docs/design.md §13.3).

Everything the compiled cycle (`kernel.step`) reads and writes lives in a few arrays, so
a call hands over a handful of them instead of dozens; the names below are the rows of
those arrays (compile-time constants of the compiled code). The machine and the tests
see rows and blocks of them as the kernel's named arrays (`Kernel.actual`, …).

* `F7` [NF7, n, 7] floats and `B7` [NB7, n, 7] booleans: one [n, 7] block per quantity of
  every axis and compensation column (`common.COMP_ORDER`);
* `I7` [NI7, n, 7] integers: the sin² filter's k and length N per column, and where its
  weights start;
* `homing` [n, 7, HOMING_MAX] integers and `homing_n` [n, 7]: the axes (slots) that must
  be homed for a column of an axis to act, and how many of them there are (whether the
  column is configured at all is `B7[CONF]`);
* `F1` [NF1, n] floats and `B1` [NB1, n] booleans: one vector per per-axis quantity;
* `P` [NP, n] floats and `IP` [NIP, n] integers: the per-axis parameters and table
  offsets of one load of the lists (refilled in place on reload);
* `G` [NG] integers: the kernel's scalars;
* `ring` [RING, n]: the friction delay line; `tab`: the tables of one load
  (`tables.Packer`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class KernelState(NamedTuple):
    """What the compiled cycle takes of the kernel (`Kernel.state`): its arrays, named
    (numba passes a named tuple of arrays as one argument)."""

    F7: np.ndarray
    B7: np.ndarray
    I7: np.ndarray
    F1: np.ndarray
    B1: np.ndarray
    P: np.ndarray
    IP: np.ndarray
    G: np.ndarray
    ring: np.ndarray
    tab: np.ndarray
    weights: np.ndarray
    homing: np.ndarray
    homing_n: np.ndarray


# ---- F7: [n, 7] float blocks
ACT, TGT, PREV, DELTA, JUMP = range(5)
#: crosstalk: its last targets, HIST the latest (000 p.83: its values pass the sin²
#: filter, of order n_cycles <= XT_ORDER_MAX, 000 p.87); in column CROSSTALK only
HIST = 5
XT_ORDER_MAX = 20
NF7 = HIST + XT_ORDER_MAX

# ---- B7: [n, 7] boolean blocks
EFF, SEL, HELD, PRE, PEND, EVENT, CONF = range(7)
NB7 = 7

# ---- I7: [n, 7] integer blocks
KIDX, NCYC, WOFF = range(3)
NI7 = 3
#: the most axes one column needs homed (a plane compensation: its two masters)
HOMING_MAX = 2

# ---- F1: per-axis float vectors (state)
(
    TOTAL,  # Σ columns but friction
    POSP,  # the previous cycle's command position
    DIR,  # the direction held (±1)
    PATH,  # friction: path since the last reversal
    TC_COEF,  # live TEMPC parameters (000 §3.2.3 objects 0x43–0x45)
    TC_OFF0,
    TC_POS0,
) = range(7)
NF1 = 7
#: the live TEMPC parameters' rows, in the order of `TempcObjects.fields`
TEMPC_ROWS = (TC_COEF, TC_OFF0, TC_POS0)

# ---- B1: per-axis boolean vectors (state)
DRIVE, REV = range(2)  # drive enabled (SIM::drive_enable); a reversal this cycle
NB1 = 2

# ---- P: per-axis float parameters of one load
(
    INIT_DIR,  # start-up direction (P-AXIS-00021)
    LOSE,  # backlash (P-AXIS-00041)
    PERIOD,  # modulo period of the axis (1 on other axes)
    PL_START1,  # plane: start and interval of master 1 and 2
    PL_START2,
    PL_INT1,
    PL_INT2,
    LS_X0,  # LSEC: first setpoint and the table's period
    LS_PER,
    FR_SCALE,  # friction: scaling_factor/1000, position_delay
    FR_PD,
    XT_INV_ACC,  # crosstalk: 1/|a_ref| accelerating, decelerating
    XT_INV_DEC,
) = range(13)
NP = 13

# ---- IP: per-axis integer parameters and table offsets of one load
(
    MODULO,  # the axis is a modulo axis
    CR_M,  # cross: master slot, table offset, points
    CR_T,
    CR_N,
    PL_M1,  # plane: master slots, table offset, columns (master 1), rows (master 2)
    PL_M2,
    PL_T,
    PL_NI,
    PL_NJ,
    LS_POS,  # LSEC: table offsets (positive, negative direction), points, wraps,
    LS_NEG,  # lookup at the command position alone (set_pos_without_comp)
    LS_N,
    LS_WRAP,
    LS_CMD,
    FR_T,  # friction: table offset (|v| in µm/s), points, delay cycles, lookahead
    FR_N,
    FR_DELAY,
    FR_LOOK,
    XT_KIND,  # crosstalk: `crosstalk.MODE1` … `OLD`, 0 none
    XT_DYN,  # dynamic master, position masters
    XT_P1,
    XT_P2,
    XT_VELDEP,  # velocity dependent
    XT_T,  # modes 1/2/old: table offset, points; mode 3: points, triangles, edges
    XT_N,
    XT_TRI,
    XT_NTRI,
    XT_EDGE,
    XT_NEDGE,
) = range(29)
NIP = 29

# ---- G: scalars
RING_POS, FIRST, PENDING = range(3)  # delay line's write row, no step yet, an event pending
NG = 3
