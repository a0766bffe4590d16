"""An ISO 230-2 bidirectional positioning test on the twin, and what a commissioning makes
of it (docs/twin.md).

The test cycle of ISO 230-2:2014 (§5, the "standard test cycle"): per run, the axis
comes from below the first target by the approach overrun and stops at every target
moving positive, waits the dwell and reads the deviation (true position − target, what a
laser interferometer reads: `TWIN::true_position`); then it goes beyond the last target by
the overrun and stops at every target moving negative. `runs` runs (the standard asks
for five).

The procedure talks to the machine only through a `Bench` — in-process and stepped
(`StepBench`: exact, as fast as the host computes; `geo-server measure`), or on a
running server (`LiveBench`: the Zenoh command `cmd/measure`) — and through the object
service's public calls (object writes, NC lines), so it measures exactly what a client
would. Before the test the named compensations are switched off with NC `COMP OFF`
(000 §5.1) and afterwards back on when they were on.

Commissioning (`commission`): the LSEC table and the backlash from the result, written
into the axis's lists as they are (only the value tokens), ready for `reload`:

- unilateral LSEC (000 §4.4): the table holds the measured errors Δs = actual −
  programmed *in the axis's reference direction* — the direction in which backlash
  compensation adds nothing (`lr_param.anwahl_losekomp`: 1 positive, 2 negative) — and
  the backlash is the mean difference of the other direction (000 §2.3);
- bilateral LSEC: the two tables hold x̄↑ and x̄↓; the reversal is inside them, so the
  backlash compensation has to be switched off (lose 0) or measured on.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from geo_server.dictionary import load_dictionary
from geo_server.errors import GeoError
from geo_server.kernel.temperature import offset as tempc_offset
from geo_server.listfile import rewrite_values
from geo_server.listfile.writer import write_atomic
from geo_server.model import COMP_NAMES, SELECTED_OBJECTS, MachineConfig
from geo_server.seam import Measured, Stepping
from geo_server.twin import iso230
from geo_server.twin.iso230 import Evaluation
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM, parse_axis_names


class MeasureError(GeoError):
    """The test cannot run (axis busy, not homed, target out of reach, no twin)."""


@dataclass(frozen=True)
class MeasurementPlan:
    """One bidirectional positioning test (ISO 230-2:2014 §5)."""

    axis: int  # logical axis number
    targets: tuple[float, ...]  # P_i, mm or °, ascending
    runs: int = 5
    overrun: float = 5.0  # mm or °, beyond the first and the last target
    #: standstill before each reading, s of the machine's clock (cycles × cycle length;
    #: the twin's thermal clock runs `time_scale` times faster)
    dwell_s: float = 0.2
    compensation_off: tuple[str, ...] = ()  # COMP kinds switched off during the test


class Bench(Protocol):
    """What the test needs of a machine."""

    def move(self, axis: int, position: float) -> None:
        """Move to `position` (increments) and return once the axis stands there."""

    def dwell(self, seconds: float) -> None: ...

    def at(self, axis: int, position: float) -> bool:
        """The axis stands at `position` (increments; modulo axes: within the period)."""

    def true_position(self, axis: int) -> float:
        """Increments."""

    def nc(self, text: str) -> None:
        """Run NC lines to their end."""

    def read(self, name: str, axis: int) -> Any: ...

    def write(self, name: str, axis: int, value: object) -> None:
        """Write an object and return once it is applied."""


#: Positions a test may reach (mm or °): the range of `SIM::target_position`.
MAX_POSITION = load_dictionary().by_name("SIM::target_position").type.hi / UNITS_PER_MM


def check_plan(plan: MeasurementPlan) -> None:
    """MeasureError unless the plan is a test ISO 230-2 can evaluate: at least two
    finite, strictly ascending targets, an overrun > 0 (every target is approached from
    its side: without one, the first and the last are reached from the wrong direction),
    two runs or more, a dwell ≥ 0, every position within the axis' increments."""
    t = plan.targets
    if len(t) < 2 or not all(math.isfinite(v) for v in t):
        raise MeasureError("targets: two or more finite positions (mm or °)")
    if any(b <= a for a, b in itertools.pairwise(t)):
        raise MeasureError("targets must ascend strictly")
    if not (math.isfinite(plan.overrun) and plan.overrun > 0):
        raise MeasureError("overrun must be > 0 (mm or °): each target is approached from its side")
    if max(abs(t[0] - plan.overrun), abs(t[-1] + plan.overrun)) > MAX_POSITION:
        raise MeasureError(f"targets ± overrun must stay within ±{MAX_POSITION:.0f} mm")
    if plan.runs < 2:
        raise MeasureError("runs must be 2 or more (ISO 230-2 §2.15 needs n ≥ 2)")
    if not (math.isfinite(plan.dwell_s) and plan.dwell_s >= 0):
        raise MeasureError("dwell_s must be ≥ 0")
    unknown = [k for k in plan.compensation_off if k not in _SELECTED]
    if unknown:
        raise MeasureError(f"off: unknown kind(s) {unknown}; known: {', '.join(_SELECTED)}")


