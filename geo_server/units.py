"""Engineering units for people: what a raw object value means in mm, µm, ° or mm/s.

The CNC objects carry internal units (docs/design.md §3): one increment is 0.1 µm on a
linear axis and 0.0001° on a rotary axis or spindle; velocities are µm/s (0.001°/s).
Clients show values in engineering units by default and the raw value on request. What
an object measures comes from its `quantity` in the dictionary; whether its axis is
linear or rotary from `SIM::axis_type` (kenngr.achs_typ: 1 linear, 2 rotary, 4 spindle).

| quantity | linear axis | rotary axis / spindle |
|---|---|---|
| position | mm, 4 decimals (increments / 10 000) | °, 4 decimals (increments / 10 000) |
| offset | µm, 1 decimal (increments / 10) | °, 4 decimals (increments / 10 000) |
| velocity | mm/s, 3 decimals (µm/s / 1000) | °/s, 3 decimals (0.001°/s / 1000) |

Everything else is shown as it is, with the dictionary's unit (`TEMPC::coefficient` in
µm/m, `SIM::acceleration` in mm/s², flags, counters).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from geo_server.dictionary import ObjectDef

#: kenngr.achs_typ (P-AXIS-00018): linear, rotary, spindle.
LINEAR, ROTARY, SPINDLE = 1, 2, 4
#: kenngr.achs_typ by the model's axis kind (`AxisParams.kind`: "T", "R", "S").
ACHS_TYP = {"T": LINEAR, "R": ROTARY, "S": SPINDLE}

#: Increments per mm (linear) or per ° (rotary): one increment is 0.1 µm / 0.0001°
#: (docs/design.md §3.1). The one definition; every module takes it from here.
UNITS_PER_MM = 10_000.0
#: Increments per µm (linear) or per 0.001° (rotary); also µm/s per increment/s.
UNITS_PER_UM = 10.0

#: quantity -> (linear (divisor, unit, decimals), rotary (divisor, unit, decimals))
_SCALES: dict[str, tuple[tuple[float, str, int], tuple[float, str, int]]] = {
    "position": ((UNITS_PER_MM, "mm", 4), (UNITS_PER_MM, "°", 4)),
    "offset": ((UNITS_PER_UM, "µm", 1), (UNITS_PER_MM, "°", 4)),
    "velocity": ((1000.0, "mm/s", 3), (1000.0, "°/s", 3)),
}


@dataclass(frozen=True)
class Shown:
    """A value as shown: the number (or flag, text), its unit, and the text of both."""

    value: Any
    unit: str

    def __str__(self) -> str:
        return f"{self.value} {self.unit}".rstrip()


def raw_unit(obj: ObjectDef) -> str:
    """The dictionary's unit without brackets (`[µm/m]` -> `µm/m`, `[-]` -> ``)."""
    unit = obj.unit.strip("[]")
    return "" if unit == "-" else unit


#: quantity -> the raw increment on a rotary axis or spindle, where the dictionary's unit
#: (`[0.1 µm]`, `[µm/s]`) names the linear one (docs/design.md §3.1)
_ROTARY_RAW = {"position": "0.0001°", "offset": "0.0001°", "velocity": "0.001°/s"}


def raw_unit_on(obj: ObjectDef, axis_type: int) -> str:
    """`raw_unit` for an axis of `axis_type`: a position or offset of a rotary axis
    counts 0.0001°, not 0.1 µm; of a unit the dictionary gives for both kinds
    (`mm/s² | °/s²`) the one of the axis' kind."""
    unit = raw_unit(obj)
    if "|" in unit:
        linear, _, rotary = unit.partition("|")
        return (linear if axis_type == LINEAR else rotary).strip()
    if axis_type != LINEAR and obj.quantity in _ROTARY_RAW and unit != "Incr.":
        return _ROTARY_RAW[obj.quantity]
    return unit


#: A unit as the dictionary writes it -> its UN/CEFACT common code (UNECE
#: Recommendation 20) and name, as OPC UA's EUInformation takes them (OPC 10000-8
#: §5.6.3). The dictionary's other units (an increment of 0.1 µm or 0.0001°, µm/s,
#: 0.001°/s, drive units) have no common code: their UnitId is -1.
UNECE: dict[str, tuple[str, str]] = {
    "mm": ("MMT", "millimetre"),
    "µm": ("4H", "micrometre (micron)"),
    "°": ("DD", "degree [unit of angle]"),
    "s": ("SEC", "second [unit of time]"),
    "µs": ("B98", "microsecond"),
    "°C": ("CEL", "degree Celsius"),
    "mm/s": ("C16", "millimetre per second"),
    "°/s": ("E96", "degree per second"),
    "mm/s²": ("M41", "millimetre per second squared"),
    "°/s²": ("M45", "degree [unit of angle] per second squared"),
    "µm/m": ("59", "part per million"),  # (µm/m is 10⁻⁶: a part per million)
    # (the OPC UA CNC model's drive and channel values: transports/opcua/cnc.py)
    "%": ("P1", "percent"),
    "W": ("WTT", "watt"),
    "N·m": ("NU", "newton metre"),
    "mm/min": ("H81", "millimetre per minute"),
}


def unece_unit_id(unit: str) -> int:
    """The EUInformation UnitId of a unit: its common code's characters as the bytes
    of one number (OPC 10000-8 §5.6.3: "MMT" is 5 066 068), -1 without a code."""
    code = UNECE.get(unit, ("", ""))[0]
    number = 0
    for char in code:
        number = number << 8 | ord(char)
    return number if code else -1


def show(obj: ObjectDef, value: Any, axis_type: int = LINEAR, raw: bool = False) -> Shown:
    """`value` of `obj` in engineering units (or as it is with `raw`)."""
    scales = _SCALES.get(obj.quantity or "")
    if raw or scales is None or isinstance(value, bool) or not isinstance(value, int | float):
        return Shown(value, raw_unit(obj) or ("Incr." if obj.quantity else ""))
    divisor, unit, decimals = scales[0] if axis_type == LINEAR else scales[1]
    return Shown(round(value / divisor, decimals), unit)


def parse_axis_names(text: str) -> dict[str, int]:
    """`SIM::axis_names` ("1=X 2=Y 3=Z 4=C") as {"X": 1, …} (names upper-case)."""
    out: dict[str, int] = {}
    for item in text.split():
        number, _, name = item.partition("=")
        if number.isdigit() and name:
            out[name.upper()] = int(number)
    return out


__all__ = [
    "ACHS_TYP",
    "LINEAR",
    "ROTARY",
    "SPINDLE",
    "UNECE",
    "UNITS_PER_MM",
    "UNITS_PER_UM",
    "Shown",
    "parse_axis_names",
    "raw_unit",
    "raw_unit_on",
    "show",
    "unece_unit_id",
]
