"""The kinematic model of one volumetric compensation (004 §6.1, p.28-30; docs/volumetric.md §2).

What the correction files and the VOLC list say about the machine, gathered per axis of
the chain: direction, rotation centre, position errors (constants) and the tables of its
component errors. `geo_server.volcomp.reference` evaluates it plainly, the compiled law
(`geo_server.volcomp.law`) from its packed arrays; both read this one description.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geo_server.volcomp.names import ROTARY
from geo_server.volcomp.tables import ParamTable

#: Nominal direction of each axis letter (ISO 841: A, B, C turn about X, Y, Z).
NOMINAL_DIRECTION = {
    "X": (1.0, 0.0, 0.0),
    "Y": (0.0, 1.0, 0.0),
    "Z": (0.0, 0.0, 1.0),
    "A": (1.0, 0.0, 0.0),
    "B": (0.0, 1.0, 0.0),
    "C": (0.0, 0.0, 1.0),
}
_DIRS = "XYZ"
_ANGLES = "ABC"


@dataclass(frozen=True)
class AxisModel:
    """One axis of the chain.

    `sign` is +1 for an axis on the tool side and −1 on the workpiece side (it moves the
    workpiece, so the tool's position relative to the workpiece changes by +q when the
    workpiece moves by −q: ISO 841's primed axes). `position_shift` (X0k, Y0k, Z0k) and
    `position_tilt` (A0k, B0k, C0k) are the position errors; the shift only matters for a
    rotary axis (004 p.28: "position deviation is only relevant for rotary axes").
    `offset` is IDk (004 p.30): added to the programmed value before the model sees it."""

    letter: str
    sign: float
    direction: np.ndarray
    centre: np.ndarray
    position_shift: np.ndarray
    position_tilt: np.ndarray
    offset: float = 0.0

    @property
    def rotary(self) -> bool:
        return self.letter in ROTARY

    def component(self, kind: str) -> list[str]:
        """The names of its translation ("E") component errors EX?, EY?, EZ? or its
        rotation errors EA?, EB?, EC? (004 p.29-30)."""
        letters = _DIRS if kind == "shift" else _ANGLES
        return [f"E{d}{self.letter}" for d in letters]

    def position(self, kind: str) -> list[str]:
        """The names of its position errors: the shift X0?, Y0?, Z0? or the tilt A0?,
        B0?, C0? (004 p.30)."""
        letters = _DIRS if kind == "shift" else _ANGLES
        return [f"{d}0{self.letter}" for d in letters]


@dataclass(frozen=True)
class VolModel:
    """Everything the evaluation needs: chain from the workpiece to the tool (004 p.13),
    how many of its axes carry the workpiece, the axes, the tool point at zero position
    (P0X..P0Z) and the scaled tool orientation (N0X..N0Z, 004 p.15), the tables."""

    chain: tuple[str, ...]
    workpiece_axes: int
    axes: dict[str, AxisModel]
    tables: dict[str, ParamTable]
    tool_zero: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tool_orientation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    alternative: bool = False

    @property
    def linear(self) -> tuple[str, ...]:
        """The linear axes of the chain in X, Y, Z order: the ones corrected."""
        return tuple(a for a in "XYZ" if a in self.chain)

    def tool_point(self, tool_length: float) -> np.ndarray:
        """The tool tip in the frame of the last axis: P0 + length · N0 (004 p.15)."""
        return self.tool_zero + tool_length * self.tool_orientation


def _const(tables: dict[str, ParamTable], name: str, default: float = 0.0) -> float:
    t = tables.get(name)
    if t is None or t.arguments:
        return default
    return float(t.values)


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def build_model(
    chain: str, workpiece_axes: int, tables: dict[str, ParamTable], alternative: bool = False
) -> VolModel:
    """Gather the constant parameters of `tables` per axis (004 p.30: position errors,
    P0?, N0?, P?k centres, V?k orientations, IDk offsets); the component-error tables
    stay tables. Nothing here is validated: `geo_server.volcomp.config` checks the chain
    and the parameters before."""
    axes: dict[str, AxisModel] = {}
    for i, letter in enumerate(chain):
        v = np.array([_const(tables, f"V{d}{letter}", np.nan) for d in _DIRS])
        direction = (
            np.array(NOMINAL_DIRECTION[letter])
            if np.isnan(v).all()
            else _unit(np.nan_to_num(v, nan=0.0))
        )
        axes[letter] = AxisModel(
            letter=letter,
            sign=-1.0 if i < workpiece_axes else 1.0,
            direction=direction,
            centre=np.array([_const(tables, f"P{d}{letter}") for d in _DIRS])
            if letter in ROTARY
            else np.zeros(3),
            position_shift=np.array([_const(tables, f"{d}0{letter}") for d in _DIRS]),
            position_tilt=np.array([_const(tables, f"{a}0{letter}") for a in _ANGLES]),
            offset=_const(tables, f"ID{letter}"),
        )
    return VolModel(
        chain=tuple(chain),
        workpiece_axes=workpiece_axes,
        axes=axes,
        tables=tables,
        tool_zero=np.array([_const(tables, f"P0{d}") for d in _DIRS]),
        tool_orientation=_unit(np.array([_const(tables, f"N0{d}") for d in _DIRS])),
        alternative=alternative,
    )


__all__ = ["NOMINAL_DIRECTION", "AxisModel", "VolModel", "build_model"]
