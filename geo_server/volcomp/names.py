"""Names of the volumetric error parameters and their arguments (004 §6.2 p.30, §6.3.1 p.31).

- position errors `<dir>0<axis>` (X0X … C0C): constants, "global quantities" (004 p.31);
- component errors `E<dir><axis>` (EXX … ECC): typically tables over the axis (004 p.29);
- ISG parameters (004 p.30): tool zero P0*, N0*; rotation centres P?A, P?B, P?C; axis
  orientations V?k; offsets IDk; logical axis numbers LNk.

Units (004 p.31): parameter values in mm, angles in rad; arguments X Y Z in mm, A B C in
degrees.
"""

from __future__ import annotations

AXES = ("X", "Y", "Z", "A", "B", "C")
LINEAR = ("X", "Y", "Z")
ROTARY = ("A", "B", "C")

#: 004 p.30, table "Position errors", row by row: X0X, Y0X, Z0X, A0X, B0X, C0X, X0Y, …
POSITION_ERRORS = tuple(f"{d}0{a}" for a in AXES for d in AXES)
#: 004 p.30, table "Component errors", row by row: EXX, EYX, EZX, EAX, EBX, ECX, EXY, …
COMPONENT_ERRORS = tuple(f"E{d}{a}" for a in AXES for d in AXES)
#: 004 p.30, "ISG parameters", in the order of the manual's table
ISG_PARAMETERS = (
    *("P0X", "P0Y", "P0Z", "N0X", "N0Y", "N0Z"),
    *(f"P{d}{a}" for a in ROTARY for d in LINEAR),
    *(f"V{d}{a}" for a in AXES for d in LINEAR),
    *(f"ID{a}" for a in AXES),
    *(f"LN{a}" for a in AXES),
)
PARAMETERS = frozenset((*POSITION_ERRORS, *COMPONENT_ERRORS, *ISG_PARAMETERS))
#: column names that are arguments: X Y Z in mm, A B C in degrees (004 p.31)
ARGUMENTS = AXES

#: the tool's zero position and orientation belong to no axis (004 p.30)
_TOOL = frozenset({"P0X", "P0Y", "P0Z", "N0X", "N0Y", "N0Z"})


def _known(name: str) -> str:
    if name not in PARAMETERS:
        raise ValueError(f"{name!r} is not a volumetric error parameter (004 p.30)")
    return name


def axis_of(name: str) -> str:
    """The axis a parameter belongs to (004 p.30): the last letter of a position or
    component error (EYX: X), of V?k, P?k, IDk, LNk; "" for the tool's P0* and N0*.

    Raises ValueError for a name that is not a parameter."""
    return "" if _known(name) in _TOOL else name[-1]


def is_angle(name: str) -> bool:
    """Whether the parameter's value is an angle in rad (004 p.31): the A/B/C-direction
    position and component errors (A0X, EBX, ECC …). Everything else is mm or unitless.

    Raises ValueError for a name that is not a parameter."""
    _known(name)
    if name in POSITION_ERRORS:
        return name[0] in ROTARY
    return name in COMPONENT_ERRORS and name[1] in ROTARY
