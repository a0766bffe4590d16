"""Axis motion simulation: synchronised trapezoidal profiles (docs/design.md §5 "Motion").

Pure computation: no I/O, no asyncio, no wall clock. Time only advances by `Motion.step()`,
one call per GEO cycle of length `dt` seconds. The state lives in numpy arrays indexed by
axis *slot* (0…n−1, the order of the `AxisParams` list), so the kernel can read
`pos`/`vel`/`acc` without copying.

Units (docs/design.md §3): positions in internal units (0.1 µm linear, 0.0001° rotary;
1 mm = 1° = 10000 units), velocities in units/s, accelerations in units/s².
`AxisParams.v_max` is already units/s; `AxisParams.a_max` is mm/s² (°/s²) and is scaled
×10000 here.

Profile model. Every move is described per axis by a start position `p0`, a signed
distance `dist` and a *normalised* path profile u(t) rising from 0 to 1:

* phase A (0 ≤ t < ta):        u = ½·j·t²
* phase B (ta ≤ t < T − ta):   u = ½·w·ta + w·(t − ta)
* phase C (T − ta ≤ t < T):    u = 1 − ½·j·(T − t)²

with j = w/ta. A triangular profile has T = 2·ta (phase B empty). All axes of one linear
move (G00/G01) share the same (ta, T, w, j), so they start and arrive together on a
straight line: pos_i = p0_i + dist_i·u(t). The path limits are chosen so that no axis
exceeds its own v_max / a_max (the slowest axis governs). The profile is sampled at
t = k·dt after k steps; the move lasts N = ⌈T/dt⌉ cycles and in cycle N the position is
set to the target exactly (no overshoot, no drift). `vel` and `acc` are the analytic
derivatives at the sample time (0 at rest).

The compiled per-cycle step of these profiles, the rows of the arrays and the bundle the
compiled cycle takes are `profile.py`'s; this is the class that plans moves and owns them.

Modulo rotary axes: `pos` stays *unwrapped* (continuous) for motion and is what the
compensation kernel should read (velocity, reversal and modulo tables are the kernel's
business); `display_pos()` wraps into [0, period) for displayed positions and objects.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from geo_server.errors import GeoError
from geo_server.jit import Packed
from geo_server.machine.profile import (
    A_MAX,
    ACC,
    DIR,
    DIST,
    DONE,
    FEED,
    HOMED,
    MODULO,
    MOVING,
    NB,
    NC,
    NEXT_DIR,
    NF,
    NI,
    P0,
    PERIOD,
    POS,
    Q_FEED,
    Q_TARGET,
    QUEUED,
    START_QUEUED,
    TA,
    TARGET,
    TD,
    TT,
    UB0,
    V_MAX,
    VEL,
    J,
    K,
    MotionState,
    W,
    display,
    profile_step,
    reversal_in,
)
from geo_server.model import AxisParams
from geo_server.units import UNITS_PER_MM

#: Internal units per mm (linear) or per degree (rotary): 0.1 µm / 0.0001°.

#: Tolerance (in cycles) when rounding a move duration up to whole cycles, so that
#: T/dt = 3000.0000000004 still counts as 3000 cycles.
_CYCLE_EPS = 1e-6


class MotionError(GeoError, ValueError):
    """A motion command that cannot be executed (busy axis, bad feed, bad slot)."""


class Motion:
    """Command-position generator for all axes of the machine (docs/design.md §5).

    Public state arrays (float64 [n] unless noted; read them, do not rebind them):
    `pos` command position, `vel` velocity, `acc` acceleration, `target` end position of
    the current (or last) move, `feed` default feed of `move_to` (units/s, = v_max),
    `v_max` units/s, `a_max` units/s², `homed` bool [n], `modulo` bool [n],
    `period` modulo period in units (0 for non-modulo axes).
    """

    def __init__(self, params: Sequence[AxisParams], dt: float) -> None:
        if dt <= 0:
            raise MotionError(f"cycle time must be > 0, got {dt}")
        self.dt = float(dt)
        self.n = n = len(params)
        bad = [p.log_nr for p in params if p.v_max <= 0 or p.a_max <= 0]
        if bad:
            raise MotionError(f"axes {bad}: v_max and a_max must be > 0")
        #: the compiled step's arrays (rows above): the attributes below are their rows
        self.F = np.zeros((NF, n))
        self.I = np.zeros((NI, n), dtype=np.int64)
        self.B = np.zeros((NB, n), dtype=bool)
        #: ... as the compiled cycle takes them (`machine.cycle.cycles`)
        self.state: Packed = tuple(MotionState(self.F, self.I, self.B, self.dt))
        f, b = self.F, self.B
        self.pos, self.vel, self.acc, self.target = f[POS], f[VEL], f[ACC], f[TARGET]
        self.feed, self.v_max, self.a_max, self.period = f[FEED], f[V_MAX], f[A_MAX], f[PERIOD]
        self.homed, self.modulo = b[HOMED], b[MODULO]
        self._moving, self._queued, self._done = b[MOVING], b[QUEUED], b[DONE]
        self._p0, self._dist, self._ta, self._td, self._tt = f[P0], f[DIST], f[TA], f[TD], f[TT]
        self._w, self._j, self._ub0 = f[W], f[J], f[UB0]
        self._dir, self._next_dir = f[DIR], f[NEXT_DIR]  # the current/last move's sign
        self._q_target, self._q_feed = f[Q_TARGET], f[Q_FEED]
        self._k, self._nc = self.I[K], self.I[NC]
        self.v_max[:] = [p.v_max for p in params]
        self.a_max[:] = [p.a_max * UNITS_PER_MM for p in params]
        self.modulo[:] = [p.modulo for p in params]
        self.period[:] = [p.modulo_period if p.modulo else 0.0 for p in params]
        self.homed[:] = [p.homed for p in params]
        self.pos[:] = [p.start_position for p in params]
        self.target[:] = self.pos
        self._p0[:] = self.pos
        self.feed[:] = self.v_max

    # ------------------------------------------------------------------ commands

    def move_to(self, slot: int, target: float, feed: float | None = None) -> int:
        """Single-axis point-to-point move (trapezoidal, triangular when short).

        `feed` in units/s (default `self.feed[slot]`, clamped to v_max). Returns the
        duration in cycles (0 when already at the target). Raises `MotionError` when the
        axis is still moving (use `queue_next` to chain moves).
        """
        self._check_idle([slot])
        f = float(self.feed[slot]) if feed is None else feed
        return self._plan({slot: float(target)}, f)

    def move_linear(
        self, targets: dict[int, float], feed: float | None, rapid: bool = False
    ) -> int:
        """Synchronised linear move of several axes (G01; G00 when `rapid`).

        G01: path feed `feed` in units/s along the Euclidean path of all programmed axes
        (None: no feed limit). G00: every axis may run at its own v_max; the slowest axis
        governs so that all still arrive together on the straight line. Returns the
        duration in cycles; axes whose target equals their position do not move.
        """
        self._check_idle(targets)
        if rapid or feed is None:
            return self._plan(targets, math.inf)
        return self._plan(targets, feed)

    def queue_next(self, slot: int, target: float, feed: float | None = None) -> None:
        """One-deep queue: start this single-axis move when the current one ends.

        When the axis is idle the move starts at once. A second call replaces the queued
        move. The queued move starts in the cycle in which the current move arrives
        (its first sample is the next cycle) and sets the announced direction, so
        `reversal_in` sees a coming reversal.
        """
        self._check_slot(slot)
        if not self._moving[slot]:
            self.move_to(slot, target, feed)
            return
        f = float(self.feed[slot]) if feed is None else feed
        if not f > 0:
            raise MotionError(f"feed must be > 0, got {f}")
        self._queued[slot] = True
        self._q_target[slot] = target
        self._q_feed[slot] = f
        self._next_dir[slot] = np.sign(target - self.target[slot])

    def announce_next(self, slot: int, direction: int) -> None:
        """Lookahead hint: the next move of `slot` goes in `direction` (−1, 0, +1).

        Used by the NC player, which knows the next block. Cleared when a new move of
        the axis starts, by `stop` and by `set_position`.
        """
        self._check_slot(slot)
        self._next_dir[slot] = float(np.sign(direction))

    def set_position(self, slot: int, pos: float) -> None:
        """Jump to `pos` without motion (tests, synchronisation); stops any move."""
        self._check_slot(slot)
        self._halt(slot)
        self.pos[slot] = pos
        self.target[slot] = pos
        self._p0[slot] = pos

    def home(self, slot: int) -> None:
        """G74 / homing: mark the axis referenced *in place*.

        The emulator has no reference cams: the position is unchanged and no motion
        happens, so the homing block finishes at once.
        """
        self._check_slot(slot)
        self.homed[slot] = True

    def stop(self, slot: int | None = None) -> None:
        """Controlled stop: decelerate with the current profile's deceleration.

        The axis keeps its direction and comes to rest after ⌈v/a / dt⌉ cycles; the new
        target is where it stops. Queued moves and announcements are dropped.
        `slot=None` stops all axes.
        """
        slots = range(self.n) if slot is None else [slot]
        for s in slots:
            self._check_slot(s)
            self._queued[s] = False
            self._next_dir[s] = 0.0
            if self._moving[s]:
                self._replan_stop(s)

    # ------------------------------------------------------------------ queries

    def in_position(self, slot: int) -> bool:
        """True when the axis is at rest on its target with nothing queued."""
        return not (self._moving[slot] or self._queued[slot])

    def all_in_position(self, slots: Iterable[int] | None = None) -> bool:
        """`in_position` for every slot in `slots` (all axes when None)."""
        if slots is None:
            return not (self._moving.any() or self._queued.any())
        return all(self.in_position(s) for s in slots)

    def direction(self, slot: int) -> int:
        """Sign of the current or last move (0 before the first move)."""
        return int(self._dir[slot])

    def display_pos(self, out: np.ndarray | None = None) -> np.ndarray:
        """Command positions with modulo axes wrapped into [0, period) (`display`).

        Use for displayed positions and objects; the kernel reads the unwrapped `pos`.
        """
        if out is None:
            out = np.empty(self.n)
        display(self.F, self.B, out)
        return out

    def reversal_in(self, out: np.ndarray) -> None:
        """Cycles until the planned velocity changes sign, per axis (−1 if none known):
        `reversal_in` of the compiled cycle, into `out` (int64, length n)."""
        reversal_in(self.F, self.I, out)

    # ------------------------------------------------------------------ the cycle

    def step(self) -> None:
        """Advance one cycle: update `pos`, `vel`, `acc` in place (`profile_step`).

        In the cycle a move reaches its duration the axis snaps to its target with
        vel = acc = 0; a queued move of that axis is then planned (first sample next
        cycle).
        """
        if profile_step(self.F, self.I, self.B, self.dt) & START_QUEUED:
            self.start_queued()

    def start_queued(self) -> None:
        """Start the queued moves of the axes that arrived in this cycle (after
        `profile_step` said so: planning is Python)."""
        for i in np.flatnonzero(self._queued & self._done):
            s = int(i)
            self._queued[s] = False
            self._plan({s: float(self._q_target[s])}, float(self._q_feed[s]))

    # ------------------------------------------------------------------ planning

    def _check_slot(self, slot: int) -> None:
        if not 0 <= slot < self.n:
            raise MotionError(f"no axis in slot {slot} (0..{self.n - 1})")

    def _check_idle(self, slots: Iterable[int]) -> None:
        for s in slots:
            self._check_slot(s)
            if self._moving[s] or self._queued[s]:
                raise MotionError(f"axis in slot {s} is still moving")

    def _plan(self, targets: dict[int, float], feed: float) -> int:
        """Plan one synchronised move; returns its duration in cycles."""
        if not feed > 0:
            raise MotionError(f"feed must be > 0, got {feed}")
        dists = {s: float(t) - float(self.pos[s]) for s, t in targets.items()}
        for s, t in targets.items():
            self.target[s] = t
            self._next_dir[s] = 0.0
        moving = {s: d for s, d in dists.items() if d != 0.0}
        if not moving:
            return 0
        length = math.hypot(*moving.values())
        v, a = feed, math.inf
        for s, d in moving.items():
            scale = length / abs(d)
            v = min(v, float(self.v_max[s]) * scale)
            a = min(a, float(self.a_max[s]) * scale)
        ta, tt, w = _trapezoid(length, v, a)
        n_cyc = max(1, math.ceil(tt / self.dt - _CYCLE_EPS))
        for s, d in moving.items():
            self._set_profile(s, d, ta, tt, w, a / length, n_cyc)
        return n_cyc

    def _set_profile(
        self, s: int, dist: float, ta: float, tt: float, w: float, j: float, n_cyc: int
    ) -> None:
        self._p0[s] = self.pos[s]
        self._dist[s] = dist
        self._ta[s] = ta
        self._td[s] = tt - ta
        self._tt[s] = tt
        self._w[s] = w
        self._j[s] = j
        self._ub0[s] = 0.5 * w * ta
        self._k[s] = 0
        self._nc[s] = n_cyc
        self._dir[s] = math.copysign(1.0, dist)
        self._moving[s] = True

    def _replan_stop(self, s: int) -> None:
        """Turn the running move of `s` into a pure deceleration from its state now."""
        du = float(self.vel[s]) / float(self._dist[s])  # normalised velocity, >= 0
        j = float(self._j[s])
        r0 = du / j if j > 0 else 0.0
        n_cyc = math.ceil(r0 / self.dt - _CYCLE_EPS)
        if n_cyc <= 0 or du <= 0:
            self._halt(s)
            return
        rest = float(self._dist[s]) * 0.5 * j * r0 * r0
        self.target[s] = self.pos[s] + rest
        self._set_profile(s, rest, 0.0, r0, 0.0, 2.0 / (r0 * r0), n_cyc)
        self._td[s] = 0.0  # phase C from now on

    def _halt(self, s: int) -> None:
        """Immediate stop in place (no ramp)."""
        self._moving[s] = False
        self._queued[s] = False
        self._next_dir[s] = 0.0
        self.vel[s] = 0.0
        self.acc[s] = 0.0
        self.target[s] = self.pos[s]
        self._k[s] = self._nc[s]


def _trapezoid(length: float, v: float, a: float) -> tuple[float, float, float]:
    """Symmetric profile over `length` with peak ≤ v and acceleration a.

    Returns (ta, T, w): acceleration time, total time and the normalised peak velocity
    w = v_peak/length. Triangular (T = 2·ta) when the distance is too short to reach v.
    """
    if length * a >= v * v:
        return v / a, length / v + v / a, v / length
    ta = math.sqrt(length / a)
    return ta, 2.0 * ta, a * ta / length