def run_test(bench: Bench, plan: MeasurementPlan, name: str = "") -> Evaluation:
    """Run the test cycle; the deviations in µm (0.001° rotary).

    The compensations of `plan.compensation_off` that are selected are switched off one
    by one with NC `COMP OFF` and, whatever happens, the same ones back on after the
    test — exactly those, one line each (a `COMP ON` line fails as a whole when one of
    its kinds cannot be selected, 000 p.73)."""
    check_plan(plan)
    targets = [t * UNITS_PER_MM for t in plan.targets]
    if not bench.read("SIM::homed", plan.axis):
        raise MeasureError(f"axis {plan.axis} is not homed")
    label = name or _axis_name(bench, plan.axis)
    switched: list[str] = []
    try:
        for kind in plan.compensation_off:
            if _selected(bench, plan.axis, kind):
                switched.append(kind)
                bench.nc(f"{label}[COMP OFF {kind}]")
        m = len(targets)
        up, down = np.zeros((plan.runs, m)), np.zeros((plan.runs, m))
        over = plan.overrun * UNITS_PER_MM
        for j in range(plan.runs):
            bench.move(plan.axis, targets[0] - over)
            for i, target in enumerate(targets):
                up[j, i] = _reading(bench, plan, target)
            bench.move(plan.axis, targets[-1] + over)
            for i in range(m - 1, -1, -1):
                down[j, i] = _reading(bench, plan, targets[i])
    finally:
        for kind in switched:
            bench.nc(f"{label}[COMP ON {kind}]")
    return iso230.evaluate(plan.targets, up, down)


def _reading(bench: Bench, plan: MeasurementPlan, target: float) -> float:
    """Approach `target`, dwell, check the axis still stands there, read (µm)."""
    bench.move(plan.axis, target)
    bench.dwell(plan.dwell_s)
    if not bench.at(plan.axis, target):
        raise MeasureError(
            f"axis {plan.axis} left {target:.0f} during the dwell (moved by someone else?)"
        )
    return (bench.true_position(plan.axis) - target) / UNITS_PER_UM


#: COMP kind -> the object that tells whether it is selected (000 §5.1).
_SELECTED = {COMP_NAMES[kind]: name for kind, name in SELECTED_OBJECTS.items()}


def _axis_name(bench: Bench, axis: int) -> str:
    """The name NC uses for the axis (`SIM::axis_names`)."""
    names = parse_axis_names(str(bench.read("SIM::axis_names", 0)))
    return next((name for name, nr in names.items() if nr == axis), str(axis))


def axis_number(cfg: MachineConfig, axis: object) -> int:
    """A logical axis number from a number or a name (`X`, any case)."""
    for nr, ax in cfg.axes.items():
        if (axis == nr and not isinstance(axis, bool)) or (
            isinstance(axis, str) and axis.upper() in (str(nr), ax.params.name.upper())
        ):
            return nr
    names = ", ".join(f"{ax.params.name or nr} ({nr})" for nr, ax in cfg.axes.items())
    raise MeasureError(f"no axis {axis!r}: not an axis of this machine ({names})")


def _selected(bench: Bench, axis: int, kind: str) -> bool:
    return bool(bench.read(_SELECTED[kind], axis))


