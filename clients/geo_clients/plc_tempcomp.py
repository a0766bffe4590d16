"""PLC temperature adaptation: retune `TEMPC::*` live from a temperature (docs/design.md §10).

What a PLC does for the temperature compensation of the TF5200 manual (000 §3, p.14–24):
the compensation value is the straight line

    Δs(T, s) = offset_0(T) + coefficient(T) · 1e-6 · (s − position_0)        (000 p.15)

(positions and offsets in 0.1 µm — rotary axes 0.0001° — coefficient in µm/m, docs/design.md §3).
A **reference measurement** (000 p.16, "Reference measurement", Fig. 5) records the
deviation of the axis position against an external measuring system at several
temperatures; each temperature gives an error line. "Temperatures that are not measured
can be interpolated or extrapolated from the measured temperature curves", and "if the
virtual intersection of the approximated linear curves is chosen as the reference
position, the offset is independent of temperature" (000 p.17, "Determine parameters").
"The individual parameters can be set by the PLC depending on the current temperature
… a temperature signal (sensor) is transmitted to the PLC which then derives the
parameters from it" (000 p.17, "Influence of temperature"). This program is that PLC:
it reads a temperature, derives the parameters per axis and writes `TEMPC::position_0`
(0x45), `TEMPC::offset_0` (0x44) and `TEMPC::coefficient` (0x43) (000 p.22–23) over
Zenoh, Modbus or ADS at a fixed period.

Reference-measurement file (CSV, UTF-8)
---------------------------------------
`#` starts a comment line; blank lines are ignored; a line whose first cell is `axis` is
a header, and it selects the form of the rows after it (columns in any order, names
case-insensitive; a file may hold several sections with their own headers):

1. **Measured points** — `axis, temperature_C, position, deviation`: one row per measured
   point; the points of one (axis, temperature) are fitted with a least-squares line
   (at least two distinct positions).
2. **Error lines** — `axis, temperature_C, position_0, offset_0, coefficient`: one row
   per (axis, temperature), the line already read off the measurement curve.

`axis` is the logical axis number. Position-like columns (`position`, `deviation`,
`position_0`, `offset_0`) are in increments (0.1 µm / 0.0001°) unless the name carries a
unit suffix: `_um` (µm, ×10) or `_mm` (mm, ×10000), e.g. `position_mm, deviation_um`.
`coefficient` is in µm/m. `deviation` is the value the compensation has to add at that
position (the curve of 000 Fig. 5, from which the manual takes the parameters directly);
if your measuring system reports actual − programmed, negate it.

Derivation (pure functions below, checked by hand in the tests)
--------------------------------------------------------------
1. Per (axis, temperature) an error line `d(s) = a + b·s` (`fit_line` or from the row).
2. The reference position P of the axis: the one configured (`--reference-position`);
   else the **virtual intersection** of the lines when they all pass through one point
   within `tolerance` increments (least-squares point, `virtual_intersection`; with two
   non-parallel lines that is their intersection) and it lies inside SGN32; else the
   `position_0` all line rows share; else the mean of the measured positions.
3. For a temperature T: the line is interpolated linearly in T between the two
   neighbouring measured temperatures, and extrapolated linearly beyond the ends with
   the outermost pair (one measured temperature: that line). Interpolating the lines is
   the same as interpolating `offset_0 = d(P)` and `coefficient` linearly, so P only
   chooses the representation: `position_0 = round(P)`, `offset_0 = round(d_T(position_0))`
   (SGN32, rounded half away from zero), `coefficient = b_T · 1e6` rounded to
   `coefficient_decimals` (default 4) decimals. With P the virtual intersection,
   offset_0 stays constant and only the coefficient changes (000 p.17).
4. Every value is checked against the object's range (`TEMPC::coefficient`
   −10000 … 10000 µm/m, 000 p.21; SGN32 for the others) before anything is written;
   an axis with a value out of range is **not written** for that period and the log
   says which value, why and for which temperature.

Writes: only values that changed since the last write (all of them the first time),
in the order position_0, offset_0, coefficient; each write is logged with value,
transport and round-trip time; transient failures (timeouts, lost connections, ADS
0x707 not ready, 0x708 busy, 0x719 device timeout, 0x745/0x746/0x748 client sync errors)
are retried `retries` times. When a write of an axis fails for good, the rest of that
axis is not written in that period (no half-updated parameter set: offset_0 and the
coefficient belong to the position_0 they were derived for); the next period tries the
whole set again. Every parameter write is a step event ramped with `temp_comp_n_cycles`
by the server (docs/design.md §3). A temperature outside `plausible` (−40 … 150 °C by
default: a broken sensor wire reads the terminal's overrange value) writes nothing: the
server keeps the parameters of the last plausible reading (*hold*) until the sensor reads
sensibly again. How the adapter behaves under each injected fault is in docs/faults.md.

Temperature sources: `WarmUp` (a simulated warm-up curve `T(t) = T_end − (T_end −
T_start)·exp(−t/τ)`), `CsvTemperature` (timestamped samples `time,temperature_C`,
seconds from start or ISO-8601 times; linear between samples, held outside),
`ZenohTemperature` (the latest JSON number published on a Zenoh key by another program)
and `TwinSensors` (each axis' `TWIN::sensor_temperature`, the twin's sensor, read over
the same transport: the loop a real PLC closes, docs/twin.md).

Usage (see `--help`):

    python -m geo_clients.plc_tempcomp clients/geo_clients/data/reference_measurement.csv \\
        --warmup 20:35:600 --period 1 --via zenoh
    python -m geo_clients.plc_tempcomp REF.csv --csv temps.csv --via modbus --connect 127.0.0.1:5020
    python -m geo_clients.plc_tempcomp REF.csv --zenoh-key lab/spindle/temperature --via ads
    python -m geo_clients.plc_tempcomp REF.csv --derive 20 25 30 45    # print, no server
    python -m geo_clients.plc_tempcomp clients/geo_clients/data/twin_reference_measurement.csv \\
        --twin-sensor --period 1 --via modbus                            # the twin's sensors
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import itertools
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Protocol, TypeVar, runtime_checkable

from geo_clients.common import add_transport_arguments, client_from_args, transport_name
from geo_server.dictionary import load_dictionary, round_half_away
from geo_server.errors import AdsError, GeoError
from geo_server.kernel.temperature import offset as tempc_offset
from geo_server.kernel.temperature import slope as tempc_slope
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM

log = logging.getLogger("geo_clients.plc_tempcomp")
_T = TypeVar("_T")

#: Shipped example: the default machine's axes X, Y, Z measured at several temperatures.
EXAMPLE_REFERENCE = Path(__file__).resolve().parent / "data" / "reference_measurement.csv"

SGN32_MIN, SGN32_MAX = -(2**31), 2**31 - 1
#: Unit suffixes of position-like columns: factor to increments (0.1 µm / 0.0001°).
UNIT_FACTORS = {"": 1.0, "_incr": 1.0, "_um": UNITS_PER_UM, "_mm": UNITS_PER_MM}
#: ADS codes worth a retry: device not ready, device busy, device timeout (a write the
#: server could not apply in time), client sync timeout / invalid response / port locked
#: (pyads).
TRANSIENT_ADS = frozenset({0x707, 0x708, 0x719, 0x745, 0x746, 0x748})
#: Temperatures a machine's sensor can plausibly read (°C); outside: a failed sensor.
PLAUSIBLE_C = (-40.0, 150.0)
#: Writable TEMPC objects `(field, object name)` in write order, from the dictionary:
#: position_0 and offset_0 before coefficient (highest element ID first, 000 p.22–23), so
#: the line's anchor is in place before its slope changes.
PARAMETER_OBJECTS = tuple(
    (o.key_field, o.name) for o in reversed(load_dictionary().tempc_parameters())
)


class ReferenceTableError(GeoError, ValueError):
    """The reference-measurement file cannot be used (names file and line)."""


# ============================================================================ the math


@dataclass(frozen=True)
class ErrorLine:
    """A measured error line `d(s) = intercept + slope·s` at one temperature.

    `intercept` in increments (0.1 µm / 0.0001°), `slope` dimensionless (µm/µm).
    """

    temperature: float
    intercept: float
    slope: float

    def at(self, s: float) -> float:
        """Deviation at position `s`."""
        return self.intercept + self.slope * s

    @property
    def coefficient(self) -> float:
        """The slope in µm/m, the unit of `TEMPC::coefficient` (000 p.21)."""
        return self.slope * 1e6

    @classmethod
    def from_parameters(
        cls, temperature: float, position_0: float, offset_0: float, coefficient: float
    ) -> ErrorLine:
        """The line `offset_0 + coefficient·1e-6·(s − position_0)` (000 p.15)."""
        slope = tempc_slope(coefficient)
        return cls(temperature, offset_0 - slope * position_0, slope)


@dataclass(frozen=True)
class Parameters:
    """The TEMPC parameters for one axis at one temperature (object units)."""

    temperature: float
    position_0: int  # 0.1 µm
    offset_0: int  # 0.1 µm
    coefficient: float  # µm/m

    def compensation(self, s: float) -> float:
        """Δs at command position `s` by the manual's formula (000 p.15), unrounded."""
        return compensation(self, s)


