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
µm/0.001° are converted once, at load.

What a cycle changes — the motion heat, the thermal update every `thermal_every` cycles
(steps 1 and 2) — is one compiled function (`laws.twin_cycle`), the same for a single cycle, a
pass of moving cycles and a stretch at rest (docs/design.md §13: the three paths are one
function in a loop). What needs Python — the sensors' seeded noise (step 3) and a new
scatter draw when an axis starts, stops or reverses — it reports as flags, and the
engine handles them after the cycle, in the cycle's order. The outputs (steps 4 and 5)
are only evaluated when someone looks (`evaluate`); all 1-D curves of all axes are then
served by one merged table lookup.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from geo_server.faults import OPEN_CIRCUIT_C
from geo_server.jit import Packed
from geo_server.kernel.tables import Packer
from geo_server.twin.laws import (
    AMBIENT,
    AXIS_SENSOR,
    CYCLES,
    DIRECTION,
    DT,
    EVERY,
    EXP_COEF,
    EXP_NODE,
    EXP_REF,
    FAULTS,
    HALF_REVERSAL,
    HELD,
    LIN_OFF,
    LIN_REF,
    LIN_SLOPE,
    LINE_A,
    LINE_B,
    MOTION,
    MOTION_GAIN,
    MOTION_SLOT,
    NA,
    NC,
    NEXT_SAMPLE,
    NN,
    NODE_K,
    NODE_TEMP,
    NS,
    NSN,
    OFFSET,
    REF_DIR,
    RNG,
    S_DUE,
    S_EXTRA,
    S_FAULT,
    S_INV_RES,
    S_NODE,
    S_NOISE,
    S_PERIOD,
    S_RES,
    S_VALUE,
    SCATTER_NOW,
    SENSOR_TEMP,
    SIGN_BEFORE,
    SPINDLE_GAIN,
    T_REF,
    V_SCALE,
    VSUM,
    Geometry,
    TwinState,
    ambient_at,
    errors,
    lines,
    offsets,
    quantize,
    rest_cycles,
    twin_cycle,
)
from geo_server.twin.model import AxisTwin, Curve, RigidBody, TwinConfig
from geo_server.twin.noise import normal, seed
from geo_server.twin.volumetric import rigid_tables
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM
from geo_server.volcomp.evaluator import Evaluator
from geo_server.volcomp.model import build_model


