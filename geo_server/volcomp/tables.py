"""Error parameters as tables over their arguments (004 §6.4, p.34-35).

A correction file gives records: argument values (X, Y, Z in mm; A, B, C in degrees,
004 p.31) and parameter values (mm or rad). `build_tables` turns the blocks of every file
of one compensation into one `ParamTable` per parameter:

- a parameter without arguments is a constant (position errors, ISG parameters);
- records of one parameter over the same arguments are merged, also across files and
  blocks (a second block for Z = 100 adds to the first for Z = 0, 004 p.32);
- GRID (the default, 004 p.34) needs the records on a full rectilinear grid: every
  combination of the argument values once. Multi-linear interpolation inside, the edge
  values held outside the grid;
- splicing (004 p.35, `enable_splicing 1`): a 1-D table over a rotary argument that has
  a 0° record but none at 360° gets one with the 0° values, so the table is continuous
  over the modulo passage; its argument is then taken modulo 360°.

The other modes (SCATTER, AUTO, PATH, PATH_XY) keep the records as they are; their laws
are in docs/volumetric.md §6 (`evaluate` here, plainly; compiled in `geo_server.volcomp.law`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from geo_server.volcomp.names import ROTARY
from geo_server.volcomp.paramfile import Block


class TableError(ValueError):
    """A parameter's records do not form a table: file, line and what is wrong."""

    def __init__(self, file: str, line: int, message: str) -> None:
        self.file, self.line, self.message = file, line, message
        where = f"{file}:{line}: " if file else ""
        super().__init__(f"{where}{message}")


@dataclass(frozen=True)
class ParamTable:
    """One parameter over its arguments on a rectilinear grid.

    `grid[i]` holds the ascending values of argument `arguments[i]`; `values` has the
    shape `tuple(len(g) for g in grid)`. No arguments: `values` is a 0-d array."""

    name: str
    arguments: tuple[str, ...]
    grid: tuple[np.ndarray, ...]
    values: np.ndarray
    spliced: bool = False  # rotary argument taken modulo 360° (splicing)
    file: str = ""
    line: int = 0
    #: "GRID", or "SCATTER", "PATH", "PATH_XY": then `points` [m, k] holds the records'
    #: arguments in file order and `point_values` [m] their values (docs/volumetric.md §6)
    mode: str = "GRID"
    points: np.ndarray | None = None
    point_values: np.ndarray | None = None


def _parameter_records(
    blocks: Iterable[Block],
) -> dict[str, tuple[tuple[str, ...], list[tuple[tuple[float, ...], float, str, int]]]]:
    """name -> (arguments, [(argument values, value, file, line of the header)])."""
    out: dict[str, tuple[tuple[str, ...], list[tuple[tuple[float, ...], float, str, int]]]] = {}
    for block in blocks:
        k = len(block.arguments)
        for j, name in enumerate(block.parameters):
            args, records = out.setdefault(name, (block.arguments, []))
            if args != block.arguments:
                first = records[0] if records else ("", 0.0, "", 0)
                raise TableError(
                    block.file,
                    block.line,
                    f"{name} is given over ({', '.join(block.arguments) or 'nothing'}) here "
                    f"but over ({', '.join(args) or 'nothing'}) in {first[2]}:{first[3]}",
                )
            for row in block.rows:
                records.append((tuple(row[:k]), row[k + j], block.file, block.line))
    return out


def _grid_table(
    name: str,
    args: tuple[str, ...],
    records: Sequence[tuple[tuple[float, ...], float, str, int]],
    splicing: bool,
) -> ParamTable:
    file, line = records[0][2], records[0][3]
    if not args:
        if len(records) > 1:
            raise TableError(
                records[1][2], records[1][3], f"{name} has no argument but {len(records)} values"
            )
        return ParamTable(name, (), (), np.array(records[0][1]), file=file, line=line)
    grid = tuple(np.array(sorted({r[0][i] for r in records})) for i in range(len(args)))
    values = np.full(tuple(len(g) for g in grid), np.nan)
    for point, value, f, ln in records:
        at = tuple(int(np.searchsorted(g, v)) for g, v in zip(grid, point, strict=True))
        if not np.isnan(values[at]):
            where = ", ".join(f"{a}={v:g}" for a, v in zip(args, point, strict=True))
            raise TableError(f, ln, f"{name}: the record at {where} is given twice")
        values[at] = value
    if np.isnan(values).any():
        at = tuple(int(i[0]) for i in np.nonzero(np.isnan(values)))
        where = ", ".join(f"{a}={g[i]:g}" for a, g, i in zip(args, grid, at, strict=True))
        raise TableError(
            file,
            line,
            f"{name}: the records are not on a grid (none at {where}); interpolation GRID "
            "needs every combination of the argument values (004 p.34)",
        )
    spliced = False
    if splicing and len(args) == 1 and args[0] in ROTARY:
        g = grid[0]
        if g[0] == 0.0 and g[-1] < 360.0:
            grid = (np.append(g, 360.0),)
            values = np.append(values, values[0])
            spliced = True
        elif g[0] == 0.0 and g[-1] == 360.0:
            spliced = True
    return ParamTable(name, args, grid, values, spliced, file, line)