def compensation(p: Parameters, s: float) -> float:
    """`Δs = offset_0 + coefficient·1e-6·(s − position_0)` (000 p.15; docs/design.md §6):
    the kernel's own law (`geo_server.kernel.temperature.offset`)."""
    return tempc_offset(p.offset_0, p.coefficient, p.position_0, s)


def fit_line(points: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """Least-squares line through `(position, deviation)` points: `(intercept, slope)`."""
    n = len(points)
    if n < 2:
        raise ValueError("a line needs at least two points")
    mx = sum(p for p, _ in points) / n
    my = sum(d for _, d in points) / n
    sxx = sum((p - mx) ** 2 for p, _ in points)
    if sxx == 0:
        raise ValueError("a line needs at least two distinct positions")
    sxy = sum((p - mx) * (d - my) for p, d in points)
    slope = sxy / sxx
    return my - slope * mx, slope


def virtual_intersection(
    lines: Sequence[ErrorLine], tolerance: float = 0.5
) -> tuple[float, float] | None:
    """The point all lines pass through (000 p.16 Fig. 5, "virtual intersection").

    The least-squares solution `(s, d)` of `d − slope_k·s = intercept_k` over all lines;
    None when the lines are parallel or miss that point by more than `tolerance`
    increments. Two non-parallel lines always have one.
    """
    if len(lines) < 2:
        return None
    # normal equations of [1, -b_k] · [d, s] = a_k
    n = len(lines)
    sb = sum(ln.slope for ln in lines)
    sbb = sum(ln.slope**2 for ln in lines)
    sa = sum(ln.intercept for ln in lines)
    sab = sum(ln.intercept * ln.slope for ln in lines)
    det = n * sbb - sb * sb
    if abs(det) <= 1e-18 * max(1.0, n * sbb):
        return None
    d = (sa * sbb - sab * sb) / det
    s = (sa * sb - n * sab) / det
    if max(abs(ln.at(s) - d) for ln in lines) > tolerance:
        return None
    return s, d


def interpolate_line(lines: Sequence[ErrorLine], temperature: float) -> ErrorLine:
    """The error line at `temperature`, linear in T between the neighbouring measured
    lines and extrapolated with the outermost pair beyond the ends (000 p.17)."""
    if not lines:
        raise ValueError("no measured lines")
    ordered = sorted(lines, key=lambda ln: ln.temperature)
    if len(ordered) == 1:
        only = ordered[0]
        return ErrorLine(temperature, only.intercept, only.slope)
    pairs = list(itertools.pairwise(ordered))
    lo, hi = pairs[-1]  # beyond the last: extrapolate with the outermost pair
    for a, b in pairs:
        if temperature <= b.temperature:  # below the first: the first pair
            lo, hi = a, b
            break
    w = (temperature - lo.temperature) / (hi.temperature - lo.temperature)
    return ErrorLine(
        temperature,
        lo.intercept + w * (hi.intercept - lo.intercept),
        lo.slope + w * (hi.slope - lo.slope),
    )


def derive_parameters(
    lines: Sequence[ErrorLine],
    temperature: float,
    reference_position: float,
    coefficient_decimals: int = 4,
) -> Parameters:
    """`position_0`, `offset_0`, `coefficient` at `temperature` for reference position P."""
    line = interpolate_line(lines, temperature)
    p0 = round_half_away(reference_position)
    return Parameters(
        temperature=temperature,
        position_0=p0,
        offset_0=round_half_away(line.at(p0)),
        coefficient=round(line.coefficient, coefficient_decimals) + 0.0,
    )


def warmup_temperature(t: float, start: float, end: float, time_constant: float) -> float:
    """First-order warm-up: `T(t) = end − (end − start)·exp(−t/τ)`; `start` for t ≤ 0."""
    if t <= 0:
        return start
    if time_constant <= 0:
        return end
    return end - (end - start) * math.exp(-t / time_constant)


def interpolate_samples(samples: Sequence[tuple[float, float]], t: float) -> float:
    """Linear interpolation of `(time, value)` samples sorted by time; held outside."""
    if not samples:
        raise ValueError("no samples")
    if t <= samples[0][0]:
        return samples[0][1]
    for (t0, v0), (t1, v1) in itertools.pairwise(samples):
        if t <= t1:
            return v0 if t1 == t0 else v0 + (v1 - v0) * (t - t0) / (t1 - t0)
    return samples[-1][1]


# ============================================================================ the table


@dataclass
class AxisReference:
    """The measured lines of one axis and how its reference position was chosen."""

    axis: int
    lines: list[ErrorLine]
    positions: list[float] = field(default_factory=list)  # measured positions (points)
    row_position_0: set[float] = field(default_factory=set)  # position_0 of line rows

    def reference_position(
        self, configured: float | None = None, tolerance: float = 0.5
    ) -> tuple[float, str]:
        """(P, how) by the rule of the module docstring."""
        if configured is not None:
            return float(configured), "configured"
        vi = virtual_intersection(self.lines, tolerance)
        if vi is not None and SGN32_MIN <= vi[0] <= SGN32_MAX:
            return vi[0], "virtual intersection"
        if len(self.row_position_0) == 1:
            return next(iter(self.row_position_0)), "position_0 of the table"
        pts = self.positions or sorted(self.row_position_0)
        return (sum(pts) / len(pts) if pts else 0.0), "mean measured position"


@dataclass
class ReferenceTable:
    """A parsed reference-measurement file: `AxisReference` per axis."""

    axes: dict[int, AxisReference]
    path: str = ""
    form: str = ""  # "points" | "lines"

    def lines(self, axis: int) -> list[ErrorLine]:
        return self.axes[axis].lines


def _column(header: list[str], base: str) -> tuple[int, float] | None:
    for suffix, factor in UNIT_FACTORS.items():
        if base + suffix in header:
            return header.index(base + suffix), factor
    return None


def _section_columns(header: list[str], where: str) -> dict[str, tuple[int, float]]:
    """Column index and unit factor of every column a section's header names."""

    def need(base: str) -> tuple[int, float]:
        col = _column(header, base)
        if col is None:
            raise ReferenceTableError(f"{where}: header has no column {base!r}: {header}")
        return col

    cols = {"axis": need("axis")}
    if "temperature_c" not in header:
        raise ReferenceTableError(f"{where}: header has no column 'temperature_C': {header}")
    cols["temperature"] = (header.index("temperature_c"), 1.0)
    if _column(header, "deviation") is not None:
        cols["position"], cols["deviation"] = need("position"), need("deviation")
        return cols
    p0, o0 = _column(header, "position_0"), _column(header, "offset_0")
    if p0 is None or o0 is None or "coefficient" not in header:
        raise ReferenceTableError(
            f"{where}: the header needs 'position, deviation' (measured points) or "
            f"'position_0, offset_0, coefficient' (error lines): {header}"
        )
    cols["position_0"], cols["offset_0"] = p0, o0
    cols["coefficient"] = (header.index("coefficient"), 1.0)
    return cols


def parse_reference(text: str, path: str = "<reference>") -> ReferenceTable:
    """Parse a reference-measurement file (format: module docstring).

    A line whose first cell is `axis` is a header; a file may hold several sections, each
    with its own header (e.g. measured points for one axis, error lines for another).
    """
    points: dict[tuple[int, float], list[tuple[float, float]]] = {}
    line_rows: dict[tuple[int, float], tuple[int, ErrorLine, float]] = {}
    first_line: dict[tuple[int, float], int] = {}
    header: list[str] | None = None
    cols: dict[str, tuple[int, float]] = {}
    forms: set[str] = set()
    for lineno, raw in enumerate(text.splitlines(), 1):
        stripped = raw.strip()
        if not stripped or stripped.startswith("#"):
            continue
        cells = [c.strip() for c in next(csv.reader([stripped]))]
        where = f"{path}:{lineno}"
        if cells[0].lower() == "axis":
            header = [c.lower() for c in cells]
            cols = _section_columns(header, where)
            continue
        values = _row_values(cells, header, cols, where)
        axis, temp = int(values["axis"]), values["temperature"]
        key = (axis, temp)
        if "deviation" in values:
            forms.add("points")
            if key in line_rows:
                raise ReferenceTableError(
                    f"{where}: axis {axis} at {temp} °C already given as a line "
                    f"(line {line_rows[key][0]})"
                )
            points.setdefault(key, []).append((values["position"], values["deviation"]))
            first_line.setdefault(key, lineno)
        else:
            forms.add("lines")
            if key in line_rows or key in points:
                first = line_rows[key][0] if key in line_rows else first_line[key]
                raise ReferenceTableError(
                    f"{where}: axis {axis} at {temp} °C given twice (first in line {first})"
                )
            p0 = values["position_0"]
            line = ErrorLine.from_parameters(temp, p0, values["offset_0"], values["coefficient"])
            line_rows[key] = (lineno, line, p0)
    axes = _reference_axes(points, line_rows, first_line, path)
    if not axes:
        raise ReferenceTableError(f"{path}: no measurements")
    return ReferenceTable(axes, path, "+".join(sorted(forms)))


def _row_values(
    cells: list[str], header: list[str] | None, cols: dict[str, tuple[int, float]], where: str
) -> dict[str, float]:
    """The values of one data row by column name, in the section's units (`cols`: the
    index and unit factor of each column): one per column of its header, all finite."""
    if header is None:
        raise ReferenceTableError(f"{where}: the first line must be a header (axis, …)")
    if len(cells) != len(header):
        raise ReferenceTableError(f"{where}: {len(cells)} values for {len(header)} columns")
    try:
        values = {k: float(cells[i]) * f for k, (i, f) in cols.items()}
    except ValueError as exc:
        raise ReferenceTableError(f"{where}: not a number ({exc})") from None
    if not all(math.isfinite(v) for v in values.values()):
        raise ReferenceTableError(f"{where}: values must be finite")
    return values


def _reference_axes(
    points: dict[tuple[int, float], list[tuple[float, float]]],
    line_rows: dict[tuple[int, float], tuple[int, ErrorLine, float]],
    first_line: dict[tuple[int, float], int],
    path: str,
) -> dict[int, AxisReference]:
    """Every axis' error lines, ordered by temperature: one fitted through the measured
    points of each (axis, temperature) (`fit_line`; `first_line` says where an error is)
    and the lines given as rows (`line_rows`: line number, line, position_0)."""
    axes: dict[int, AxisReference] = {}
    for (axis, temp), pts in sorted(points.items()):
        try:
            a, b = fit_line(pts)
        except ValueError as exc:
            raise ReferenceTableError(
                f"{path}:{first_line[(axis, temp)]}: axis {axis} at {temp} °C: {exc}"
            ) from None
        ref = axes.setdefault(axis, AxisReference(axis, []))
        ref.lines.append(ErrorLine(temp, a, b))
        ref.positions.extend(p for p, _ in pts)
    for (axis, _temp), (_ln, line, p0) in sorted(line_rows.items()):
        ref = axes.setdefault(axis, AxisReference(axis, []))
        ref.lines.append(line)
        ref.row_position_0.add(p0)
    for ref in axes.values():
        ref.lines.sort(key=lambda ln: ln.temperature)
    return axes


def load_reference(path: str | Path) -> ReferenceTable:
    """Read and parse a reference-measurement file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ReferenceTableError(f"{p}: {exc.strerror or exc}") from None
    return parse_reference(text, str(p))


# ============================================================================ temperatures


class TemperatureSource(Protocol):
    """Where the temperature comes from; `t` is the adapter's time in seconds."""

    def temperature(self, t: float) -> float | None: ...


@runtime_checkable
class PerAxisTemperatureSource(TemperatureSource, Protocol):
    """A source with a temperature per axis (`TwinSensors`, or one of your own): each
    axis is adapted to its own."""

    def temperature_of(self, axis: int, t: float) -> float | None: ...


@dataclass
class WarmUp:
    """Simulated warm-up: `T(t) = end − (end − start)·exp(−t/time_constant)` [°C, s]."""

    start: float = 20.0
    end: float = 35.0
    time_constant: float = 600.0

    def temperature(self, t: float) -> float:
        return warmup_temperature(t, self.start, self.end, self.time_constant)


@dataclass
class ConstantTemperature:
    """A fixed temperature (commissioning, tests)."""

    value: float

    def temperature(self, t: float) -> float:
        return self.value


class CsvTemperature:
    """Timestamped samples from a CSV `time,temperature_C` (header optional).

    `time` is seconds since the start of the recording, or an ISO-8601 timestamp
    (then relative to the earliest timestamp in the file, wherever its row is). Linear
    between samples, held outside.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self.samples = self._load(Path(path))

    def _load(self, path: Path) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        stamped: list[tuple[datetime, float]] = []
        for lineno, cells in enumerate(
            csv.reader(path.read_text(encoding="utf-8").splitlines()), 1
        ):
            if not cells or cells[0].strip().startswith("#"):
                continue
            if len(cells) < 2:
                raise ValueError(f"{path}:{lineno}: need time,temperature_C")
            ts, val = cells[0].strip(), cells[1].strip()
            try:
                temp = float(val)
            except ValueError:
                if not out and not stamped:
                    continue  # the header
                raise ValueError(f"{path}:{lineno}: not a temperature: {val!r}") from None
            try:
                out.append((float(ts), temp))
            except ValueError:
                try:
                    stamped.append((datetime.fromisoformat(ts), temp))
                except ValueError:
                    raise ValueError(
                        f"{path}:{lineno}: time must be seconds or ISO-8601: {ts!r}"
                    ) from None
        if stamped:
            t0 = min(stamp for stamp, _ in stamped)
            out += [((stamp - t0).total_seconds(), temp) for stamp, temp in stamped]
        if not out:
            raise ValueError(f"{path}: no samples")
        out.sort()
        return out

    def temperature(self, t: float) -> float:
        return interpolate_samples(self.samples, t)


class ZenohTemperature:
    """The latest temperature published on a Zenoh key (JSON number, or an object with
    `value` or `temperature_C`); None until the first sample arrives."""

    def __init__(self, session: Any, key: str) -> None:
        self.key = key
        self.value: float | None = None
        self.samples = 0
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            v = parse_temperature(sample.payload.to_bytes())
        except ValueError as exc:
            log.warning("temperature on %s ignored: %s", self.key, exc)
            return
        with self._lock:
            self.value = v
            self.samples += 1

    def temperature(self, t: float) -> float | None:
        with self._lock:
            return self.value

    def close(self) -> None:
        self._sub.undeclare()


class TwinSensors:
    """The twin's temperature sensors (`TWIN::sensor_temperature`, docs/twin.md), read
    over the client's transport like any object: each axis gets its own sensor's
    reading (`temperature_of`); `temperature` is the first axis' (for the log)."""

    def __init__(self, client: Any, axes: Iterable[int]) -> None:
        self.client = client
        self.axes = sorted(axes)

    def temperature_of(self, axis: int, t: float) -> float:
        return float(self.client.read("TWIN::sensor_temperature", axis))

    def temperature(self, t: float) -> float | None:
        return self.temperature_of(self.axes[0], t) if self.axes else None


def parse_temperature(payload: bytes) -> float:
    """A temperature from a payload: `23.5`, `{"value": 23.5}`, `{"temperature_C": 23.5}`."""
    try:
        v: Any = json.loads(payload)
    except ValueError:
        raise ValueError(f"not JSON: {payload[:40]!r}") from None
    if isinstance(v, dict):
        v = v.get("temperature_C", v.get("value"))
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"not a finite number: {payload[:40]!r}")
    return float(v)