# ---------------------------------------------------------------------- benches


class StepBench:
    """A machine in stepped mode in this process: exact and as fast as the host."""

    def __init__(self, service: Measured, max_cycles_per_move: int = 200_000) -> None:
        """`service`: a `geo_server.service.ObjectService` in stepped mode (duck-typed:
        this layer sits below the service); the bench steps its scheduler."""
        self.svc = service
        self.max_cycles = max_cycles_per_move
        self._periods: dict[int, float] = {}

    @property
    def _stepper(self) -> Stepping:
        """The service's stepper (`ObjectService.stepper`: RuntimeError once its cycles
        run by themselves)."""
        return self.svc.stepper()

    def _period(self, axis: int) -> float:
        """The modulo period in increments (0: not a modulo axis): the command position
        of a modulo axis reads wrapped (docs/design.md §3.8). Looked up once per axis."""
        if axis not in self._periods:
            params = self.svc.info.config.axes[axis].params
            self._periods[axis] = float(params.modulo_period) if params.modulo else 0.0
        return self._periods[axis]

    def at(self, axis: int, position: float) -> bool:
        if self.read("SIM::velocity", axis) != 0:
            return False
        diff = float(self.read("SIM::command_position", axis)) - round(position)
        period = self._period(axis)
        if period:
            diff = (diff + period / 2) % period - period / 2
        return abs(diff) < 0.5

    def move(self, axis: int, position: float) -> None:
        self.write("SIM::target_position", axis, round(position))
        for _ in range(self.max_cycles):
            if self.at(axis, position):
                return
            self._stepper.step(1)
        raise MeasureError(f"axis {axis} did not reach {position:.0f} increments")

    def dwell(self, seconds: float) -> None:
        self._stepper.step(max(1, round(seconds / float(self.svc.info.cycle_s))))

    def true_position(self, axis: int) -> float:
        return float(self.read("TWIN::true_position", axis))

    def nc(self, text: str) -> None:
        """Run NC lines to their end; MeasureError if they report an error."""
        since = self._cycle()
        pending = self.svc.nc.run(text)
        for _ in range(self.max_cycles):
            self._stepper.step(1)
            if not self.read("SIM::program_running", 0):
                break
        else:
            raise MeasureError(f"NC {text!r} did not end")
        if pending.done():
            pending.result()
        self._check_errors(text, since)

    def _check_errors(self, text: str, since: int) -> None:
        """An NC error reported since cycle `since` (an operation is stamped with the
        cycle completed before it was applied)."""
        for e in self.svc.errors():
            if e["cycle"] >= since and e["severity"] == "error" and e["file"] == "<nc>":
                raise MeasureError(f"NC {text!r}: {e['message']}")

    def read(self, name: str, axis: int) -> Any:
        """An object's value from the snapshot due now (0x707 while stalled)."""
        return self.svc.current().value(self.svc.lookup(name, axis), axis)

    def write(self, name: str, axis: int, value: object) -> None:
        pending = self._submit(name, axis, value)
        self._stepper.step(1)
        if pending.done():
            _raise_refused(pending.result())

    def _submit(self, name: str, axis: int, value: object) -> Any:
        """Validate and queue one object write (the future of `submit_writes`)."""
        return self.svc.submit_writes([self.svc.prepare_name(name, axis, value)])

    def _cycle(self) -> int:
        """The cycle of the latest snapshot (also while stalled)."""
        return int(self.svc.current(stale_ok=True).cycle)


