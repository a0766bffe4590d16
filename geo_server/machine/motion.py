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

Modulo rotary axes: `pos` stays *unwrapped* (continuous) for motion and is what the
compensation kernel should read (velocity, reversal and modulo tables are the kernel's
business); `display_pos()` wraps into [0, period) for displayed positions and objects.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from geo_server.errors import GeoError
from geo_server.model import AxisParams
from geo_server.units import UNITS_PER_MM

#: Internal units per mm (linear) or per degree (rotary): 0.1 µm / 0.0001°.

#: Tolerance (in cycles) when rounding a move duration up to whole cycles, so that
#: T/dt = 3000.0000000004 still counts as 3000 cycles.
_CYCLE_EPS = 1e-6

#: Up to this many moving axes `Motion.step` runs per axis in Python (see `_step_scalar`).
_SCALAR_MAX = 6


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
        self.v_max = np.array([p.v_max for p in params], dtype=np.float64)
        self.a_max = np.array([p.a_max for p in params], dtype=np.float64) * UNITS_PER_MM
        bad = [p.log_nr for p in params if p.v_max <= 0 or p.a_max <= 0]
        if bad:
            raise MotionError(f"axes {bad}: v_max and a_max must be > 0")
        self.modulo = np.array([p.modulo for p in params], dtype=bool)
        self.period = np.array(
            [p.modulo_period if p.modulo else 0.0 for p in params], dtype=np.float64
        )
        self.homed = np.array([p.homed for p in params], dtype=bool)
        self.pos = np.array([p.start_position for p in params], dtype=np.float64)
        self.vel = np.zeros(n)
        self.acc = np.zeros(n)
        self.target = self.pos.copy()
        self.feed = self.v_max.copy()
        self._init_profile(n)

    def _init_profile(self, n: int) -> None:
        """Allocate the per-axis profile parameters and the step() scratch buffers."""
        self._moving = np.zeros(n, dtype=bool)
        self._p0 = self.pos.copy()
        self._dist = np.zeros(n)
        self._ta = np.zeros(n)
        self._td = np.zeros(n)  # start of deceleration, T − ta
        self._tt = np.zeros(n)  # total time T
        self._w = np.zeros(n)
        self._j = np.zeros(n)
        self._ub0 = np.zeros(n)  # u at the end of phase A, ½·w·ta
        self._k = np.zeros(n, dtype=np.int64)
        self._nc = np.zeros(n, dtype=np.int64)  # duration N in cycles
        self._dir = np.zeros(n)  # sign of the current/last move
        self._next_dir = np.zeros(n)  # announced direction of the next move
        self._queued = np.zeros(n, dtype=bool)
        self._q_target = np.zeros(n)
        self._q_feed = np.zeros(n)
        self._t = np.zeros(n)
        self._u = np.zeros(n)
        self._du = np.zeros(n)
        self._ddu = np.zeros(n)
        self._s = np.zeros(n)
        self._r = np.zeros(n)
        self._m = np.zeros(n, dtype=bool)
        self._done = np.zeros(n, dtype=bool)
        self._ki = np.zeros(n, dtype=np.int64)

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
        """Command positions with modulo axes wrapped into [0, period).

        Use for displayed positions and objects; the kernel reads the unwrapped `pos`.
        """
        if out is None:
            out = np.empty(self.n)
        np.copyto(out, self.pos)
        np.mod(self.pos, self.period, out=out, where=self.modulo)
        # np.mod can return exactly `period` for tiny negative inputs
        np.greater_equal(out, self.period, out=self._m)
        np.logical_and(self._m, self.modulo, out=self._m)
        np.subtract(out, self.period, out=out, where=self._m)
        return out

    def reversal_in(self, out: np.ndarray) -> None:
        """Cycles until the planned velocity changes sign, per axis (−1 if none known).

        A reversal is known when the next move (queued with `queue_next` or announced
        with `announce_next`) goes against the current/last move direction. The value
        is the number of `step()` calls until the current move arrives at rest, 0 when
        the axis already rests and the next move will reverse it, else −1.
        `out` must be an int64 (or float64) array of length n; nothing is allocated.
        """
        np.multiply(self._next_dir, self._dir, out=self._s)
        np.less(self._s, 0.0, out=self._m)
        np.subtract(self._nc, self._k, out=self._ki)
        np.copyto(out, self._ki, casting="unsafe")
        np.logical_not(self._m, out=self._m)
        np.copyto(out, -1, where=self._m)

    # ------------------------------------------------------------------ the cycle

    def step(self) -> None:
        """Advance one cycle: update `pos`, `vel`, `acc` in place (no allocation).

        In the cycle a move reaches its duration the axis snaps to its target with
        vel = acc = 0; a queued move of that axis is then planned (first sample next
        cycle).
        """
        mv = self._moving
        moving = np.flatnonzero(mv)
        if len(moving) == 0:  # nothing changes at rest
            return
        if len(moving) <= _SCALAR_MAX:
            self._step_scalar(moving.tolist())
            return
        np.add(self._k, mv, out=self._k, casting="unsafe")
        np.multiply(self._k, self.dt, out=self._t)
        u, du, ddu, s, r, m = self._u, self._du, self._ddu, self._s, self._r, self._m
        self._eval_profile(self._t, u, du, ddu, s, r, m)
        np.greater_equal(self._k, self._nc, out=self._done)
        np.logical_and(self._done, mv, out=self._done)
        self._apply(mv, u, du, ddu, s, self.pos, self.vel, self.acc)
        np.copyto(self.pos, self.target, where=self._done)
        np.copyto(self.vel, 0.0, where=self._done)
        np.copyto(self.acc, 0.0, where=self._done)
        np.logical_not(self._done, out=self._m)
        np.logical_and(mv, self._m, out=mv)
        if self._queued.any() and self._done.any():
            self._start_queued()

    def steady_cycles(self) -> int:
        """How many of the next steps only sample running profiles: some axis moves,
        every moving axis has taken its first step and none arrives within them (so
        no move starts, ends or is replanned, and no velocity changes sign). 0 when
        none (docs/design.md §13.2)."""
        mv = self._moving
        if not mv.any():
            return 0
        k = self._k[mv]
        if k.min() < 1:
            return 0
        return max(int((self._nc[mv] - k).min()) - 1, 0)

    def sample(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, rev: np.ndarray) -> None:
        """The next `len(pos)` (≤ `steady_cycles`) steps, into [b, n] rows,
        without changing the state (`advance` does): pos/vel/acc after step b + 1 and
        what `reversal_in` then gives (docs/design.md §13.2): `step`'s own
        `_eval_profile`/`_apply` with the steps as a leading axis (and the operations of
        `_step_scalar`), so the numbers are bit-identical."""
        nb = len(pos)
        mv = self._moving
        kb = np.multiply.outer(np.arange(1, nb + 1), mv)
        kb += self._k  # k after each step
        t = kb * self.dt
        u, du, ddu, sc, r = (np.empty_like(t) for _ in range(5))
        m = np.empty(t.shape, dtype=bool)
        self._eval_profile(t, u, du, ddu, sc, r, m)
        np.copyto(pos, self.pos)
        np.copyto(vel, self.vel)
        np.copyto(acc, self.acc)
        self._apply(mv, u, du, ddu, sc, pos, vel, acc)
        # reversal_in after each step: cycles to arrival where the next move reverses
        coming = self._next_dir * self._dir < 0.0
        np.subtract(self._nc, kb, out=rev, casting="unsafe")
        np.copyto(rev, -1, where=~coming)

    def advance(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> None:
        """Take the state after the steps `sample` gave (its last row)."""
        mv = self._moving
        self._k += len(pos) * mv
        np.copyto(self.pos, pos[-1])
        np.copyto(self.vel, vel[-1])
        np.copyto(self.acc, acc[-1])

    def _step_scalar(self, moving: list[int]) -> None:
        """`step()` for a few moving axes, one at a time with Python floats.

        Bit-identical to the vectorised path: the same IEEE operations in the same
        order (`_eval_profile`, `_apply`), only without the numpy call overhead, which
        dominates when one or two axes move.
        """
        dt = self.dt
        k_arr, pos, vel, acc = self._k, self.pos, self.vel, self.acc
        done = []
        for s in moving:
            k = k_arr.item(s) + 1
            k_arr[s] = k
            t = k * dt
            j = self._j.item(s)
            u = t * t * 0.5 * j  # phase A
            du = j * t
            ddu = j
            ta = self._ta.item(s)
            if t >= ta:  # phase B
                u = (t - ta) * self._w.item(s) + self._ub0.item(s)
                du = self._w.item(s)
                ddu = 0.0
            if t >= self._td.item(s):  # phase C
                r = self._tt.item(s) - t
                u = r * r * j * -0.5 + 1.0
                du = j * r
                ddu = -j
            if k >= self._nc.item(s):
                pos[s] = self.target.item(s)
                vel[s] = 0.0
                acc[s] = 0.0
                self._moving[s] = False
                done.append(s)
            else:
                dist = self._dist.item(s)
                pos[s] = dist * u + self._p0.item(s)
                vel[s] = dist * du
                acc[s] = dist * ddu
        if done and self._queued.any():
            self._done.fill(False)
            self._done[done] = True
            self._start_queued()

    def _eval_profile(
        self,
        t: np.ndarray,
        u: np.ndarray,
        du: np.ndarray,
        ddu: np.ndarray,
        s: np.ndarray,
        r: np.ndarray,
        m: np.ndarray,
    ) -> None:
        """u, du/dt, d²u/dt² at the times `t` (phases A, B, C), into `u`, `du`, `ddu`
        (`s`, `r`, `m`: scratch of t's shape). `t` is [n] for one step or [b, n] for
        the steps of `sample`: the profile parameters broadcast over the rows."""
        j = self._j
        np.multiply(t, t, out=u)  # phase A
        u *= 0.5
        u *= j
        np.multiply(j, t, out=du)
        np.copyto(ddu, j)
        np.greater_equal(t, self._ta, out=m)  # phase B
        np.subtract(t, self._ta, out=s)
        s *= self._w
        s += self._ub0
        np.copyto(u, s, where=m)
        np.copyto(du, self._w, where=m)
        np.copyto(ddu, 0.0, where=m)
        np.greater_equal(t, self._td, out=m)  # phase C
        np.subtract(self._tt, t, out=r)
        np.multiply(r, r, out=s)
        s *= j
        s *= -0.5
        s += 1.0
        np.copyto(u, s, where=m)
        np.multiply(j, r, out=s)
        np.copyto(du, s, where=m)
        np.negative(j, out=s)
        np.copyto(ddu, s, where=m)

    def _apply(
        self,
        mv: np.ndarray,
        u: np.ndarray,
        du: np.ndarray,
        ddu: np.ndarray,
        s: np.ndarray,
        pos: np.ndarray,
        vel: np.ndarray,
        acc: np.ndarray,
    ) -> None:
        """pos/vel/acc of the moving axes `mv` from the normalised profile (`s`:
        scratch); the other axes keep what `pos`/`vel`/`acc` hold."""
        np.multiply(self._dist, u, out=s)
        s += self._p0
        np.copyto(pos, s, where=mv)
        np.multiply(self._dist, du, out=s)
        np.copyto(vel, s, where=mv)
        np.multiply(self._dist, ddu, out=s)
        np.copyto(acc, s, where=mv)

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

    def _start_queued(self) -> None:
        """Start the queued moves of the axes that arrived in this cycle."""
        for i in np.flatnonzero(self._queued & self._done):
            s = int(i)
            self._queued[s] = False
            self._plan({s: float(self._q_target[s])}, float(self._q_feed[s]))


def _trapezoid(length: float, v: float, a: float) -> tuple[float, float, float]:
    """Symmetric profile over `length` with peak ≤ v and acceleration a.

    Returns (ta, T, w): acceleration time, total time and the normalised peak velocity
    w = v_peak/length. Triangular (T = 2·ta) when the distance is too short to reach v.
    """
    if length * a >= v * v:
        return v / a, length / v + v / a, v / length
    ta = math.sqrt(length / a)
    return ta, 2.0 * ta, a * ta / length