# ============================================================================ the adapter


@dataclass
class WriteRecord:
    """One write attempt of one parameter (what the log shows)."""

    t: float
    temperature: float
    axis: int
    name: str
    value: Any
    transport: str
    ok: bool
    rtt_s: float = 0.0
    attempts: int = 0
    error: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class TickResult:
    """What one period did."""

    t: float
    temperature: float | None
    parameters: dict[int, Parameters] = field(default_factory=dict)
    writes: list[WriteRecord] = field(default_factory=list)
    refused: dict[int, str] = field(default_factory=dict)
    #: why nothing was written this period although a temperature was read ('' if not)
    held: str = ""


def is_transient(exc: BaseException) -> bool:
    """Worth a retry: timeouts, lost connections, ADS device not ready/busy/timeout."""
    if isinstance(exc, AdsError):
        return exc.code in TRANSIENT_ADS
    return isinstance(exc, TimeoutError | ConnectionError | OSError)


class TemperatureAdapter:
    """Derive and write TEMPC parameters from a temperature (000 p.17), one `tick` a period.

    `client`: any `GeoClient` (Zenoh, Modbus, ADS, in-process). Deterministic when driven
    by `tick(t)` with simulated times; `run()` drives it from the wall clock.
    """

    def __init__(
        self,
        client: Any,
        table: ReferenceTable,
        source: TemperatureSource,
        *,
        axes: Iterable[int] | None = None,
        reference_positions: dict[int, float] | None = None,
        tolerance: float = 0.5,
        coefficient_decimals: int = 4,
        retries: int = 3,
        retry_delay: float = 0.1,
        write_unchanged: bool = False,
        plausible: tuple[float, float] = PLAUSIBLE_C,
        sleep: Callable[[float], None] = time.sleep,
        clock: Callable[[], float] = time.perf_counter,
        transport: str | None = None,
        on_write: Callable[[WriteRecord], None] | None = None,
    ) -> None:
        self.client = client
        self.table = table
        self.source = source
        self.axes = sorted(axes) if axes is not None else sorted(table.axes)
        missing = [a for a in self.axes if a not in table.axes]
        if missing:
            raise ReferenceTableError(f"{table.path}: no measurement for axis {missing}")
        refs = reference_positions or {}
        self.reference: dict[int, tuple[float, str]] = {
            a: table.axes[a].reference_position(refs.get(a), tolerance) for a in self.axes
        }
        if isinstance(source, TwinSensors) and not source.axes:
            source.axes = list(self.axes)
        self.coefficient_decimals = coefficient_decimals
        self.retries = retries
        self.retry_delay = retry_delay
        self.write_unchanged = write_unchanged
        self.plausible = plausible
        self.sleep = sleep
        self.clock = clock
        self.transport = transport or transport_name(client)
        self.on_write = on_write
        self.dictionary = load_dictionary()
        self.written: dict[tuple[int, str], Any] = {}
        self.history: list[WriteRecord] = []
        for a in self.axes:
            p, how = self.reference[a]
            log.info("axis %d: reference position %.1f (%s)", a, p, how)

    # ------------------------------------------------------------------ derivation

    def parameters(self, temperature: float) -> dict[int, Parameters]:
        """The parameters of every axis at `temperature` (pure; nothing written)."""
        return {
            a: derive_parameters(
                self.table.lines(a), temperature, self.reference[a][0], self.coefficient_decimals
            )
            for a in self.axes
        }

    def check(self, p: Parameters) -> str:
        """'' when every value is inside its object's range, else why not (000 p.20–21)."""
        for attr, name in PARAMETER_OBJECTS:
            value = getattr(p, attr)
            try:
                self.dictionary.by_name(name).check_range(value)
            except AdsError as exc:
                return (
                    f"{exc.message} (derived for {p.temperature:.3f} °C from the reference "
                    "table; check the table and the temperature source)"
                )
        return ""

    # ------------------------------------------------------------------ one period

    def tick(self, t: float) -> TickResult:
        """Read the temperature at time `t` [s], derive and write the changed parameters."""
        temps = self._temperatures(t)
        temp = next(iter(temps.values()), None)
        result = TickResult(t, temp)
        if temp is None:
            log.info("t=%.3fs: no temperature yet; nothing written", t)
            return result
        if not all(v is not None and math.isfinite(v) for v in temps.values()):
            log.error("t=%.3fs: temperature %r is not finite; nothing written", t, temps)
            return result
        low, high = self.plausible
        wrong = {a: v for a, v in temps.items() if v is not None and not low <= v <= high}
        if wrong:
            # a broken wire reads the terminal's overrange value, a short its underrange
            # one: derived from that the parameters would be nonsense, so the server keeps
            # the ones of the last plausible reading (hold) until the sensor reads again
            result.held = (
                "implausible temperature "
                + ", ".join(f"axis {a}: {v:g} °C" for a, v in sorted(wrong.items()))
                + f" (outside {low:g} … {high:g} °C: sensor open or shorted?); holding the "
                "parameters of the last plausible reading"
            )
            log.error("t=%.3fs: %s", t, result.held)
            return result
        for axis in self.axes:
            temp_axis = float(temps[axis])  # type: ignore[arg-type]
            p = derive_parameters(
                self.table.lines(axis),
                temp_axis,
                self.reference[axis][0],
                self.coefficient_decimals,
            )
            result.parameters[axis] = p
            why = self.check(p)
            if why:
                result.refused[axis] = why
                log.error(
                    "t=%.3fs T=%.3f°C axis %d: refused, not written: %s", t, temp_axis, axis, why
                )
                continue
            for attr, name in PARAMETER_OBJECTS:
                value = getattr(p, attr)
                if not self.write_unchanged and self.written.get((axis, name)) == value:
                    continue
                rec = self._write(t, temp_axis, axis, name, value)
                result.writes.append(rec)
                if not rec.ok:
                    result.refused[axis] = (
                        f"{name} := {value} failed ({rec.error}); the rest of the axis is "
                        "not written this period"
                    )
                    log.error("t=%.3fs axis %d: %s", t, axis, result.refused[axis])
                    break
        return result

    def _temperatures(self, t: float) -> dict[int, float | None]:
        """Each axis' temperature: its own where the source has one per axis
        (`TwinSensors`), else the source's one temperature for all. A source that reads
        over the network may fail: transient failures are retried like writes; when the
        reading fails for good, no temperature this period (nothing is written, the
        adapter goes on)."""

        def read() -> dict[int, float | None]:
            if isinstance(self.source, PerAxisTemperatureSource):
                return {a: self.source.temperature_of(a, t) for a in self.axes}
            return dict.fromkeys(self.axes, self.source.temperature(t))

        temps, exc, _ = self._retrying(read, f"t={t:.3f}s: reading the temperature")
        if exc is not None:
            log.error("t=%.3fs: no temperature (%s); nothing written this period", t, exc)
            return dict.fromkeys(self.axes)
        assert temps is not None
        return temps

    def _retrying(self, fn: Callable[[], _T], what: str) -> tuple[_T | None, Exception | None, int]:
        """`fn()` with `retries` retries of a transient failure, `retry_delay`·attempt
        apart: (result, None, attempts) or (None, the last error, attempts)."""
        for attempt in range(1, self.retries + 2):
            try:
                return fn(), None, attempt
            except Exception as exc:
                if not (is_transient(exc) and attempt <= self.retries):
                    return None, exc, attempt
                delay = self.retry_delay * attempt
                log.warning("%s: %s; retry %d/%d in %.2fs", what, exc, attempt, self.retries, delay)
                self.sleep(delay)
        raise AssertionError("unreachable: the last attempt returns")

    def _write(self, t: float, temp: float, axis: int, name: str, value: Any) -> WriteRecord:
        unit = self.dictionary.by_name(name).unit
        rec = WriteRecord(t, temp, axis, name, value, self.transport, ok=False)
        started = [self.clock()]

        def write() -> None:
            started[0] = self.clock()  # the round trip of the last attempt
            self.client.write(name, axis, value)

        _, exc, rec.attempts = self._retrying(write, f"axis {axis} {name} := {value}")
        rec.rtt_s = self.clock() - started[0]
        if exc is not None:
            rec.error = str(exc)
            log.error(
                "t=%.3fs T=%.3f°C axis %d %s := %s %s via %s FAILED after %d attempt(s): %s",
                t,
                temp,
                axis,
                name,
                value,
                unit,
                self.transport,
                rec.attempts,
                exc,
            )
        else:
            rec.ok = True
            self.written[(axis, name)] = value
            log.info(
                "t=%.3fs T=%.3f°C axis %d %s := %s %s via %s rtt %.2f ms (%d attempt%s)",
                t,
                temp,
                axis,
                name,
                value,
                unit,
                self.transport,
                rec.rtt_s * 1000,
                rec.attempts,
                "" if rec.attempts == 1 else "s",
            )
        self.history.append(rec)
        if self.on_write is not None:
            self.on_write(rec)
        return rec

    # ------------------------------------------------------------------ real time

    def run(
        self,
        period: float,
        duration: float | None = None,
        speed: float = 1.0,
        stop: threading.Event | None = None,
    ) -> int:
        """Tick every `period` seconds of wall-clock time until `duration` (None: until
        `stop` is set or Ctrl-C). Source time runs `speed` times faster. Returns ticks."""
        stop = stop or threading.Event()
        start = time.monotonic()
        n = 0
        while not stop.is_set():
            elapsed = time.monotonic() - start
            if duration is not None and elapsed > duration:
                break
            self.tick(elapsed * speed)
            n += 1
            next_at = start + n * period
            stop.wait(max(0.0, next_at - time.monotonic()))
        return n