class LiveBench(StepBench):
    """A running server (real time or free-running): moves are object writes, waits
    watch the published snapshots; no sleep is longer than a cycle's worth of polls.
    `timeout_s` bounds every wait, `deadline_s` the whole test; `cancel` ends it."""

    def __init__(
        self,
        service: Measured,
        timeout_s: float = 120.0,
        deadline_s: float = 3600.0,
        cancel: threading.Event | None = None,
        *,
        settle: Callable[[Any, float], Any],
    ) -> None:
        """`settle(pending, timeout)`: the service's wait for a queued operation (its
        timeout/withdraw rule, `commands.ports.Ports.settle_sync`)."""
        super().__init__(service)
        self.settle = settle
        self.timeout = timeout_s
        self.deadline = time.monotonic() + deadline_s
        self.cancel = cancel or threading.Event()

    def _until(self, done: Callable[[], bool], what: str) -> None:
        deadline = min(time.monotonic() + self.timeout, self.deadline)
        while not done():
            if self.cancel.is_set():
                raise MeasureError("the measurement was cancelled")
            if time.monotonic() > deadline:
                raise MeasureError(f"{what} did not happen in time")
            time.sleep(max(float(self.svc.info.cycle_s), 0.0005))

    def move(self, axis: int, position: float) -> None:
        self.write("SIM::target_position", axis, round(position))
        self._until(lambda: self.at(axis, position), f"axis {axis} reaching {position:.0f}")

    def dwell(self, seconds: float) -> None:
        start = self._cycle()
        cycles = max(1, round(seconds / float(self.svc.info.cycle_s)))
        self._until(lambda: self._cycle() >= start + cycles, "the dwell")

    def write(self, name: str, axis: int, value: object) -> None:
        _raise_refused(self.settle(self._submit(name, axis, value), self.timeout))

    def nc(self, text: str) -> None:
        since = self._cycle()
        self.settle(self.svc.nc.run(text), self.timeout)
        self._until(lambda: not self.read("SIM::program_running", 0), f"NC {text!r}")
        self._check_errors(text, since)


def _raise_refused(outcome: Any) -> None:
    """The error a one-item object write raised when the cycle applied it (the outcome
    of `submit_writes` is a tuple with None or the error of each item)."""
    if isinstance(outcome, tuple) and outcome[0] is not None:
        raise outcome[0]


# ---------------------------------------------------------------------- a plan from JSON

#: Bounds of a plan that arrives over the network (a measurement holds the machine).
MAX_TARGETS = 1500  # the LSEC table's maximum (P-COMP-00020)
MAX_RUNS = 50
KINDS = tuple(_SELECTED)


def plan_from_json(spec: Any, cfg: MachineConfig) -> MeasurementPlan:
    """A `MeasurementPlan` from a JSON object: {"axis": 1 or "X", "targets": [mm…] (default: the
    axis' LSEC setpoints), "runs": 5, "overrun": 5.0, "dwell_s": 0.2, "off": ["LEAD"]}.
    MeasureError names the field that is wrong."""
    if not isinstance(spec, dict):
        raise MeasureError('the plan must be a JSON object, e.g. {"axis": "X"}')
    unknown = set(spec) - {"axis", "targets", "runs", "overrun", "dwell_s", "off"}
    if unknown:
        raise MeasureError(f"unknown field(s) {sorted(unknown)} in the plan")
    axis = axis_number(cfg, spec.get("axis"))
    targets = spec.get("targets")
    if targets is None:
        targets = lsec_setpoints(cfg, axis)
    if not isinstance(targets, list | tuple) or not all(
        isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t) for t in targets
    ):
        raise MeasureError("targets must be a list of finite numbers (mm or °)")
    if not 2 <= len(targets) <= MAX_TARGETS:
        raise MeasureError(f"targets: 2 … {MAX_TARGETS} positions, got {len(targets)}")
    runs = spec.get("runs", 5)
    if not isinstance(runs, int) or isinstance(runs, bool) or not 2 <= runs <= MAX_RUNS:
        raise MeasureError(f"runs must be an integer 2 … {MAX_RUNS}")
    numbers = {}
    for key, default, low, top in (("overrun", 5.0, 0.001, 1000.0), ("dwell_s", 0.2, 0.0, 10.0)):
        v = spec.get(key, default)
        if not isinstance(v, int | float) or isinstance(v, bool) or not low <= v <= top:
            raise MeasureError(f"{key} must be a number {low:g} … {top:g}")
        numbers[key] = float(v)
    off = spec.get("off", [])
    if not isinstance(off, list) or not all(isinstance(k, str) and k.upper() in KINDS for k in off):
        raise MeasureError(f"off must be a list of {', '.join(KINDS)}")
    plan = MeasurementPlan(
        axis=axis,
        targets=tuple(float(t) for t in targets),
        runs=runs,
        overrun=numbers["overrun"],
        dwell_s=numbers["dwell_s"],
        compensation_off=tuple(k.upper() for k in off),
    )
    check_plan(plan)
    return plan


