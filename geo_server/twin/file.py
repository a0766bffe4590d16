"""The twin file: TOML beside the start-up list (`twin.toml`), validated with file and line.

```toml
[twin]
reference_temperature = 20.0          # °C: the geometric errors hold at this temperature
time_scale = 1.0                      # simulated s per real s (thermal model, sensors)
seed = 1                              # sensor noise and positioning scatter
ambient = [[0, 20.0], [7200, 22.0]]   # (s, °C): linear, held outside

[[node]]                              # a first-order thermal mass
name = "x_screw"
tau = 1800.0                          # s
initial = 20.0                        # °C
motion_axis = "X"                     # heated by the motion of X ...
motion_gain = 8.0                     # ... by 8 K at 1 m/s, in steady state
spindle_gain = 0.0                    # K while TWIN::spindle_on

[[sensor]]
name = "x_screw"
node = "x_screw"
axis = "X"                            # shown as TWIN::sensor_temperature of X
noise = 0.02                          # °C, one standard deviation
resolution = 0.01                     # °C
period = 0.1                          # s

[axis.X]
linear = { offset = 4.0, slope = 4000.0, reference = 0.01 }     # µm, µm/m, mm
pitch = { positions = [-500.0, 0.0, 500.0], errors = [-3.0, 0.0, 2.5] }
pitch_negative = { positions = [...], errors = [...] }          # bilateral axes
periodic = { amplitude = 0.5, period = 10.0 }                   # µm, mm
reversal = 100.0                      # µm lost when moving against reference_direction
reference_direction = 1
squareness = { Y = 20.0 }             # µrad
expansion = { node = "x_screw", coefficient = 50.0, reference = 0.01 }   # µm/m/K, mm
friction = { coulomb = 100.0, viscous = 20.0 }
scatter = 0.3                         # µm, one standard deviation per approach

[[axis.Z.straightness]]               # Z's error over the position of X
over = "X"
positions = [-500.0, 500.0]
errors = [0.0, -12.0]

[[axis.Z.grid]]                       # Z's error over X and Y
over = ["X", "Y"]
start = [-500.0, -500.0]
step = [50.0, 50.0]
errors = [[0.0, 1.0], [2.0, 3.0]]     # errors[j][i]: j along the second axis
```

Units (docs/twin.md): positions mm (rotary °), errors µm (rotary 0.001°). Every problem
is a `TwinFileError` naming the file and the line, and nothing of a file with an error
is used (a reload with a bad twin file is rejected as a whole).
"""

from __future__ import annotations

import difflib
import itertools
import math
import re
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from geo_server.errors import GeoError
from geo_server.safefile import FileRefused, read_regular
from geo_server.twin.model import (
    RIGID_COMPONENTS,
    RIGID_SQUARENESS,
    AxisTwin,
    Curve,
    Expansion,
    Grid,
    RigidBody,
    Sensor,
    Straightness,
    ThermalNode,
    TwinConfig,
)

#: The twin file's name beside the start-up list.
TWIN_FILE = "twin.toml"
#: Largest twin file read (tables of a few thousand points are a few hundred KiB).
MAX_TWIN_BYTES = 16 * 1024 * 1024


class TwinFileError(GeoError):
    """The twin file cannot be used: `path:line: message`."""

    def __init__(self, path: Path | str, line: int, message: str) -> None:
        self.path, self.line, self.message = str(path), line, message
        super().__init__(f"{self.path}:{line}: {message}" if line else f"{self.path}: {message}")


class _Lines:
    """Where a table, an array-of-tables entry or a key is written in the file."""

    _HEADER = re.compile(r"^\s*(\[\[?)\s*([^\]]+?)\s*\]\]?\s*(?:#.*)?$")

    def __init__(self, text: str) -> None:
        self.sections: list[tuple[str, int, int]] = [("", 0, 1)]  # (table, index, line)
        counts: dict[str, int] = {}
        self.lines = text.splitlines()
        for number, line in enumerate(self.lines, 1):
            m = self._HEADER.match(line)
            if not m:
                continue
            name = m.group(2).replace(" ", "")
            if m.group(1) == "[[":
                counts[name] = counts.get(name, -1) + 1
                self.sections.append((name, counts[name], number))
            else:
                self.sections.append((name, 0, number))

    def table(self, name: str, index: int = 0) -> int:
        for table, i, line in self.sections:
            if table == name and i == index:
                return line
        return 0

    def key(self, table: str, key: str, index: int = 0) -> int:
        """Line of `key = …` inside `[table]` (or `table.key = …` / an inline table)."""
        start = self.table(table, index) if table else 1
        if table and not start:  # a dotted key in the parent table: `axis.X.reversal = …`
            return self.key("", f"{table}.{key}")
        end = min((ln for _t, _i, ln in self.sections if ln > start), default=len(self.lines) + 1)
        pattern = re.compile(rf"^\s*{re.escape(key)}\s*=")
        for number in range(start, end):
            if pattern.match(self.lines[number - 1]):
                return number
        return start