# ============================================================================ the CLI


def _range(text: str) -> tuple[float, float]:
    low, sep, high = text.partition(":")
    try:
        pair = (float(low), float(high))
    except ValueError:
        pair = (math.nan, math.nan)
    if not sep or not pair[0] < pair[1]:
        raise argparse.ArgumentTypeError(f"expected MIN:MAX with MIN < MAX, not {text!r}")
    return pair


def _reference_positions(items: Sequence[str]) -> dict[int, float]:
    out: dict[int, float] = {}
    for item in items:
        axis, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"--reference-position needs AXIS=POSITION: {item}")
        out[int(axis)] = float(value)
    return out


def _warmup(text: str) -> WarmUp:
    try:
        start, end, tau = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--warmup needs START:END:TAU (°C, °C, s), got {text!r}"
        ) from None
    return WarmUp(start, end, tau)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="geo-plc-tempcomp",
        description="PLC temperature adaptation (TF5200 manual §3.2): derive TEMPC "
        "parameters from a temperature and a reference measurement, write them live.",
    )
    p.add_argument(
        "reference",
        nargs="?",
        default=str(EXAMPLE_REFERENCE),
        help="reference-measurement CSV (default: the shipped example for the default machine)",
    )
    src = p.add_argument_group("temperature (one of)")
    g = src.add_mutually_exclusive_group()
    g.add_argument(
        "--warmup",
        type=_warmup,
        metavar="START:END:TAU",
        help="simulated warm-up from START to END °C with time constant TAU s (default 20:35:600)",
    )
    g.add_argument("--csv", metavar="FILE", help="timestamped samples: time,temperature_C")
    g.add_argument("--zenoh-key", metavar="KEY", help="Zenoh key another program publishes on")
    g.add_argument("--constant", type=float, metavar="DEG_C", help="a fixed temperature")
    g.add_argument(
        "--twin-sensor",
        action="store_true",
        help="each axis' TWIN::sensor_temperature, read over --via from the server's twin",
    )
    src.add_argument(
        "--temperature-connect",
        metavar="ENDPOINT",
        help="Zenoh endpoint for --zenoh-key (default: --connect with --via zenoh, "
        "else tcp/127.0.0.1:7447)",
    )
    src.add_argument("--speed", type=float, default=1.0, help="source time runs this much faster")
    w = p.add_argument_group("adaptation")
    w.add_argument("--period", type=float, default=1.0, help="seconds between writes (default 1)")
    w.add_argument("--duration", type=float, help="stop after this many seconds")
    w.add_argument("--once", action="store_true", help="one period at source time 0, then exit")
    w.add_argument("--axis", type=int, action="append", help="only these axes (repeatable)")
    w.add_argument(
        "--reference-position",
        action="append",
        default=[],
        metavar="AXIS=POS",
        help="reference position P [0.1 µm] of an axis (default: virtual intersection)",
    )
    w.add_argument("--tolerance", type=float, default=0.5, help="virtual intersection [0.1 µm]")
    w.add_argument("--decimals", type=int, default=4, help="coefficient decimals (default 4)")
    w.add_argument("--retries", type=int, default=3, help="retries of a transient failure")
    w.add_argument(
        "--plausible",
        type=_range,
        default=PLAUSIBLE_C,
        metavar="MIN:MAX",
        help="temperatures a sensor can read, °C (default -40:150); outside, nothing is "
        "written (the server holds the last parameters)",
    )
    w.add_argument("--activate", action="store_true", help="write TEMPC::activated TRUE first")
    w.add_argument("--log-file", metavar="FILE", help="append every write as a JSON line")
    w.add_argument(
        "--derive",
        type=float,
        nargs="+",
        metavar="DEG_C",
        help="print the parameters for these temperatures and exit (no server)",
    )
    add_transport_arguments(p)
    return p