def _point_table(
    name: str,
    args: tuple[str, ...],
    records: Sequence[tuple[tuple[float, ...], float, str, int]],
    mode: str,
) -> ParamTable:
    """SCATTER, PATH or PATH_XY: the records as they are (004 p.34)."""
    file, line = records[0][2], records[0][3]
    if mode == "PATH_XY" and not {"X", "Y"} <= set(args):
        raise TableError(
            file,
            line,
            f"{name}: PATH_XY needs X and Y among the arguments, not ({', '.join(args)})",
        )
    pts = np.array([r[0] for r in records], dtype=float)
    if mode == "SCATTER" and len({tuple(p) for p in pts.tolist()}) != len(pts):
        raise TableError(file, line, f"{name}: a point given twice (SCATTER)")
    return ParamTable(
        name,
        args,
        (),
        np.array(np.nan),
        file=file,
        line=line,
        mode=mode,
        points=pts,
        point_values=np.array([r[1] for r in records], dtype=float),
    )


def build_tables(
    blocks: Sequence[Block], splicing: bool = False, interpolation: str = "GRID"
) -> tuple[dict[str, ParamTable], int]:
    """Every parameter's table (GRID) and the number of records, the rows of the blocks
    plus one per 360° record splicing added (`vol_comp[i].max_records` bounds it: 004
    p.12, and p.35 asks to leave room for the spliced records)."""
    tables: dict[str, ParamTable] = {}
    added = 0
    for name, (args, records) in _parameter_records(blocks).items():
        if not args or interpolation == "GRID":
            t = tables[name] = _grid_table(name, args, records, splicing)
        elif interpolation == "AUTO":  # a grid if the records form one (004 p.34)
            try:
                t = tables[name] = _grid_table(name, args, records, splicing)
            except TableError as exc:
                if "not on a grid" not in exc.message:
                    raise
                t = tables[name] = _point_table(name, args, records, "SCATTER")
        else:
            t = tables[name] = _point_table(name, args, records, interpolation)
        added += (
            t.spliced and float(t.grid[0][-1]) == 360.0 and 360.0 not in {r[0][0] for r in records}
        )
    return tables, sum(len(b.rows) for b in blocks) + added


def evaluate(table: ParamTable, point: dict[str, float]) -> float:
    """The parameter at `point` (argument -> value), multi-linear, edges held: the plain
    reference (`geo_server.volcomp.reference`); the cycle's is compiled (`volcomp.law`)."""
    if not table.arguments:
        return float(table.values)
    if table.mode == "SCATTER":
        return _scatter(table, point)
    if table.mode in ("PATH", "PATH_XY"):
        return _path(table, point)
    corners: list[tuple[tuple[int, ...], float]] = [((), 1.0)]
    for arg, g in zip(table.arguments, table.grid, strict=True):
        v = point.get(arg, 0.0)
        if table.spliced:
            v %= 360.0
        v = min(max(v, float(g[0])), float(g[-1]))
        if len(g) == 1:
            corners = [((*c, 0), w) for c, w in corners]
            continue
        i = min(int(np.searchsorted(g, v, side="right")) - 1, len(g) - 2)
        f = (v - float(g[i])) / (float(g[i + 1]) - float(g[i]))
        corners = [((*c, i), w * (1 - f)) for c, w in corners] + [
            ((*c, i + 1), w * f) for c, w in corners
        ]
    return sum(w * float(table.values[c]) for c, w in corners)


def _scatter(table: ParamTable, point: dict[str, float]) -> float:
    """SCATTER (004 p.34: "non-linear interpolation, any distribution"): inverse
    distance weighting, w = 1/d² in the space of the arguments (mm, °) — exact at every
    record, smooth between, bounded by the records' values."""
    assert table.points is not None and table.point_values is not None
    x = [point.get(a, 0.0) for a in table.arguments]
    num = den = 0.0
    for p, v in zip(table.points.tolist(), table.point_values.tolist(), strict=True):
        d2 = sum((pi - xi) ** 2 for pi, xi in zip(p, x, strict=True))
        if d2 == 0.0:
            return float(v)
        num += v / d2
        den += 1.0 / d2
    return num / den


def path_columns(table: ParamTable) -> list[int]:
    """The argument columns a PATH measures distance in: all, or X and Y (PATH_XY)."""
    if table.mode == "PATH_XY":
        return [table.arguments.index("X"), table.arguments.index("Y")]
    return list(range(len(table.arguments)))


def _path(table: ParamTable, point: dict[str, float]) -> float:
    """PATH / PATH_XY (004 p.34: "specified at the corner points of a polygon.
    Interpolation takes place in linear sections along the polygon"): the records in
    file order are the corners; the value is the one at the point of the polygon nearest
    to `point` (in the XY plane for PATH_XY), linear along its section; the first
    section wins a tie."""
    assert table.points is not None and table.point_values is not None
    cols = path_columns(table)
    x = [point.get(table.arguments[c], 0.0) for c in cols]
    pts = [[p[c] for c in cols] for p in table.points.tolist()]
    vals = table.point_values.tolist()
    if len(pts) == 1:
        return float(vals[0])
    best, value = math.inf, 0.0
    for i in range(len(pts) - 1):
        a, b = pts[i], pts[i + 1]
        ab = [bi - ai for ai, bi in zip(a, b, strict=True)]
        ll = sum(c * c for c in ab)
        t = (
            0.0
            if ll == 0.0
            else sum((xi - ai) * c for xi, ai, c in zip(x, a, ab, strict=True)) / ll
        )
        t = min(max(t, 0.0), 1.0)
        d2 = sum((ai + t * c - xi) ** 2 for ai, c, xi in zip(a, ab, x, strict=True))
        if d2 < best:
            best, value = d2, vals[i] + t * (vals[i + 1] - vals[i])
    return value


__all__ = ["ParamTable", "TableError", "build_tables", "evaluate", "path_columns"]