# ---------------------------------------------------------------------- commissioning


@dataclass(frozen=True)
class Commissioning:
    """What a test gives the lists: LSEC values per setpoint (0.1 µm) and the backlash."""

    axis: int
    setpoints: tuple[float, ...]  # increments
    pos: tuple[int, ...]
    neg: tuple[int, ...] | None
    backlash: int | None  # increments (getriebe[0].lose), None: leave as it is


def commission(
    evaluation: Evaluation, axis: int, bilateral: bool, reference_direction: int
) -> Commissioning:
    """LSEC table and backlash from a test measured without LSEC and backlash
    compensation (module docstring)."""
    setpoints = tuple(round(p * UNITS_PER_MM) for p in evaluation.targets)
    if bilateral:
        pos = tuple(round(v * UNITS_PER_UM) for v in evaluation.mean_up)
        neg = tuple(round(v * UNITS_PER_UM) for v in evaluation.mean_down)
        return Commissioning(axis, setpoints, pos, neg, None)
    ref = evaluation.mean_up if reference_direction > 0 else evaluation.mean_down
    other = evaluation.mean_down if reference_direction > 0 else evaluation.mean_up
    table = tuple(round(v * UNITS_PER_UM) for v in ref)
    # lost motion: how far the other direction stops beyond the reference one
    lose = round(float(np.mean(other - ref)) * UNITS_PER_UM * reference_direction)
    return Commissioning(axis, setpoints, table, None, lose)


def write_lists(c: Commissioning, axis_list: Path | str, comp_list: Path | str) -> list[str]:
    """Write the values into the axis's lists (only the value tokens; the table keeps its
    layout: the setpoints must be those of the list's table). Both files or neither: if
    the second cannot be written, the first gets its old text back. Returns the files
    written."""
    changes: dict[str, str] = {}
    for i, v in enumerate(c.pos):
        changes[f"kw.ssfk.table[{i}].pos"] = str(v)
    if c.neg is not None:
        for i, v in enumerate(c.neg):
            changes[f"kw.ssfk.table[{i}].neg"] = str(v)
    comp_path = Path(comp_list)
    before = comp_path.read_bytes()
    rewrite_values(comp_path, changes)
    written = [str(comp_list)]
    if c.backlash is not None:
        try:
            rewrite_values(axis_list, {"getriebe[0].lose": str(c.backlash)})
        except BaseException:
            write_atomic(comp_path, before)
            raise
        written.append(str(axis_list))
    return written


def lsec_list(c: Commissioning, name: str) -> str:
    """A compensation value list [COMP] holding only the LSEC table of `c` (000 §4.4,
    P-COMP-00017…00028): non-equidistant (`interval 0`, one `setpoint` per target), in
    0.1 µm (`unit 1`), unilateral or bilateral — ready to load as the axis' list or to
    copy into one."""
    lines = [
        f"# LSEC table of axis {name} ({c.axis}) measured on the twin by geo-server measure",
        "# values: measured errors ds = s_actual - s_programmed [0.1 um] (000 §4.4)",
        f"kopf.achs_nr {c.axis}",
        f"kopf.log_achs_name {name}",
        "kw.ssfk.unit 1",
        "kw.ssfk.interval 0",
        f"kw.ssfk.kw_startpos {c.setpoints[0]}",
        f"kw.ssfk.kw_nr_max {len(c.setpoints)}",
        f"kw.ssfk.bilateral {int(c.neg is not None)}",
        "kw.ssfk.modulo 0",
    ]
    for i, sp in enumerate(c.setpoints):
        lines.append(f"kw.ssfk.table[{i}].setpoint {sp}")
        lines.append(f"kw.ssfk.table[{i}].pos {c.pos[i]}")
        if c.neg is not None:
            lines.append(f"kw.ssfk.table[{i}].neg {c.neg[i]}")
    return "\n".join(lines) + "\n"