def _source(args: argparse.Namespace, client: Any) -> tuple[TemperatureSource, Callable[[], None]]:
    if args.csv:
        return CsvTemperature(args.csv), lambda: None
    if args.zenoh_key:
        session = None
        if args.via == "zenoh":  # (its session, shared)
            from geo_server.client.zenoh_client import ZenohClient

            session = client.session if isinstance(client, ZenohClient) else None
        owned = None
        if session is None:
            import zenoh

            from geo_server.client.zenoh_client import client_config

            ep = args.temperature_connect or "tcp/127.0.0.1:7447"
            owned = session = zenoh.open(client_config([ep]))
        src = ZenohTemperature(session, args.zenoh_key)

        def close() -> None:
            src.close()
            if owned is not None:
                owned.close()

        return src, close
    if args.constant is not None:
        return ConstantTemperature(args.constant), lambda: None
    if args.twin_sensor:
        return TwinSensors(client, args.axis or ()), lambda: None
    return args.warmup or WarmUp(), lambda: None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    try:
        table = load_reference(args.reference)
        refs = _reference_positions(args.reference_position)
    except (ReferenceTableError, argparse.ArgumentTypeError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.derive:
        adapter = TemperatureAdapter(
            None, table, ConstantTemperature(0.0), axes=args.axis, reference_positions=refs,
            tolerance=args.tolerance, coefficient_decimals=args.decimals, transport="none",
        )  # fmt: skip
        w = csv.writer(sys.stdout, lineterminator="\n")
        w.writerow(["temperature_C", "axis", "position_0", "offset_0", "coefficient", "ok"])
        for temp in args.derive:
            for axis, prm in adapter.parameters(temp).items():
                why = adapter.check(prm)
                w.writerow([temp, axis, prm.position_0, prm.offset_0, prm.coefficient, why or "ok"])
        return 0
    try:
        client = client_from_args(args)
    except (OSError, AdsError, RuntimeError) as exc:
        print(f"error: cannot connect over {args.via}: {exc}", file=sys.stderr)
        return 2
    log_file = open(args.log_file, "a", encoding="utf-8") if args.log_file else None  # noqa: SIM115
    close_source: Callable[[], None] = lambda: None  # noqa: E731
    try:
        source, close_source = _source(args, client)

        def on_write(rec: WriteRecord) -> None:
            if log_file is not None:
                log_file.write(json.dumps(rec.as_dict()) + "\n")
                log_file.flush()

        adapter = TemperatureAdapter(
            client,
            table,
            source,
            axes=args.axis,
            reference_positions=refs,
            tolerance=args.tolerance,
            coefficient_decimals=args.decimals,
            retries=args.retries,
            plausible=args.plausible,
            on_write=on_write,
        )
        if args.activate:
            for axis in adapter.axes:
                client.write("TEMPC::activated", axis, True)
        if args.once:
            result = adapter.tick(0.0)
            return 1 if result.refused or any(not r.ok for r in result.writes) else 0
        with contextlib.suppress(KeyboardInterrupt):
            adapter.run(args.period, args.duration, args.speed)
        failed = sum(1 for r in adapter.history if not r.ok)
        log.info("%d writes, %d failed", len(adapter.history), failed)
        return 1 if failed else 0
    except (ReferenceTableError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        close_source()
        client.close()
        if log_file is not None:
            log_file.close()


if __name__ == "__main__":
    raise SystemExit(main())
