"""Measuring the twin's rigid-body errors and writing the volumetric correction files.

The loop of docs/twin.md §2.1 and docs/volumetric.md §8: the twin's machine has the 21
rigid-body errors of a three-axis machine (`RigidBody`); a measurement gives each
component error at grid points along its axis and the squareness errors (what a laser
interferometer with linear, straightness and angular optics, or a tracker's
multilateration, delivers per ISO 230-1 — here without measurement uncertainty); the
result is written as an ISG CSV correction file (004 §6.3.2) and a VOLC list (004 §3.1),
which the CNC loads (`#VOLCOMP [ID0 UPDATE]`, `cnc_interpr_vol_comp_file_w`). Between
the grid points the compensation interpolates linearly, so what is left is the
*interpolation floor*: the twin's curves minus their chords.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from geo_server.twin.model import RigidBody
from geo_server.volcomp.names import is_angle
from geo_server.volcomp.paramfile import Block, write_isg_csv
from geo_server.volcomp.tables import ParamTable


def rigid_tables(rb: RigidBody) -> dict[str, ParamTable]:
    """The twin's rigid-body errors as the volumetric model's tables (004 p.30-31 units:
    µm → mm, µrad → rad for the angles, `names.is_angle`), with its tool point as P0."""
    tables: dict[str, ParamTable] = {}
    for name, c in rb.components:
        scale = _scale(name)
        tables[name] = ParamTable(
            name, (name[2],), (np.array(c.positions),), np.array(c.errors) * scale
        )
    for name, value in rb.squareness:
        tables[name] = ParamTable(name, (), (), np.array(value * _scale(name)))
    for d, v in zip("XYZ", rb.tool, strict=True):
        tables[f"P0{d}"] = ParamTable(f"P0{d}", (), (), np.array(float(v)))
    return tables


def _scale(name: str) -> float:
    """Twin units (µm, µrad) to the model's (mm, rad)."""
    return 1e-6 if is_angle(name) else 1e-3


def measure_rigid_body(
    rb: RigidBody, travel: Mapping[str, tuple[float, float]], step: float
) -> list[Block]:
    """The component errors of X, Y, Z every `step` mm over `travel` (mm, both ends
    included) in mm and rad, one block per axis over its own position, the squareness
    errors and the tool point (P0X … P0Z) as constants (004 p.30 names)."""
    tables = rigid_tables(rb)
    blocks = []
    for axis in "XYZ":
        lo, hi = travel[axis]
        grid = np.linspace(lo, hi, max(2, round((hi - lo) / step) + 1))
        names = [f"E{d}{axis}" for d in "XYZABC" if f"E{d}{axis}" in tables]
        if not names:
            continue
        cols = [np.interp(grid, tables[n].grid[0], tables[n].values) for n in names]
        rows = tuple((float(g), *(float(col[i]) for col in cols)) for i, g in enumerate(grid))
        blocks.append(Block((axis,), tuple(names), rows))
    constants = [n for n, _ in rb.squareness] + ["P0X", "P0Y", "P0Z"]
    blocks.append(Block((), tuple(constants), (tuple(float(tables[n].values) for n in constants),)))
    return blocks


def write_correction(
    folder: Path,
    blocks: list[Block],
    rb: RigidBody,
    axes: Mapping[str, int],
    name: str = "volcomp_twin",
    filter_steps: int = 0,
) -> Path:
    """Write `<name>.csv` (ISG CSV) and `<name>.lis` (the VOLC list: axis numbers, the
    twin's chain and workpiece axes, the file) into `folder`; returns the list's path."""
    csv = folder / f"{name}.csv"
    csv.write_text(write_isg_csv(blocks), encoding="utf-8")
    lis = folder / f"{name}.lis"
    lines = [
        "# volumetric compensation list [VOLC] written by geo-server from a twin measurement",
        *(f"{a} {axes[a]}" for a in "XYZ"),
        f"chain {rb.chain}",
        f"workpiece_axes {rb.workpiece_axes}",
        f"filter_steps {filter_steps}",
        f"file[0] {csv.name}",
        "file_format[0] ISG_CSV",
    ]
    lis.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return lis


__all__ = ["measure_rigid_body", "write_correction"]