def backlash_lines(c: Commissioning, reference_direction: int) -> str:
    """The backlash entries of the axis parameter list (000 §2, P-AXIS-00103/00021) to
    copy into it; empty for a bilateral table (its reversal is inside the table)."""
    if c.backlash is None:
        return ""
    anwahl = 1 if reference_direction > 0 else 2
    return (
        f"# backlash of axis {c.axis} measured on the twin: copy into its axis list\n"
        f"getriebe[0].lose {c.backlash}\n"
        f"lr_param.anwahl_losekomp {anwahl}\n"
    )


def lsec_setpoints(cfg: MachineConfig, axis: int) -> tuple[float, ...]:
    """The setpoints (mm or °) of the axis's LSEC table, the natural targets of a test
    whose result becomes that table."""
    comp = cfg.axes[axis].comp
    lsec = comp.lsec if comp is not None else None
    if lsec is None:
        raise MeasureError(f"axis {axis} has no LSEC table to take the targets from")
    return tuple(float(p) / UNITS_PER_MM for p in lsec.setpoint)


def tempc_line(bench: Bench, axis: int) -> tuple[float, float, float]:
    """The temperature compensation the axis applies now, as (position_0 [incr.],
    offset_0 [µm], coefficient [µm/m]) — zero when it is not active (000 p.15)."""
    if not bench.read("TEMPC::activated", axis):
        return (0.0, 0.0, 0.0)
    return (
        float(bench.read("TEMPC::position_0", axis)),
        float(bench.read("TEMPC::offset_0", axis)) / UNITS_PER_UM,
        float(bench.read("TEMPC::coefficient", axis)),
    )


@dataclass(frozen=True)
class ReferencePoint:
    """One test of a reference measurement: the chamber temperature, the mean sensor
    temperature during the test, the result and the compensation that was active."""

    chamber: float
    temperature: float
    evaluation: Evaluation
    tempc: tuple[float, float, float]

    def rows(self, axis: int) -> list[tuple[int, float, float, float]]:
        """Rows (axis, °C, position mm, deviation µm) for `geo-plc-tempcomp`: what the
        temperature compensation must add at P_i = what it adds now − x̄_i (the rows of
        `iso230.reference_rows`, −x̄_i, plus the active line)."""
        p0, off, coef = self.tempc

        def active(p_mm: float) -> float:  # µm the temperature compensation adds now
            return off + tempc_offset(0.0, coef, p0, p_mm * UNITS_PER_MM) / UNITS_PER_UM

        rows = iso230.reference_rows(axis, self.temperature, self.evaluation)
        return [(a, round(t, 3), p, round(dev + active(p), 4)) for a, t, p, dev in rows]


def reference_measurement(
    bench: Bench, plan: MeasurementPlan, temperatures: Sequence[float]
) -> list[ReferencePoint]:
    """A reference measurement (000 §3.2, p.16): the test repeated in a climate chamber
    at each temperature (`TWIN::ambient_temperature` held, `TWIN::soak`), the axis'
    sensor read before and after each test. The compensations stay as they are; the
    rows add the active temperature compensation back (`ReferencePoint.rows`), so the
    result is the whole line the compensation needs at that temperature."""
    points = []
    for chamber in temperatures:
        bench.write("TWIN::ambient_temperature", 0, float(chamber))
        bench.write("TWIN::soak", 0, 1)
        bench.dwell(0.2)  # the sensors sample the soaked nodes
        t0 = float(bench.read("TWIN::sensor_temperature", plan.axis))
        ev = run_test(bench, plan)
        t1 = float(bench.read("TWIN::sensor_temperature", plan.axis))
        points.append(
            ReferencePoint(float(chamber), (t0 + t1) / 2, ev, tempc_line(bench, plan.axis))
        )
    return points


__all__ = [
    "Bench",
    "Commissioning",
    "LiveBench",
    "MeasureError",
    "MeasurementPlan",
    "ReferencePoint",
    "StepBench",
    "axis_number",
    "backlash_lines",
    "check_plan",
    "commission",
    "lsec_list",
    "lsec_setpoints",
    "plan_from_json",
    "reference_measurement",
    "run_test",
    "tempc_line",
    "write_lists",
]
