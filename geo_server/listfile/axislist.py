"""Axis parameter list [AXIS] (`achsmd*.lis`) -> `AxisParams`.

Manual entries: backlash (000 §2.3: `getriebe[0].lose`, `lr_param.anwahl_losekomp`,
`lr_param.n_backlash_cyc`), temperature (000 §3.2: `lr_param.temp_comp*`), the
selections `lr_param.crosscomp`, `crosscomp2`, `ssfk`, `frict_comp`, `crosstalk`, and
`lr_param.prog_movement_requires_compensations` (000 §5.3, number or `LEAD | CROSS`).

Emulator entries (the manuals do not define them; names follow the CNC axis list):

* `kenngr.achs_typ` — axis type, 1 = T linear, 2 = R rotary, 4 = S spindle (default 1);
* `kenngr.modulo_calc` — BOOLEAN, the axis is a modulo axis (default 0);
* `kenngr.modulo_wert` — modulo period in internal units (default 3600000 = 360°);
* `getriebe[0].vb_max` — maximum velocity in µm/s (rotary 0.001°/s); stored ×10 as
  internal units/s;
* `getriebe[0].a_max` — maximum acceleration in mm/s² (rotary °/s²);
* `sim.homed` — BOOLEAN, the axis is referenced at start-up (default 0);
* `sim.start_position` — position at start-up, internal units (default 0).

Configuration errors of backlash (110392) and temperature (emulator ID 990271) switch
that compensation off for the axis: `anwahl_losekomp` / `temp_comp` become 0 (000 §2.4).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from geo_server.listfile.checks import RANGE_CHECK
from geo_server.listfile.schema import Value
from geo_server.listfile.syntax import Entry
from geo_server.listfile.values import Reporter, Values, range_errors_of
from geo_server.model import AxisParams, CompKind, Source
from geo_server.units import ACHS_TYP, UNITS_PER_UM

_KINDS = {typ: kind for kind, typ in ACHS_TYP.items()}  # kenngr.achs_typ -> kind

#: entry (canonical base) -> (AxisParams attribute, conversion). The conversion takes Any:
#: the converted value's type is that of the entry's spec (a MASK is a CompKind already).
_FIELDS: dict[str, tuple[str, Callable[[Any], object]]] = {
    "kopf.log_achs_name": ("name", str),
    "getriebe[].lose": ("lose", int),
    "lr_param.anwahl_losekomp": ("anwahl_losekomp", int),
    "lr_param.n_backlash_cyc": ("n_backlash_cyc", int),
    "lr_param.temp_comp": ("temp_comp", bool),
    "lr_param.temp_comp_position_0": ("temp_comp_position_0", int),
    "lr_param.temp_comp_offset_0": ("temp_comp_offset_0", int),
    "lr_param.temp_comp_coefficient": ("temp_comp_coefficient", float),
    "lr_param.temp_comp_n_cycles": ("temp_comp_n_cycles", int),
    "lr_param.temp_comp_manual_activation": ("temp_comp_manual_activation", bool),
    "lr_param.crosscomp": ("crosscomp", bool),
    "lr_param.crosscomp2": ("crosscomp2", bool),
    "lr_param.ssfk": ("ssfk", bool),
    "lr_param.frict_comp": ("frict_comp", bool),
    "lr_param.crosstalk": ("crosstalk", bool),
    "lr_param.prog_movement_requires_compensations": (
        "prog_movement_requires_compensations",
        CompKind,
    ),
    "kenngr.modulo_calc": ("modulo", bool),
    "kenngr.modulo_wert": ("modulo_period", float),
    "getriebe[].vb_max": ("v_max", lambda v: float(v) * UNITS_PER_UM),  # µm/s -> 0.1 µm/s
    "getriebe[].a_max": ("a_max", float),
    "sim.homed": ("homed", bool),
    "sim.start_position": ("start_position", float),
    "lr_param.vol_comp.s_limit": ("vol_comp_s_limit", int),
}

#: Which attribute switches a compensation off after a configuration error.
_SWITCH = {CompKind.BACKLASH: ("anwahl_losekomp", 0), CompKind.TEMP: ("temp_comp", False)}


def axis_number(values: Values) -> int:
    """`kopf.achs_nr` of the list, 0 if absent (000 p.16 prints it in axis lists)."""
    return int(values.get("kopf.achs_nr", 0))


def build_axis_params(values: Values, log_nr: int, rep: Reporter) -> AxisParams:
    """Fill `AxisParams` from the converted entries of one axis parameter list."""
    params = AxisParams(log_nr=log_nr, path=values.path)
    bad = {e.name for _, e, _ in values.range_errors}
    for base, table in values.data.items():
        for index, item in sorted(table.items()):
            params.sources[item.entry.name] = Source(item.entry.file, item.entry.line)
            if base.startswith("getriebe[]") and index != (0,):
                rep.at("list.ignored", "only gear stage getriebe[0] is used", item.entry)
                continue
            if item.entry.name not in bad:
                _apply(params, base, item.value, rep, item.entry)
    for comp in (CompKind.BACKLASH, CompKind.TEMP):
        _report_ranges(params, values, comp, rep)
    return params


def _apply(params: AxisParams, base: str, value: Value, rep: Reporter, entry: Entry) -> None:
    if base == "kenngr.achs_typ":
        if value not in _KINDS:
            rep.at("list.defective", f"axis type {value} is not 1, 2 or 4: T used", entry)
            return
        params.kind = _KINDS[value]  # type: ignore[index]
        return
    if base in _FIELDS:
        attr, conv = _FIELDS[base]
        setattr(params, attr, conv(value))


def _report_ranges(params: AxisParams, values: Values, comp: CompKind, rep: Reporter) -> None:
    errors = range_errors_of(values, comp)
    for _spec, entry, problem in errors:
        rep.at(RANGE_CHECK[comp], f"{problem}: default used", entry, axis=params.log_nr)
    if errors:
        attr, off = _SWITCH[comp]
        setattr(params, attr, off)