def _curve(c: Curve, tab: Packer) -> tuple[int, int]:
    """A 1-D error curve (mm → increments, µm → increments) into `tab`: (offset, points)."""
    pos = np.asarray(c.positions, dtype=float) * UNITS_PER_MM
    return tab.table(pos, np.asarray(c.errors, dtype=float) * UNITS_PER_UM), len(pos)


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
        #: the compiled cycle's arrays (rows above), allocated once; the attributes below
        #: are views of them
        self.A = np.zeros((NA, n))
        self.N = np.zeros((NN, len(cfg.nodes)))
        self.SN = np.zeros((NSN, len(cfg.sensors)))
        self.S = np.zeros(NS)
        self.S[RNG:] = seed(cfg.seed)
        self.C = np.zeros(NC, dtype=np.int64)
        self.S[DT] = self.dt = cycle_s * self.time_scale  # simulated seconds per cycle
        #: stretches at rest (`advance`) in which a thermal update or a sensor sample ran
        self.rest_events = 0
        axes = [cfg.axes.get(name, AxisTwin(name)) for name in self.names]
        self.period = np.array(list(modulo) or [0.0] * n, dtype=float)
        # state
        a = self.A
        self._vsum, self._sign_before = a[VSUM], a[SIGN_BEFORE]
        self.direction, self._scatter_now, self._offset = a[DIRECTION], a[SCATTER_NOW], a[OFFSET]
        self._line_a, self._line_b = a[LINE_A], a[LINE_B]
        self.direction[:] = [float(ax.reference_direction) for ax in axes]
        self._sign = np.zeros(n)
        self._still = np.zeros(n)  # the velocities of a machine at rest
        self._setup_geometry(axes, slot)
        self._setup_thermal(axes, slot)
        self._setup_rigid(cfg.rigid_body, slot)
        # outputs (read by the machine's snapshot)
        self.error, self.true_position, self.residual, self.friction_current = self.O

    # ------------------------------------------------------------------ the scalars

    @property
    def cycles(self) -> int:
        """Cycles run."""
        return int(self.C[CYCLES])

    @cycles.setter
    def cycles(self, value: int) -> None:
        self.C[CYCLES] = value

    @property
    def time(self) -> float:
        """Simulated seconds: cycles · dt (a product, never a running sum that drifts)."""
        return float(self.C[CYCLES] * self.S[DT])

    @property
    def ambient(self) -> float:
        """The ambient temperature (°C) of the last thermal update."""
        return float(self.S[AMBIENT])

    @ambient.setter
    def ambient(self, value: float) -> None:
        self.S[AMBIENT] = value

    @property
    def held_ambient(self) -> float | None:
        """A climate chamber: the ambient held at this temperature instead of the profile."""
        return float(self.S[AMBIENT]) if self.S[HELD] else None

    @property
    def _next_sample(self) -> float:
        return float(self.S[NEXT_SAMPLE])

    @_next_sample.setter
    def _next_sample(self, value: float) -> None:
        self.S[NEXT_SAMPLE] = value

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
        rows = self.A
        self.lin_off, self.lin_slope, self.lin_ref = rows[LIN_OFF], rows[LIN_SLOPE], rows[LIN_REF]
        self.lin_off[:] = [a.linear_offset * UNITS_PER_UM for a in axes]
        self.lin_slope[:] = [a.linear_slope * 1e-6 for a in axes]
        self.lin_ref[:] = [a.linear_reference * UNITS_PER_MM for a in axes]
        self.per_amp = np.array([a.periodic_amplitude * UNITS_PER_UM for a in axes])
        self.per_k = np.array(
            [
                2 * math.pi / (a.periodic_period * UNITS_PER_MM) if a.periodic_period else 0.0
                for a in axes
            ]
        )
        self.reversal = np.array([a.reversal * UNITS_PER_UM for a in axes])
        self.ref_dir = rows[REF_DIR]
        self.ref_dir[:] = [float(a.reference_direction) for a in axes]
        self.scatter = np.array([a.scatter * UNITS_PER_UM for a in axes])
        self._half_reversal = rows[HALF_REVERSAL]
        self._half_reversal[:] = self.reversal / 2
        self.fr_coulomb = np.array([a.friction_coulomb for a in axes])
        self.fr_viscous = np.array([a.friction_viscous for a in axes])
        # per mm/s (°/s) -> per increment/s: an increment is 0.1 µm (1e-4 °)
        self._fr_viscous_incr = self.fr_viscous * 1e-4
        # every 1-D curve of every axis: (source slot, target slot, direction it holds in)
        tab = Packer()
        curves: list[tuple[int, int, int, int, int]] = []  # (table, points, src, tgt, dir)
        for i, a in enumerate(axes):
            if a.pitch is not None:
                curves.append((*_curve(a.pitch, tab), i, i, 1 if a.pitch_negative else 0))
            if a.pitch_negative is not None:
                curves.append((*_curve(a.pitch_negative, tab), i, i, -1))
            for s in a.straightness:
                if s.over in slot:  # (an axis the machine lacks contributes nothing)
                    curves.append((*_curve(s.curve, tab), slot[s.over], i, 0))
        self._curves = bool(curves)
        #: per curve: table offset, points, source slot, target slot (`errors`)
        self.curve_i = np.array([c[:4] for c in curves], dtype=np.int64).reshape(-1, 4).T.copy()
        kind = np.array([c[4] for c in curves], dtype=float)
        self._tgt = self.curve_i[3]
        self._directional = bool(np.any(kind != 0))
        self._w_a = 1.0 - np.abs(kind) / 2
        self._w_b = kind / 2
        #: per curve: the source's modulo period (0: none), the direction's weight
        self.curve_f = np.zeros((2, len(curves)))
        self.curve_f[0] = self.period[self.curve_i[2]] if curves else []
        self._w = self.curve_f[1]
        self._w[:] = 1.0
        self.square = np.zeros((n, n))
        for i, a in enumerate(axes):
            for other, urad in a.squareness:
                if other in slot:
                    self.square[i, slot[other]] += urad * 1e-6
        # grids over two axes: (table, rows, columns, target, over1, over2) and (start1,
        # step1, start2, step2) in increments (`grid_error`)
        grids = [(i, g) for i, a in enumerate(axes) for g in a.grids]
        grids = [(i, g) for i, g in grids if g.over1 in slot and g.over2 in slot]
        self.grid_i = np.zeros((6, len(grids)), dtype=np.int64)
        self.grid_f = np.zeros((4, len(grids)))
        for k, (i, g) in enumerate(grids):
            t = np.asarray(g.errors, dtype=float) * UNITS_PER_UM
            self.grid_i[:, k] = (tab.add(t), *t.shape, i, slot[g.over1], slot[g.over2])
            self.grid_f[:, k] = (
                g.start1 * UNITS_PER_MM,
                g.step1 * UNITS_PER_MM,
                g.start2 * UNITS_PER_MM,
                g.step2 * UNITS_PER_MM,
            )
        self.tab = tab.done()
        #: ... as `errors` takes them
        self.geometry: Packed = tuple(
            Geometry(self.square, self.tab, self.curve_i, self.curve_f, self.grid_i, self.grid_f)
        )
        #: per axis: periodic amplitude and wave number, friction (coulomb, viscous per
        #: increment/s) of the drive's current (`errors`)
        self.E = np.array(
            [self.per_amp, self.per_k, self.fr_coulomb, self._fr_viscous_incr]
        ).reshape(4, n)
        #: outputs: error, true position, residual, friction current
        self.O = np.zeros((4, n))

    def _setup_thermal(self, axes: list[AxisTwin], slot: dict[str, int]) -> None:
        cfg = self.cfg
        nodes = list(cfg.nodes)
        index = {nd.name: k for k, nd in enumerate(nodes)}
        self.node_names = [nd.name for nd in nodes]
        nd_rows = self.N
        self.node_temp = nd_rows[NODE_TEMP]
        self.node_temp[:] = [nd.initial for nd in nodes]
        #: cycles between two updates of the thermal model: 10 ms of simulated time (the
        #: time constants are minutes), at least every cycle
        self.thermal_every = max(1, round(0.01 / self.dt)) if self.dt > 0 else 1
        self.C[EVERY] = self.thermal_every
        dt_thermal = self.thermal_every * self.dt
        nd_rows[NODE_K] = [1.0 - math.exp(-dt_thermal / nd.tau) for nd in nodes]
        nd_rows[MOTION_SLOT] = [slot.get(nd.motion_axis, 0) for nd in nodes]
        # the mean |v| of an update is the sum over its cycles / thermal_every
        nd_rows[MOTION_GAIN] = [
            nd.motion_gain * V_SCALE / self.thermal_every if nd.motion_axis in slot else 0.0
            for nd in nodes
        ]
        nd_rows[SPINDLE_GAIN] = [nd.spindle_gain for nd in nodes]
        #: the ambient profile: (time s, temperature °C) rows
        self.amb = np.array([[p[0] for p in cfg.ambient], [p[1] for p in cfg.ambient]])
        #: the arrays the compiled cycle takes (`machine.cycle.cycles`)
        self.state: Packed = tuple(TwinState(self.A, self.N, self.SN, self.S, self.C, self.amb))
        self.ambient = ambient_at(0.0, self.amb)
        self.S[T_REF] = self.t_ref = cfg.reference_temperature
        # expansion: coefficient (per K, dimensionless) and reference per axis, its node
        rows = self.A
        self.exp_coef, self.exp_ref = rows[EXP_COEF], rows[EXP_REF]
        self.exp_coef[:] = [a.expansion.coefficient * 1e-6 if a.expansion else 0.0 for a in axes]
        self.exp_ref[:] = [
            a.expansion.reference * UNITS_PER_MM if a.expansion else 0.0 for a in axes
        ]
        rows[EXP_NODE] = [index[a.expansion.node] if a.expansion else 0 for a in axes]
        # sensors: the node each reads, the axis it is shown on, its noise and resolution
        sensors = list(cfg.sensors)
        self.sensor_names = [s.name for s in sensors]
        sn = self.SN
        sn[S_NODE] = [index[s.node] for s in sensors]
        self.sensor_noise, self.sensor_res = sn[S_NOISE], sn[S_RES]
        self.sensor_period, self.sensor_due, self.sensor_value = (
            sn[S_PERIOD],
            sn[S_DUE],
            sn[S_VALUE],
        )
        self.sensor_extra_noise = sn[S_EXTRA]  # σ a "noisy" fault adds
        self.sensor_noise[:] = [s.noise for s in sensors]
        self.sensor_res[:] = [s.resolution for s in sensors]
        sn[S_INV_RES] = [_whole_inverse(s.resolution) for s in sensors]
        self.sensor_period[:] = [s.period for s in sensors]
        for k, s in enumerate(sensors):
            self.sensor_value[k] = quantize(
                self.node_temp[index[s.node]], s.resolution, sn[S_INV_RES, k]
            )
        n = len(axes)
        #: TWIN::sensor_temperature of each axis: its sensor, else the reference temperature
        self.axis_sensor = np.full(n, -1, dtype=int)
        for k, s in enumerate(sensors):
            if s.axis in slot and self.axis_sensor[slot[s.axis]] < 0:
                self.axis_sensor[slot[s.axis]] = k
        self.A[AXIS_SENSOR] = self.axis_sensor
        self.sensor_temperature = self.A[SENSOR_TEMP]
        self.sensor_temperature[:] = self.t_ref
        self._next_sample = 0.0 if sensors else math.inf
        #: injected sensor faults (geo_server/faults.py): "", "stuck", "noisy", "open"
        self.sensor_fault = [""] * len(sensors)
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
        """One GEO cycle (see the module docstring): `twin_cycle`, then what it flags
        (`events`), then the outputs (`evaluate`) unless nobody looks at this cycle."""
        flags = twin_cycle(self.A, self.N, self.SN, self.S, self.C, self.amb, velocity, spindle)
        if flags & MOTION:
            self.events(flags, velocity)
        if evaluate:
            self.evaluate(output, command, velocity)

    def events(self, flags: int, velocity: np.ndarray) -> None:
        """What `twin_cycle` left to Python, after its cycle: the scatter draws of a
        velocity that changed sign (`MOTION`)."""
        if flags & MOTION:
            sign = self._sign
            np.sign(velocity, out=sign)
            self._motion_event(sign)

    def at_rest(self) -> bool:
        """No motion heat waits for the next thermal update (|v| summed since the last
        one is zero), so the cycles at rest ahead are the machine's only change."""
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
        positions throughout) — `twin_cycle` in a loop (`rest_cycles`), stopping for the
        sensor samples — with the outputs evaluated once, at the end (docs/design.md §13).
        The numbers are those of `n` calls of `step`, by construction."""
        end = self.cycles + n
        events = 0
        while self.C[CYCLES] < end:
            changed, flags = rest_cycles(
                end, self.A, self.N, self.SN, self.S, self.C, self.amb, self._still, spindle
            )
            events += changed
            if flags & MOTION:
                self.events(flags, self._still)
        if events:
            self.rest_events += 1  # the outputs at rest may differ (`Machine.publish`)
        if evaluate:
            self.evaluate(output, command, self._still)

    def evaluate(self, output: np.ndarray, command: np.ndarray, velocity: np.ndarray) -> None:
        """This cycle's error, true position, residual and friction current (outputs
        only: `step` keeps the state, so a cycle nobody observes may leave them):
        `errors`, and the rigid-body errors of a volumetric model when there is one."""
        errors(self.A, self.E, self.geometry, output, command, velocity, self.O)
        if self._rigid is not None:
            self._rigid_errors(output, self.error)
            np.add(output, self.error, out=self.true_position)
            np.subtract(self.true_position, command, out=self.residual)

    def _motion_event(self, sign: np.ndarray) -> None:
        """An axis started, stopped or reversed: the direction it holds (kept while it
        stands), a new scatter draw for every axis that arrived, the offset."""
        arrived = np.not_equal(self._sign_before, 0.0)
        moving = np.not_equal(sign, 0.0)
        arrived &= ~moving  # was moving, stands now
        np.copyto(self.direction, sign, where=moving)
        for i in np.flatnonzero(arrived):  # scatter: a new random error for every approach
            self._scatter_now[i] = normal(self.S, RNG) * self.scatter[i]
        np.copyto(self._sign_before, sign)
        self._update_offset()

    def _update_offset(self) -> None:
        """The error lines' offset (`offsets`) and the bilateral curves' weights (after a
        reversal, an arrival, a soak or a reload). A curve that holds in one direction
        weighs w = 1 − |k|/2 + k·d/2 (1, or 0/1 for k = ±1)."""
        offsets(self.A)
        if self._curves and self._directional:
            w = self._w
            self.direction.take(self._tgt, out=w)
            w *= self._w_b
            w += self._w_a

    # ------------------------------------------------------------------ the climate

    def hold_ambient(self, temperature: float) -> None:
        """`TWIN::ambient_temperature` written: the machine stands in a climate chamber at
        `temperature` from now on (the twin file's profile no longer applies); the nodes
        follow with their time constants."""
        self.S[HELD] = 1.0
        self.ambient = float(temperature)

    def soak(self) -> None:
        """`TWIN::soak`: every thermal node takes the ambient temperature at once, as after
        a night in the hall — the start of a measurement at a known temperature. The
        sensors read it from their next sample on."""
        self.node_temp[:] = self.ambient
        self.sensor_due[:] = self.time
        self._next_sample = self.time if len(self.sensor_due) else math.inf
        self._update_lines()

    def _update_lines(self) -> None:
        """The error lines A·pos + B after the temperatures changed (`lines`) and the
        offset with them."""
        lines(self.A, self.N, self.S)
        self._update_offset()

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
        self.SN[S_FAULT, k] = FAULTS.index(kind)
        self.sensor_extra_noise[k] = sigma if kind == "noisy" else 0.0
        if kind == "open":
            self.sensor_value[k] = OPEN_CIRCUIT_C
            self._show_sensors()

    def _show_sensors(self) -> None:
        """TWIN::sensor_temperature of the axes with a sensor: its value."""
        has = self.axis_sensor >= 0
        self.sensor_temperature[has] = self.sensor_value[self.axis_sensor[has]]

    # ------------------------------------------------------------------ reload

    def take_state(self, old: TwinEngine) -> None:
        """Continue where `old` left off (a reload): time, node temperatures by name,
        directions, the random stream."""
        self.cycles = old.cycles
        self.ambient = ambient_at(self.time, self.amb)
        for k, name in enumerate(self.node_names):
            if name in old.node_names:
                self.node_temp[k] = old.node_temp[old.node_names.index(name)]
        for k, name in enumerate(self.sensor_names):
            if name in old.sensor_names:
                j = old.sensor_names.index(name)
                self.sensor_value[k], self.sensor_due[k] = old.sensor_value[j], old.sensor_due[j]
                # a reload does not mend a wire
                self.set_sensor_fault(k, old.sensor_fault[j], old.sensor_extra_noise[j])
        self._next_sample = float(self.sensor_due.min()) if len(self.sensor_due) else math.inf
        self._show_sensors()
        held = old.held_ambient
        if held is not None:
            self.hold_ambient(held)
        if len(self.direction) == len(old.direction):  # the same axes: the same motion
            self.direction[:] = old.direction
            self._sign_before[:] = old._sign_before
            self._scatter_now[:] = old._scatter_now
        self.S[RNG:] = old.S[RNG:]  # the seeded stream goes on
        self._update_lines()


def _whole_inverse(resolution: float) -> float:
    """1/resolution when it is a whole number (0.1, 0.01 …: the value is shown as that
    decimal, `quantize`), else 0."""
    if resolution <= 0:
        return 0.0
    inv = round(1.0 / resolution)
    return float(inv) if abs(inv * resolution - 1.0) < 1e-12 else 0.0


__all__ = ["TwinEngine"]
