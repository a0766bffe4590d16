"""The twin per GEO cycle: true tool position, residual error, temperatures (vectorised).

Every cycle, after the compensation kernel (docs/twin.md):

1. simulated time advances by the cycle length × `time_scale`;
2. the thermal nodes move towards their targets — ambient(t) plus the steady-state rises
   of the heat sources (motion of an axis ∝ |v|, the spindle) — exactly for a first-order
   system: T += (T_target − T)·(1 − e^(−dt/τ));
3. the sensors due take a sample: the node's temperature plus seeded noise, rounded to
   the resolution;
4. every error is evaluated at the drive (output) position of the axes — where the
   mechanics really are: linear scale error, pitch curve (per direction where given),
   cyclic error, lost motion on reversal, straightness over other axes, grids over two
   axes, squareness, thermal expansion, and the scatter of each approach;
5. true position = output + error; residual = true − command (the programmed position).

All positions and errors are increments here (0.1 µm, 0.0001°): the file's mm/° and
µm/0.001° are converted once, at load. The work per cycle is a fixed number of numpy
calls whatever the number of axes: all 1-D curves of all axes are served by one merged
table lookup (the kernel's `MergedTable`).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np

from geo_server.faults import OPEN_CIRCUIT_C
from geo_server.kernel.tables import Lookup, MergedTable
from geo_server.twin.model import AxisTwin, Curve, Grid, RigidBody, TwinConfig
from geo_server.twin.volumetric import rigid_tables
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM
from geo_server.volcomp.evaluator import Evaluator
from geo_server.volcomp.model import build_model

#: Increments per second to m/s (linear) or to 1000 °/s (rotary).
V_SCALE = 1e-7


def _curve_rows(c: Curve) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.asarray(c.positions) * UNITS_PER_MM,
        np.asarray(c.errors) * UNITS_PER_UM,
    )


class TwinEngine:
    """The machine's errors and temperatures for the axes `names` (slot order)."""

    def __init__(
        self,
        cfg: TwinConfig,
        names: Sequence[str],
        cycle_s: float,
        time_scale: float | None = None,
        modulo: Sequence[float] = (),
    ) -> None:
        """`modulo`: the period of each modulo axis in increments (0: not modulo); its
        curves are looked up at the position within the period."""
        self.cfg = cfg
        self.names = [n.upper() for n in names]
        n = len(self.names)
        slot = {name: i for i, name in enumerate(self.names)}
        self.time_scale = time_scale if time_scale is not None else cfg.time_scale
        self.dt = cycle_s * self.time_scale  # simulated seconds per cycle
        self.cycles = 0
        self.time = 0.0  # cycles · dt (a product, never a running sum that drifts)
        #: stretches at rest (`advance`) in which a thermal update or a sensor sample ran
        self.rest_events = 0
        axes = [cfg.axes.get(name, AxisTwin(name)) for name in self.names]
        self.period = np.array(list(modulo) or [0.0] * n, dtype=float)
        # state
        self.direction = np.array([float(a.reference_direction) for a in axes])
        self._sign_before = np.zeros(n)  # sign(v) of the last cycle
        self._scatter_now = np.zeros(n)
        self._offset = np.zeros(n)
        self._rng = np.random.default_rng(cfg.seed)
        self._tmp = np.zeros(n)
        self._sign = np.zeros(n)
        self._still = np.zeros(n)  # the velocities of a machine at rest
        self._setup_geometry(axes, slot)
        self._setup_thermal(axes, slot)
        self._setup_rigid(cfg.rigid_body, slot)
        # outputs (read by the machine's snapshot)
        self.true_position = np.zeros(n)
        self.residual = np.zeros(n)
        self.friction_current = np.zeros(n)
        self.error = np.zeros(n)

    # ------------------------------------------------------------------ set-up

    def _setup_rigid(self, rb: RigidBody | None, slot: dict[str, int]) -> None:
        """The rigid-body errors (docs/twin.md §2.1) as a volumetric model (docs/
        volumetric.md §2): the same kinematics the compensation inverts, with the twin's
        curves as tables (µm → mm, µrad → rad)."""
        self._rigid: Evaluator | None = None
        if rb is None or not all(a in slot for a in "XYZ"):
            return
        model = build_model(rb.chain, rb.workpiece_axes, rigid_tables(rb))
        self._rigid = Evaluator(model)
        self._rigid_chain = [slot[a] for a in rb.chain]
        self._rigid_xyz = np.array([slot[a] for a in "XYZ"])
        self._rigid_tip = model.tool_point(0.0)

    def _rigid_errors(self, output: np.ndarray, e: np.ndarray) -> None:
        """Where the imperfect machine puts the tool minus where the ideal one would, at
        the drive positions, added to the X, Y, Z errors."""
        ev = self._rigid
        assert ev is not None
        q = output[self._rigid_chain][None, :] / UNITS_PER_MM
        tip = self._rigid_tip
        d = ev.forward(q, tip)[0] - ev.forward(q, tip, errors=False)[0]
        e[self._rigid_xyz] += d * UNITS_PER_MM

    def _setup_geometry(self, axes: list[AxisTwin], slot: dict[str, int]) -> None:
        n = len(axes)
        self.lin_off = np.array([a.linear_offset * UNITS_PER_UM for a in axes])
        self.lin_slope = np.array([a.linear_slope * 1e-6 for a in axes])
        self.lin_ref = np.array([a.linear_reference * UNITS_PER_MM for a in axes])
        self.per_amp = np.array([a.periodic_amplitude * UNITS_PER_UM for a in axes])
        self.per_k = np.array(
            [
                2 * math.pi / (a.periodic_period * UNITS_PER_MM) if a.periodic_period else 0.0
                for a in axes
            ]
        )
        self.reversal = np.array([a.reversal * UNITS_PER_UM for a in axes])
        self.ref_dir = np.array([float(a.reference_direction) for a in axes])
        self.scatter = np.array([a.scatter * UNITS_PER_UM for a in axes])
        self._any_periodic = bool(self.per_amp.any())
        self._half_reversal = self.reversal / 2
        self.fr_coulomb = np.array([a.friction_coulomb for a in axes])
        self.fr_viscous = np.array([a.friction_viscous for a in axes])
        self._fr_viscous_incr = self.fr_viscous * 1e-4  # per mm/s (°/s) -> per increment/s
        self._any_friction = bool(self.fr_coulomb.any() or self.fr_viscous.any())
        # every 1-D curve of every axis: (source slot, target slot, direction it holds in)
        rows: list[tuple[np.ndarray, np.ndarray]] = []
        links: list[tuple[int, int, int]] = []  # (source slot, target slot, direction)
        for i, a in enumerate(axes):
            if a.pitch is not None:
                rows.append(_curve_rows(a.pitch))
                links.append((i, i, 1 if a.pitch_negative else 0))
            if a.pitch_negative is not None:
                rows.append(_curve_rows(a.pitch_negative))
                links.append((i, i, -1))
            for s in a.straightness:
                if s.over in slot:  # (an axis the machine lacks contributes nothing)
                    rows.append(_curve_rows(s.curve))
                    links.append((slot[s.over], i, 0))
        src = [link[0] for link in links]
        tgt = [link[1] for link in links]
        kind = [link[2] for link in links]
        self._curves = bool(rows)
        if rows:
            self._lookup = Lookup(MergedTable(rows), np.arange(len(rows), dtype=float))
            self._src = np.array(src)
            self._tgt = np.array(tgt)
            self._kind = np.array(kind, dtype=float)
            self._directional = bool(np.any(self._kind != 0))
            self._w_a = 1.0 - np.abs(self._kind) / 2
            self._w_b = self._kind / 2
            self._w = np.zeros(len(rows))
            self._vals = np.zeros(len(rows))
            self._src_period = np.where(self.period[self._src] > 0, self.period[self._src], 1.0)
            self._wrap = self.period[self._src] > 0
            self._wrap_any = bool(self._wrap.any())
        self.square = np.zeros((n, n))
        for i, a in enumerate(axes):
            for other, urad in a.squareness:
                if other in slot:
                    self.square[i, slot[other]] += urad * 1e-6
        self._any_square = bool(self.square.any())
        self.grids: list[tuple[int, int, int, _GridLookup]] = [
            (i, slot[g.over1], slot[g.over2], _GridLookup(g))
            for i, a in enumerate(axes)
            for g in a.grids
            if g.over1 in slot and g.over2 in slot
        ]

    def _setup_thermal(self, axes: list[AxisTwin], slot: dict[str, int]) -> None:
        cfg = self.cfg
        nodes = list(cfg.nodes)
        index = {nd.name: k for k, nd in enumerate(nodes)}
        self.node_names = [nd.name for nd in nodes]
        self.node_temp = np.array([nd.initial for nd in nodes], dtype=float)
        #: cycles between two updates of the thermal model: 10 ms of simulated time (the
        #: time constants are minutes), at least every cycle
        self.thermal_every = max(1, round(0.01 / self.dt)) if self.dt > 0 else 1
        dt_thermal = self.thermal_every * self.dt
        self._node_k = np.array([1.0 - math.exp(-dt_thermal / nd.tau) for nd in nodes])
        self._motion_slot = np.array([slot.get(nd.motion_axis, 0) for nd in nodes], dtype=int)
        # the mean |v| of an update is the sum over its cycles / thermal_every
        self._motion_gain = np.array(
            [
                nd.motion_gain * V_SCALE / self.thermal_every if nd.motion_axis in slot else 0.0
                for nd in nodes
            ]
        )
        self._spindle_gain = np.array([nd.spindle_gain for nd in nodes])
        self._node_target = np.zeros(len(nodes))
        self._amb_t = np.array([p[0] for p in cfg.ambient])
        self._amb_v = np.array([p[1] for p in cfg.ambient])
        self.ambient = float(np.interp(0.0, self._amb_t, self._amb_v))
        #: a climate chamber: the ambient held at this temperature instead of the profile
        self.held_ambient: float | None = None
        self.t_ref = cfg.reference_temperature
        # expansion: coefficient (per K, dimensionless) and reference per axis, its node
        self.exp_coef = np.array(
            [a.expansion.coefficient * 1e-6 if a.expansion else 0.0 for a in axes]
        )
        self.exp_ref = np.array(
            [a.expansion.reference * UNITS_PER_MM if a.expansion else 0.0 for a in axes]
        )
        self.exp_node = np.array(
            [index[a.expansion.node] if a.expansion else 0 for a in axes], dtype=int
        )
        # sensors: the node each reads, the axis it is shown on, its noise and resolution
        sensors = list(cfg.sensors)
        self.sensor_names = [s.name for s in sensors]
        self.sensor_node = np.array([index[s.node] for s in sensors], dtype=int)
        self.sensor_noise = np.array([s.noise for s in sensors])
        self.sensor_res = np.array([s.resolution for s in sensors])
        self.sensor_period = np.array([s.period for s in sensors])
        self.sensor_due = np.zeros(len(sensors))  # next sample time
        self.sensor_value = np.array(
            [_quantize(self.node_temp[index[s.node]], s.resolution) for s in sensors]
        )
        n = len(axes)
        #: TWIN::sensor_temperature of each axis: its sensor, else the reference temperature
        self.axis_sensor = np.full(n, -1, dtype=int)
        for k, s in enumerate(sensors):
            if s.axis in slot and self.axis_sensor[slot[s.axis]] < 0:
                self.axis_sensor[slot[s.axis]] = k
        self.sensor_temperature = np.full(n, self.t_ref)
        self._next_sample = 0.0 if sensors else math.inf
        #: injected sensor faults (geo_server/faults.py): "", "stuck", "noisy", "open"
        self.sensor_fault = [""] * len(sensors)
        self.sensor_extra_noise = np.zeros(len(sensors))  # σ a "noisy" fault adds
        self._vsum = np.zeros(n)
        self._line_a = np.zeros(n)
        self._line_b = np.zeros(n)
        self._update_lines()

    # ------------------------------------------------------------------ the cycle

    def step(
        self,
        output: np.ndarray,
        command: np.ndarray,
        velocity: np.ndarray,
        spindle: bool,
        evaluate: bool = True,
    ) -> None:
        """One GEO cycle (see the module docstring).

        What changes only on events — the temperatures (every `thermal_every` cycles), a
        reversal, an arrival (a new scatter draw) — is folded into one offset per axis
        (`_update_offset`) when the event happens, so a cycle without events costs a
        fixed, small number of numpy calls."""
        self.cycles += 1
        self.time = self.cycles * self.dt
        tmp = self._tmp
        np.abs(velocity, out=tmp)
        self._vsum += tmp
        if self.cycles % self.thermal_every == 0:
            self._thermal(spindle)
        if self.time >= self._next_sample:
            self._sample_sensors()
        sign = self._sign
        np.sign(velocity, out=sign)
        # count_nonzero: a plain C call (ndarray.any() goes through Python wrappers)
        if np.count_nonzero(np.not_equal(sign, self._sign_before)):
            self._motion_event(sign)
        if evaluate:  # (the outputs only: a cycle nobody looks at can leave them)
            self.evaluate(output, command, velocity)

    def step_steady(
        self, output: np.ndarray, command: np.ndarray, velocity: np.ndarray, spindle: bool
    ) -> None:
        """`len(velocity)` cycles of `step` ([b, n] rows) in one pass,
        without evaluating the outputs (`evaluate` does, for the cycle reached), for a
        stretch in which no velocity changes sign (docs/design.md §13.2). The machine
        guarantees that (it does not reverse in a steady stretch); the rare axis that
        starts or stops (a velocity becoming exactly 0) makes it run cycle by cycle.

        Without a sign change `step` only adds |v| to the motion heat and runs the
        thermal updates and sensor samples in their cycles, so the stretch is cut at
        those events: |v| is summed up to each of them with `np.add.accumulate` (the
        same additions in the same order) and the event runs at its own cycle."""
        sign = np.sign(velocity)
        if np.count_nonzero(sign != self._sign_before):
            for b in range(len(velocity)):
                self.step(output[b], command[b], velocity[b], spindle, evaluate=False)
            return
        heat = np.abs(velocity)
        vsum, every = self._vsum, self.thermal_every
        end = self.cycles + len(velocity)
        row = 0
        while self.cycles < end:
            upto = int(min((self.cycles // every + 1) * every, self._sample_cycle(), end))
            j = upto - self.cycles
            part = np.empty((j + 1, len(vsum)))
            part[0] = vsum
            part[1:] = heat[row : row + j]
            np.add.accumulate(part, axis=0, out=part)
            vsum[:] = part[j]
            row += j
            self.cycles = upto
            self.time = upto * self.dt
            if upto % every == 0:
                self._thermal(spindle)
            if self.time >= self._next_sample:
                self._sample_sensors()

    def at_rest(self) -> bool:
        """No motion heat waits for the next thermal update (|v| summed since the last
        one is zero): `advance` may then run the thermal updates without it."""
        return not np.count_nonzero(self._vsum)

    def advance(
        self,
        n: int,
        output: np.ndarray,
        command: np.ndarray,
        spindle: bool,
        evaluate: bool = True,
    ) -> None:
        """`n` cycles of a machine at rest (every velocity 0, the same output and command
        positions throughout) in the numbers `n` calls of `step` give, at the cost of the
        events only (docs/design.md §13).

        At rest `step` changes state only at a thermal update (every `thermal_every`
        cycles) and at a sensor sample (its time reached): |v| adds nothing, no sign
        changes, and the errors are a function of the positions and of the state the
        events leave. So the events run in their cycle order, each at its own cycle
        and time, and the errors are evaluated once, at the end. The thermal updates of
        a machine at rest run on Python floats (`_RestNodes`: the same IEEE operations
        in the same order as `_thermal`, a microsecond each instead of twenty numpy
        calls); the axis lines, which only the errors read, are updated once."""
        end = self.cycles + n
        every = self.thermal_every
        nodes: _RestNodes | None = None  # made at the first thermal update
        has_nodes = len(self.node_temp) > 0
        thermal = sampled = False
        while True:
            nxt = min((self.cycles // every + 1) * every, self._sample_cycle())
            if nxt > end:
                break
            c = int(nxt)
            self.cycles = c
            self.time = c * self.dt
            if c % every == 0:
                thermal = True
                if not has_nodes:
                    self._vsum[:] = 0.0
                else:
                    if nodes is None:
                        nodes = _RestNodes(self, spindle)
                    nodes.update(self.time)
            if self.time >= self._next_sample:
                if nodes is not None:
                    nodes.store()  # the sensors read the nodes
                self._sample_sensors()
                sampled = True
        if thermal:  # (the lines follow the temperatures only)
            if nodes is not None:
                nodes.store()
            self._update_lines()
        if thermal or sampled:
            self.rest_events += 1  # the outputs at rest may differ (`Machine.publish`)
        self.cycles = end
        self.time = end * self.dt
        if evaluate:
            self.evaluate(output, command, self._still)

    def _sample_cycle(self) -> float:
        """The first cycle after this one at which `step` takes a sensor sample."""
        due = self._next_sample
        if due == math.inf or self.dt <= 0:
            return math.inf
        c = max(self.cycles + 1, math.ceil(due / self.dt))
        # `step` compares cycles·dt (a product) with the due time: match it exactly
        while c - 1 > self.cycles and (c - 1) * self.dt >= due:
            c -= 1
        while c * self.dt < due:
            c += 1
        return c

    def evaluate(self, output: np.ndarray, command: np.ndarray, velocity: np.ndarray) -> None:
        """This cycle's error, true position, residual and friction current (outputs
        only: `step` keeps the state, so a cycle nobody observes may leave them)."""
        tmp, sign = self._tmp, self._sign
        e = self.error
        # linear scale error and thermal expansion (A·pos + B, A and B from the
        # temperatures), lost motion and scatter: A·pos + offset
        np.multiply(output, self._line_a, out=e)
        e += self._offset
        if self._any_periodic:
            np.multiply(output, self.per_k, out=tmp)
            np.sin(tmp, out=tmp)
            tmp *= self.per_amp
            e += tmp
        if self._curves:
            self._curve_errors(output, e)
        for target, o1, o2, grid in self.grids:  # Python floats: no numpy scalars
            e[target] += grid(output.item(o1), output.item(o2))
        if self._any_square:
            e += self.square @ output
        if self._rigid is not None:
            self._rigid_errors(output, e)
        np.add(output, e, out=self.true_position)
        np.subtract(self.true_position, command, out=self.residual)
        if self._any_friction:  # the drive's current: sign(v)·c + k·v = sign(v)·(c + k·|v|)
            np.multiply(sign, self.fr_coulomb, out=self.friction_current)
            np.multiply(velocity, self._fr_viscous_incr, out=tmp)
            self.friction_current += tmp

    def _motion_event(self, sign: np.ndarray) -> None:
        """An axis started, stopped or reversed: the direction it holds (kept while it
        stands), a new scatter draw for every axis that arrived, the offset."""
        arrived = np.not_equal(self._sign_before, 0.0)
        moving = np.not_equal(sign, 0.0)
        arrived &= ~moving  # was moving, stands now
        np.copyto(self.direction, sign, where=moving)
        if np.count_nonzero(arrived):  # scatter: a new random error for every approach
            self._scatter_now[arrived] = (
                self._rng.normal(size=int(arrived.sum())) * self.scatter[arrived]
            )
        np.copyto(self._sign_before, sign)
        self._update_offset()

    def _update_offset(self) -> None:
        """offset = B + lost motion + scatter, and the bilateral curves' weights (after
        a temperature update, a reversal or an arrival). Lost motion while moving
        against the reference direction: direction is ±1, so −direction·reversal·
        [direction ≠ reference] = −(direction − reference)·reversal/2."""
        np.subtract(self.direction, self.ref_dir, out=self._offset)
        self._offset *= -self._half_reversal
        self._offset += self._line_b
        self._offset += self._scatter_now
        if self._curves and self._directional:
            w = self._w
            self.direction.take(self._tgt, out=w)
            w *= self._w_b
            w += self._w_a

    def _curve_errors(self, output: np.ndarray, e: np.ndarray) -> None:
        """Every 1-D curve of every axis in one merged lookup; bilateral rows weighted
        by the direction they hold in: w = 1 − |k|/2 + k·d/2 (1, or 0/1 for k = ±1)."""
        q = self._lookup.q
        output.take(self._src, out=q)
        if self._wrap_any:
            np.copyto(q, np.mod(q, self._src_period), where=self._wrap)
        self._lookup(self._vals)
        if self._directional:  # weights of the direction held (`_update_offset`)
            self._vals *= self._w
        e += np.bincount(self._tgt, weights=self._vals, minlength=len(e))

    def _thermal(self, spindle: bool) -> None:
        """Advance the nodes by `thermal_every` cycles: exact for a first-order system
        with the mean |v| of those cycles as the motion heat; then the axis lines."""
        if len(self.node_temp):
            self.ambient = self._ambient_at(self.time)
            target = self._node_target
            self._vsum.take(self._motion_slot, out=target)
            target *= self._motion_gain
            target += self.ambient
            if spindle:
                target += self._spindle_gain
            self.node_temp += (target - self.node_temp) * self._node_k
        self._vsum[:] = 0.0
        self._update_lines()

    def _ambient_at(self, t: float) -> float:
        if self.held_ambient is not None:
            return self.held_ambient
        return float(np.interp(t, self._amb_t, self._amb_v))

    # ------------------------------------------------------------------ the climate

    def hold_ambient(self, temperature: float) -> None:
        """`TWIN::ambient_temperature` written: the machine stands in a climate chamber at
        `temperature` from now on (the twin file's profile no longer applies); the nodes
        follow with their time constants."""
        self.held_ambient = float(temperature)
        self.ambient = self.held_ambient

    def soak(self) -> None:
        """`TWIN::soak`: every thermal node takes the ambient temperature at once, as after
        a night in the hall — the start of a measurement at a known temperature. The
        sensors read it from their next sample on."""
        self.node_temp[:] = self.ambient
        self.sensor_due[:] = self.time
        self._next_sample = self.time if len(self.sensor_due) else math.inf
        self._update_lines()

    def _update_lines(self) -> None:
        """error = slope·(pos − ref) + offset + coef·ΔT·(pos − exp_ref) = A·pos + B."""
        dT = self.node_temp[self.exp_node] - self.t_ref if len(self.node_temp) else 0.0
        c = self.exp_coef * dT
        np.add(self.lin_slope, c, out=self._line_a)
        np.subtract(
            self.lin_off, self.lin_slope * self.lin_ref + c * self.exp_ref, out=self._line_b
        )
        self._update_offset()

    def _sample_sensors(self) -> None:
        due = self.sensor_due <= self.time
        k = np.nonzero(due)[0]
        # a noisy fault widens the sensor's own noise (the same draws: the random stream
        # stays the one of a sound sensor)
        sigma = np.hypot(self.sensor_noise[k], self.sensor_extra_noise[k])
        raw = self.node_temp[self.sensor_node[k]] + self._rng.normal(size=len(k)) * sigma
        values = [_quantize(v, r) for v, r in zip(raw, self.sensor_res[k], strict=True)]
        for j, s in enumerate(k):
            fault = self.sensor_fault[s]
            if fault == "stuck":
                values[j] = self.sensor_value[s]  # the reading it had when it stuck
            elif fault == "open":
                values[j] = OPEN_CIRCUIT_C
        self.sensor_value[k] = values
        # the next sample one period after the one due (never drifting with dt)
        self.sensor_due[k] += self.sensor_period[k] * np.ceil(
            (self.time - self.sensor_due[k]) / self.sensor_period[k] + 1e-12
        )
        self._next_sample = float(self.sensor_due.min())
        has = self.axis_sensor >= 0
        self.sensor_temperature[has] = self.sensor_value[self.axis_sensor[has]]

    # ------------------------------------------------------------------ faults

    def sensor_index(self, label: str) -> int:
        """The sensor a fault names (docs/faults.md): a sensor name, or the axis (name
        or slot number from 1) whose `TWIN::sensor_temperature` it feeds."""
        low = label.strip().lower()
        names = [n.lower() for n in self.sensor_names]
        if low in names:
            return names.index(low)
        slot = self.names.index(low.upper()) if low.upper() in self.names else -1
        if slot < 0 and low.isdigit() and 1 <= int(low) <= len(self.names):
            slot = int(low) - 1
        if slot >= 0 and self.axis_sensor[slot] >= 0:
            return int(self.axis_sensor[slot])
        known = ", ".join(self.sensor_names) or "none: the machine has no twin sensors"
        raise LookupError(f"no twin sensor {label!r} (sensors: {known}; or an axis with one)")

    def set_sensor_fault(self, k: int, kind: str, sigma: float = 0.0) -> None:
        """Make sensor `k` stuck, noisy (σ °C more noise) or open from its next sample
        on ("" clears it: the next sample reads the node again). An open circuit shows
        at once, as an input terminal reports a broken wire."""
        self.sensor_fault[k] = kind
        self.sensor_extra_noise[k] = sigma if kind == "noisy" else 0.0
        if kind == "open":
            self.sensor_value[k] = OPEN_CIRCUIT_C
            has = self.axis_sensor >= 0
            self.sensor_temperature[has] = self.sensor_value[self.axis_sensor[has]]

    # ------------------------------------------------------------------ reload

    def take_state(self, old: TwinEngine) -> None:
        """Continue where `old` left off (a reload): time, node temperatures by name,
        directions, the random stream."""
        self.cycles, self.time = old.cycles, old.time
        self.ambient = self._ambient_at(self.time)
        for k, name in enumerate(self.node_names):
            if name in old.node_names:
                self.node_temp[k] = old.node_temp[old.node_names.index(name)]
        for k, name in enumerate(self.sensor_names):
            if name in old.sensor_names:
                j = old.sensor_names.index(name)
                self.sensor_value[k], self.sensor_due[k] = old.sensor_value[j], old.sensor_due[j]
                self.sensor_fault[k] = old.sensor_fault[j]  # a reload does not mend a wire
                self.sensor_extra_noise[k] = old.sensor_extra_noise[j]
        self._next_sample = float(self.sensor_due.min()) if len(self.sensor_due) else math.inf
        has = self.axis_sensor >= 0
        self.sensor_temperature[has] = self.sensor_value[self.axis_sensor[has]]
        if old.held_ambient is not None:
            self.hold_ambient(old.held_ambient)
        if len(self.direction) == len(old.direction):  # the same axes: the same motion
            self.direction[:] = old.direction
            self._sign_before[:] = old._sign_before
            self._scatter_now[:] = old._scatter_now
        self._rng = old._rng
        self._update_lines()


class _RestNodes:
    """`TwinEngine._thermal` for a machine at rest, on Python floats.

    At rest every |v| sum is 0, so a node's target is `0·gain + ambient (+ spindle
    gain)` = `ambient (+ spindle gain)` and its update `T + (target − T)·k`: the same
    IEEE double operations numpy performs element by element, hence the same numbers.
    The ambient temperature follows `np.interp`'s formula (`_interp`)."""

    def __init__(self, twin: TwinEngine, spindle: bool) -> None:
        self.twin = twin
        self.temps = twin.node_temp.tolist()
        self.ks = twin._node_k.tolist()
        self.spindle = twin._spindle_gain.tolist() if spindle else None
        self.xp = twin._amb_t.tolist()
        self.fp = twin._amb_v.tolist()

    def update(self, t: float) -> None:
        tw = self.twin
        held = tw.held_ambient
        amb = held if held is not None else _interp(t, self.xp, self.fp)
        tw.ambient = amb
        temps, ks, sp = self.temps, self.ks, self.spindle
        for i, k in enumerate(ks):
            target = amb if sp is None else amb + sp[i]
            temps[i] = temps[i] + (target - temps[i]) * k
        tw._vsum[:] = 0.0

    def store(self) -> None:
        self.twin.node_temp[:] = self.temps


def _interp(x: float, xp: list[float], fp: list[float]) -> float:
    """`float(np.interp(x, xp, fp))` for one x (numpy's compiled formula: clamp outside,
    slope·(x − xp[j]) + fp[j] inside, fp[-1] at the last point)."""
    if x < xp[0]:
        return fp[0]
    if x >= xp[-1]:
        return fp[-1]
    j = bisect.bisect_right(xp, x) - 1
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    y = slope * (x - xp[j]) + fp[j]
    if y != y:  # NaN (an infinite slope): numpy's fallbacks
        y = slope * (x - xp[j + 1]) + fp[j + 1]
        if y != y and fp[j] == fp[j + 1]:
            y = fp[j]
    return y


def _quantize(value: float, resolution: float) -> float:
    return round(round(value / resolution) * resolution, 12) if resolution > 0 else float(value)


class _GridLookup:
    """Bilinear interpolation on a grid, edges held; positions in increments."""

    def __init__(self, g: Grid) -> None:
        self.table = np.asarray(g.errors, dtype=float) * UNITS_PER_UM
        self.rows, self.cols = self.table.shape
        self.u0, self.du = g.start1 * UNITS_PER_MM, g.step1 * UNITS_PER_MM
        self.v0, self.dv = g.start2 * UNITS_PER_MM, g.step2 * UNITS_PER_MM
        self.t = self.table.tolist()  # Python floats: a scalar lookup without numpy calls

    def __call__(self, p1: float, p2: float) -> float:
        u = min(max((p1 - self.u0) / self.du, 0.0), self.cols - 1.0)
        v = min(max((p2 - self.v0) / self.dv, 0.0), self.rows - 1.0)
        i = min(int(u), self.cols - 2) if self.cols > 1 else 0
        j = min(int(v), self.rows - 2) if self.rows > 1 else 0
        fu, fv = u - i, v - j
        i1, j1 = min(i + 1, self.cols - 1), min(j + 1, self.rows - 1)
        r0, r1 = self.t[j], self.t[j1]
        top = r0[i] + (r0[i1] - r0[i]) * fu
        bottom = r1[i] + (r1[i1] - r1[i]) * fu
        return float(top + (bottom - top) * fv)


__all__ = ["TwinEngine"]
