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

Other interpolation modes (SCATTER, AUTO, PATH, PATH_XY) are refused with a clear error
(docs/volumetric.md §6): only GRID is emulated.
"""

from __future__ import annotations

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

    @property
    def constant(self) -> float:
        return float(self.values) if not self.arguments else float("nan")


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


def build_tables(
    blocks: Sequence[Block], splicing: bool = False
) -> tuple[dict[str, ParamTable], int]:
    """Every parameter's table (GRID) and the number of records, the rows of the blocks
    plus one per 360° record splicing added (`vol_comp[i].max_records` bounds it: 004
    p.12, and p.35 asks to leave room for the spliced records)."""
    tables: dict[str, ParamTable] = {}
    added = 0
    for name, (args, records) in _parameter_records(blocks).items():
        t = tables[name] = _grid_table(name, args, records, splicing)
        added += (
            t.spliced and float(t.grid[0][-1]) == 360.0 and 360.0 not in {r[0][0] for r in records}
        )
    return tables, sum(len(b.rows) for b in blocks) + added


def evaluate(table: ParamTable, point: dict[str, float]) -> float:
    """The parameter at `point` (argument -> value), multi-linear, edges held: the plain
    reference (`geo_server.volcomp.reference`); the kernel has its own vectorised form."""
    if not table.arguments:
        return float(table.values)
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


__all__ = ["ParamTable", "TableError", "build_tables", "evaluate"]