def load_twin(path: Path | str, axis_names: Sequence[str] = ()) -> TwinConfig:
    """Read and validate a twin file; `axis_names` (if given) are the machine's axes,
    which the file's axes, motion axes and `over` axes must name."""
    path = Path(path)
    try:  # read on every reload: never blocking on a FIFO, never past the bound
        data = read_regular(path, MAX_TWIN_BYTES)
    except FileRefused as exc:
        raise TwinFileError(path, 0, exc.reason) from None
    except OSError as exc:
        raise TwinFileError(path, 0, f"cannot read the twin file: {exc.strerror or exc}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise TwinFileError(path, 0, f"not UTF-8 text (byte {exc.start})") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        line = int(m.group(1)) if (m := re.search(r"line (\d+)", str(exc))) else 0
        raise TwinFileError(path, line, f"not valid TOML: {exc}") from None
    return _Parser(path, _Lines(text), {n.upper() for n in axis_names}).config(raw)


class _Parser:
    def __init__(self, path: Path, where: _Lines, axes: set[str]) -> None:
        self.path, self.where, self.axes = path, where, axes

    # ------------------------------------------------------------------ errors

    def fail(self, line: int, message: str) -> TwinFileError:
        return TwinFileError(self.path, line, message)

    def unknown(
        self, got: dict[str, Any], known: Sequence[str], table: str, index: int = 0
    ) -> None:
        for key in got:
            if key not in known:
                near = difflib.get_close_matches(key, known, n=1)
                hint = f"; did you mean {near[0]!r}?" if near else f" (known: {', '.join(known)})"
                raise self.fail(self.where.key(table, key, index), f"unknown key {key!r}{hint}")

    def number(
        self, d: dict[str, Any], key: str, table: str, default: float | None = None, *,
        index: int = 0, positive: bool = False, minimum: float | None = None,
    ) -> float:  # fmt: skip
        if key not in d:
            if default is None:
                raise self.fail(self.where.table(table, index), f"[{table}] needs {key!r}")
            return default
        v = d[key]
        line = self.where.key(table, key, index)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self.fail(line, f"{key} must be a number, not {v!r}")
        if positive and v <= 0:
            raise self.fail(line, f"{key} must be greater than 0, not {v}")
        if minimum is not None and v < minimum:
            raise self.fail(line, f"{key} must be at least {minimum:g}, not {v}")
        return float(v)

    def axis(self, name: Any, line: int) -> str:
        if not isinstance(name, str) or not name:
            raise self.fail(line, f"an axis name is needed, not {name!r}")
        if self.axes and name.upper() not in self.axes:
            raise self.fail(
                line, f"no axis {name!r} on this machine (axes: {', '.join(sorted(self.axes))})"
            )
        return name.upper()

    def numbers(self, v: Any, what: str, line: int) -> tuple[float, ...]:
        if not isinstance(v, list) or not all(
            isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in v
        ):
            raise self.fail(line, f"{what} must be a list of numbers")
        return tuple(float(x) for x in v)

    def curve(self, d: Any, what: str, line: int) -> Curve:
        if not isinstance(d, dict) or set(d) - {"positions", "errors"} or len(d) != 2:
            raise self.fail(line, f"{what} needs `positions` and `errors` (and nothing else)")
        pos = self.numbers(d["positions"], f"{what}.positions", line)
        err = self.numbers(d["errors"], f"{what}.errors", line)
        if len(pos) != len(err) or not pos:
            raise self.fail(line, f"{what}: {len(pos)} positions but {len(err)} errors")
        if any(b <= a for a, b in itertools.pairwise(pos)):
            raise self.fail(line, f"{what}.positions must ascend")
        return Curve(pos, err)

    # ------------------------------------------------------------------ the file

    def config(self, raw: dict[str, Any]) -> TwinConfig:
        self.unknown(raw, ("twin", "node", "sensor", "axis", "rigid_body"), "")
        top = self.table(raw, "twin")
        self.unknown(top, ("reference_temperature", "time_scale", "seed", "ambient"), "twin")
        nodes = self.nodes(raw.get("node", []))
        names = {n.name for n in nodes}
        sensors = self.sensors(raw.get("sensor", []), names)
        axes = {}
        for name, body in self.table(raw, "axis").items():
            a = self.axis_twin(name, body, names)
            axes[a.name] = a
        seed = top.get("seed", 1)
        if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
            raise self.fail(
                self.where.key("twin", "seed"), f"seed must be an integer ≥ 0, not {seed!r}"
            )
        return TwinConfig(
            path=str(self.path),
            reference_temperature=self.number(top, "reference_temperature", "twin", 20.0),
            time_scale=self.number(top, "time_scale", "twin", 1.0, positive=True),
            seed=seed,
            ambient=self.ambient(top.get("ambient", [[0.0, 20.0]])),
            nodes=tuple(nodes),
            sensors=tuple(sensors),
            axes=axes,
            rigid_body=self.rigid_body(raw.get("rigid_body")),
        )

    def rigid_body(self, d: Any) -> RigidBody | None:
        """`[rigid_body]`: chain, workpiece_axes, tool, squareness = { C0Y = µrad … },
        and `[rigid_body.errors]` with one curve per component error (EXX …)."""
        if d is None:
            return None
        table = "rigid_body"
        head = self.where.table(table)
        if not isinstance(d, dict):
            raise self.fail(head, "[rigid_body] must be a table")
        self.unknown(d, ("chain", "workpiece_axes", "tool", "squareness", "errors"), table)
        chain = d.get("chain", "YXZ")
        if not isinstance(chain, str) or sorted(chain.upper()) != ["X", "Y", "Z"]:
            raise self.fail(
                self.where.key(table, "chain"),
                f"chain must order X, Y and Z (workpiece → tool), not {chain!r}",
            )
        for a in "XYZ":
            self.axis(a, self.where.key(table, "chain"))
        wp = d.get("workpiece_axes", 0)
        if not isinstance(wp, int) or isinstance(wp, bool) or not 0 <= wp <= 3:
            raise self.fail(self.where.key(table, "workpiece_axes"), "workpiece_axes is 0 … 3")
        tool = self.numbers(d.get("tool", [0.0, 0.0, 0.0]), "tool", self.where.key(table, "tool"))
        if len(tool) != 3:
            raise self.fail(self.where.key(table, "tool"), "tool is [x, y, z] in mm")
        square = d.get("squareness", {})
        if not isinstance(square, dict):
            raise self.fail(self.where.key(table, "squareness"), "squareness = { C0Y = µrad, … }")
        self.unknown_inline(square, RIGID_SQUARENESS, table, "squareness")
        errors = d.get("errors", {})
        if not isinstance(errors, dict):
            raise self.fail(head, "[rigid_body.errors] must be a table of curves")
        self.unknown(errors, RIGID_COMPONENTS, f"{table}.errors")
        return RigidBody(
            chain=chain.upper(),
            workpiece_axes=wp,
            tool=(tool[0], tool[1], tool[2]),
            squareness=tuple(
                (k, self.inline_number(square, k, table, "squareness")) for k in square
            ),
            components=tuple(
                (k, self.curve(v, k, self.where.key(f"{table}.errors", k)))
                for k, v in errors.items()
            ),
        )

    def table(self, raw: dict[str, Any], key: str) -> dict[str, Any]:
        v = raw.get(key, {})
        if not isinstance(v, dict):
            raise self.fail(self.where.key("", key), f"{key} must be a table ([{key}])")
        return v

    def ambient(self, v: Any) -> tuple[tuple[float, float], ...]:
        line = self.where.key("twin", "ambient")
        if (
            not isinstance(v, list)
            or not v
            or not all(isinstance(p, list) and len(p) == 2 for p in v)
        ):
            raise self.fail(line, "ambient must be a list of [time_s, temperature_C] pairs")
        points = [self.numbers(p, "ambient", line) for p in v]
        if any(b[0] <= a[0] for a, b in itertools.pairwise(points)):
            raise self.fail(line, "ambient: the times must ascend")
        return tuple((p[0], p[1]) for p in points)

    def entries(self, v: Any, table: str) -> list[dict[str, Any]]:
        if not isinstance(v, list) or not all(isinstance(e, dict) for e in v):
            raise self.fail(self.where.table(table), f"{table} entries must be [[{table}]] tables")
        return v

    def nodes(self, v: Any) -> list[ThermalNode]:
        out: list[ThermalNode] = []
        keys = ("name", "tau", "initial", "motion_axis", "motion_gain", "spindle_gain")
        for i, d in enumerate(self.entries(v, "node")):
            self.unknown(d, keys, "node", i)
            name = d.get("name")
            if not isinstance(name, str) or not name or name in {n.name for n in out}:
                raise self.fail(
                    self.where.table("node", i), f"node needs a unique name, not {name!r}"
                )
            motion = d.get("motion_axis", "")
            out.append(
                ThermalNode(
                    name=name,
                    tau=self.number(d, "tau", "node", index=i, positive=True),
                    initial=self.number(d, "initial", "node", 20.0, index=i),
                    motion_axis=self.axis(motion, self.where.key("node", "motion_axis", i))
                    if motion
                    else "",
                    motion_gain=self.number(d, "motion_gain", "node", 0.0, index=i),
                    spindle_gain=self.number(d, "spindle_gain", "node", 0.0, index=i),
                )
            )
        return out

    def sensors(self, v: Any, nodes: set[str]) -> list[Sensor]:
        out: list[Sensor] = []
        keys = ("name", "node", "axis", "noise", "resolution", "period")
        for i, d in enumerate(self.entries(v, "sensor")):
            self.unknown(d, keys, "sensor", i)
            node = d.get("node")
            if node not in nodes:
                raise self.fail(
                    self.where.key("sensor", "node", i), f"sensor on unknown node {node!r}"
                )
            axis = d.get("axis", "")
            out.append(
                Sensor(
                    name=str(d.get("name", node)),
                    node=str(node),
                    axis=self.axis(axis, self.where.key("sensor", "axis", i)) if axis else "",
                    noise=self.number(d, "noise", "sensor", 0.0, index=i, minimum=0.0),
                    resolution=self.number(d, "resolution", "sensor", 0.01, index=i, minimum=0.0),
                    period=self.number(d, "period", "sensor", 0.1, index=i, positive=True),
                )
            )
        return out

    _AXIS_KEYS = (
        "linear", "pitch", "pitch_negative", "periodic", "reversal", "reference_direction",
        "squareness", "expansion", "friction", "scatter", "straightness", "grid",
    )  # fmt: skip

    def axis_twin(self, name: str, d: Any, nodes: set[str]) -> AxisTwin:
        table = f"axis.{name}"
        head = self.where.table(table) or self.where.key("axis", name)
        axis = self.axis(name, head)
        if not isinstance(d, dict):
            raise self.fail(head, f"[{table}] must be a table")
        self.unknown(d, self._AXIS_KEYS, table)

        def sub(key: str, keys: Sequence[str]) -> dict[str, Any]:
            v = d.get(key, {})
            if not isinstance(v, dict):
                raise self.fail(self.where.key(table, key), f"{key} must be a table {{ … }}")
            self.unknown_inline(v, keys, table, key)
            return v

        linear = sub("linear", ("offset", "slope", "reference"))
        periodic = sub("periodic", ("amplitude", "period"))
        friction = sub("friction", ("coulomb", "viscous"))
        expansion = sub("expansion", ("node", "coefficient", "reference"))
        square = sub("squareness", ())
        line = self.where.key(table, "reference_direction")
        direction = d.get("reference_direction", 1)
        if direction not in (1, -1) or isinstance(direction, bool):
            raise self.fail(line, f"reference_direction must be 1 or -1, not {direction!r}")
        exp = None
        if expansion:
            if expansion.get("node") not in nodes:
                raise self.fail(
                    self.where.key(table, "expansion"),
                    f"expansion on unknown node {expansion.get('node')!r}",
                )
            exp = Expansion(
                str(expansion["node"]),
                self.inline_number(expansion, "coefficient", table, "expansion"),
                self.inline_number(expansion, "reference", table, "expansion", 0.0),
            )
        return AxisTwin(
            name=axis,
            linear_offset=self.inline_number(linear, "offset", table, "linear", 0.0),
            linear_slope=self.inline_number(linear, "slope", table, "linear", 0.0),
            linear_reference=self.inline_number(linear, "reference", table, "linear", 0.0),
            pitch=self.optional_curve(d, "pitch", table),
            pitch_negative=self.optional_curve(d, "pitch_negative", table),
            periodic_amplitude=self.inline_number(periodic, "amplitude", table, "periodic", 0.0),
            periodic_period=self.inline_number(periodic, "period", table, "periodic", 1.0),
            reversal=self.number(d, "reversal", table, 0.0, minimum=0.0),
            reference_direction=int(direction),
            straightness=self.straightness(d.get("straightness", []), table),
            grids=self.grids(d.get("grid", []), table),
            squareness=tuple(
                (
                    self.axis(k, self.where.key(table, "squareness")),
                    self.inline_number(square, k, table, "squareness"),
                )
                for k in square
            ),
            expansion=exp,
            friction_coulomb=self.inline_number(friction, "coulomb", table, "friction", 0.0),
            friction_viscous=self.inline_number(friction, "viscous", table, "friction", 0.0),
            scatter=self.number(d, "scatter", table, 0.0, minimum=0.0),
        )

    def optional_curve(self, d: dict[str, Any], key: str, table: str) -> Curve | None:
        return self.curve(d[key], key, self.where.key(table, key)) if key in d else None

    def unknown_inline(self, v: dict[str, Any], keys: Sequence[str], table: str, key: str) -> None:
        if not keys:
            return
        for k in v:
            if k not in keys:
                near = difflib.get_close_matches(k, keys, n=1)
                hint = f"; did you mean {near[0]!r}?" if near else f" (known: {', '.join(keys)})"
                raise self.fail(self.where.key(table, key), f"{key}: unknown key {k!r}{hint}")

    def inline_number(
        self, v: dict[str, Any], key: str, table: str, parent: str, default: float | None = None
    ) -> float:
        if key not in v:
            if default is None:
                raise self.fail(self.where.key(table, parent), f"{parent} needs {key!r}")
            return default
        x = v[key]
        if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
            raise self.fail(
                self.where.key(table, parent), f"{parent}.{key} must be a number, not {x!r}"
            )
        if parent == "periodic" and key == "period" and x <= 0:
            raise self.fail(self.where.key(table, parent), "periodic.period must be greater than 0")
        return float(x)

    def straightness(self, v: Any, table: str) -> tuple[Straightness, ...]:
        out = []
        name = f"{table}.straightness"
        for i, d in enumerate(self.entries(v, name)):
            line = self.where.table(name, i)
            self.unknown(d, ("over", "positions", "errors"), name, i)
            over = self.axis(d.get("over"), line)
            body = {"positions": d.get("positions"), "errors": d.get("errors")}
            out.append(Straightness(over, self.curve(body, "straightness", line)))
        return tuple(out)

    def grids(self, v: Any, table: str) -> tuple[Grid, ...]:
        out = []
        name = f"{table}.grid"
        for i, d in enumerate(self.entries(v, name)):
            line = self.where.table(name, i)
            self.unknown(d, ("over", "start", "step", "errors"), name, i)
            over = d.get("over")
            if not isinstance(over, list) or len(over) != 2:
                raise self.fail(line, 'grid.over must name two axes, e.g. ["X", "Y"]')
            start = self.numbers(d.get("start"), "grid.start", line)
            step = self.numbers(d.get("step"), "grid.step", line)
            rows = d.get("errors")
            if len(start) != 2 or len(step) != 2 or min(step) <= 0:
                raise self.fail(line, "grid.start and grid.step need two numbers (steps > 0)")
            if not isinstance(rows, list) or not rows:
                raise self.fail(line, "grid.errors must be a list of rows")
            errors = tuple(self.numbers(r, "grid.errors", line) for r in rows)
            if len({len(r) for r in errors}) != 1 or len(errors[0]) < 1:
                raise self.fail(line, "grid.errors: every row needs the same number of values")
            out.append(
                Grid(
                    over1=self.axis(over[0], line),
                    over2=self.axis(over[1], line),
                    start1=start[0],
                    step1=step[0],
                    start2=start[1],
                    step2=step[1],
                    errors=errors,
                )
            )
        return tuple(out)


def twin_path(startup: Path | str) -> Path:
    """Where the twin file of a machine is: `twin.toml` beside its start-up list."""
    return Path(startup).parent / TWIN_FILE


def find_twin(startup: Path | str, axis_names: Sequence[str]) -> TwinConfig | None:
    """The machine's twin, or None when it has no twin file."""
    path = twin_path(startup)
    return load_twin(path, axis_names) if path.exists() else None


__all__ = ["MAX_TWIN_BYTES", "TWIN_FILE", "TwinFileError", "find_twin", "load_twin", "twin_path"]
