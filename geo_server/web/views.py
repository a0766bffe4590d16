"""What an HMI shows, as data: which objects make each compensation's columns, and the
JSON the web HMI sends (docs/web.md). Pure functions of a snapshot and the machine's
configuration; the terminal HMI (`geo_clients.hmi`) uses the same table."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.model import MachineConfig
from geo_server.snapshot import Snapshot
from geo_server.units import ACHS_TYP, LINEAR, UNITS_PER_MM, UNITS_PER_UM, raw_unit, show


@dataclass(frozen=True)
class CompView:
    """Which objects show one compensation's columns (None: the manual has no object)."""

    key: str
    title: str
    selected: str | None
    effective: str | None
    actual: str | None
    delta: str | None
    unfiltered: str | None
    parameters: tuple[tuple[str, str], ...] = ()


#: The compensations in the order of the GEO cycle (docs/design.md §5) and their objects (000).
COMPENSATIONS: tuple[CompView, ...] = (
    CompView(
        "TEMP",
        "temperature",
        "TEMPC::activated",
        "TEMPC::f_is_active",
        "TEMPC::actual_offset",
        None,
        None,
        (
            ("coefficient", "TEMPC::coefficient"),
            ("offset_0", "TEMPC::offset_0"),
            ("position_0", "TEMPC::position_0"),
        ),
    ),
    CompView(
        "CROSS",
        "cross",
        "CROSSC::activated",
        "CROSSC::f_is_active",
        "CROSSC::actual_offset",
        "CROSSC::delta_offset",
        None,
    ),
    CompView("PLANE", "plane", "CC2::activated", None, "CC2::correction", None, None),
    CompView(
        "CROSSTALK",
        "crosstalk",
        "CROSSTALK::activated",
        None,
        "CROSSTALK::actual_offset",
        "CROSSTALK::delta_offset",
        "CROSSTALK::end_offset",
    ),
    CompView(
        "LSEC",
        "leadscrew",
        "ssfk activated",
        "LSEC::active",
        "LSEC::sum epsilon",
        "LSEC::epsilon",
        None,
    ),
    CompView(
        "BC",
        "backlash",
        None,
        None,
        "BC::actual backlash",
        "BC::delta backlash",
        "BC::sum backlash",
        (("conf_backlash", "BC::conf. backlash"),),
    ),
    CompView("FRICT", "friction", None, None, "FRICT::additive_current", None, None),
)
#: Axis-level values: field -> object (docs/design.md §2 emulator objects).
AXIS_FIELDS: tuple[tuple[str, str], ...] = (
    ("axis_type", "SIM::axis_type"),
    ("homed", "SIM::homed"),
    ("command_position", "SIM::command_position"),
    ("output_position", "SIM::output_position"),
    ("total_offset", "SIM::total_offset"),
    ("velocity", "SIM::velocity"),
)
#: The twin's values the web HMI shows and trends (docs/twin.md).
TWIN_FIELDS: tuple[tuple[str, str], ...] = (
    ("residual", "TWIN::residual"),
    ("sensor_temperature", "TWIN::sensor_temperature"),
)
#: Trends: field -> what it is (the web page's titles).
TRENDS = ("total_offset", "residual", "sensor_temperature")


def writable_tempc(dictionary: Dictionary) -> list[ObjectDef]:
    """The TEMPC objects an HMI may edit: every writable one (000 p.21–23)."""
    return [o for o in dictionary.objects if o.key_group == "tempc" and "w" in o.access]


def object_info(obj: ObjectDef) -> dict[str, Any]:
    return {
        "name": obj.name,
        "field": obj.key_field,
        "type": obj.type.name,
        "unit": raw_unit(obj),
        "min": obj.min,
        "max": obj.max,
    }


class LiveView:
    """Builds the JSON of one push from one snapshot: every axis' positions, offsets and
    compensation columns in engineering units. The objects are looked up once."""

    def __init__(self, dictionary: Dictionary, cfg: MachineConfig, axes: tuple[int, ...]) -> None:
        self.dictionary = dictionary
        self.axes = axes
        self.kind = {a: ACHS_TYP.get(cfg.axes[a].params.kind, LINEAR) for a in axes}
        by = dictionary.by_name
        self.fields = [(f, by(n)) for f, n in AXIS_FIELDS if f != "axis_type"]
        self.twin = [(f, by(n)) for f, n in TWIN_FIELDS]
        self.tempc = [(o.key_field, o) for o in writable_tempc(dictionary)]
        self.comps = [
            (
                c.key,
                by(c.selected) if c.selected else None,
                by(c.effective) if c.effective else None,
                by(c.actual) if c.actual else None,
            )
            for c in COMPENSATIONS
        ]

    def shown(self, obj: ObjectDef, value: Any, axis: int) -> Any:
        return show(obj, value, self.kind[axis]).value

    def axis(self, snap: Snapshot, axis: int) -> dict[str, Any]:
        out: dict[str, Any] = {
            f: self.shown(o, snap.value(o, axis), axis) for f, o in (*self.fields, *self.twin)
        }
        out["tempc"] = {f: snap.value(o, axis) for f, o in self.tempc}
        out["comps"] = {
            key: [
                None if s is None else bool(snap.value(s, axis)),
                None if e is None else bool(snap.value(e, axis)),
                None if a is None else self.shown(a, snap.value(a, axis), axis),
            ]
            for key, s, e, a in self.comps
        }
        return out

    def push(self, snap: Snapshot, t: float) -> dict[str, Any]:
        return {
            "type": "live",
            "t": round(t, 3),
            "cycle": snap.cycle,
            "axes": {str(a): self.axis(snap, a) for a in self.axes},
        }

    def trend_point(self, live: dict[str, Any]) -> list[float]:
        """One trend sample: per axis total offset (µm / °), residual, sensor °C."""
        return [float(live["axes"][str(a)][f]) for a in self.axes for f in TRENDS]


class Trends:
    """The last `seconds` of trend samples at `rate` per second (a ring)."""

    def __init__(self, series: int, seconds: float = 600.0, rate: float = 10.0) -> None:
        self.samples: deque[tuple[float, list[float]]] = deque(maxlen=int(seconds * rate))
        self.series = series

    def add(self, t: float, values: list[float]) -> None:
        self.samples.append((t, values))

    def as_json(self) -> dict[str, Any]:
        t = [s[0] for s in self.samples]
        cols = [[s[1][i] for s in self.samples] for i in range(self.series)]
        return {"t": t, "series": cols}


# ---------------------------------------------------------------------- tables


def _mm(v: np.ndarray) -> list[float]:
    return [round(float(x) / UNITS_PER_MM, 4) for x in v]


def _um(v: np.ndarray) -> list[float]:
    return [round(float(x) / UNITS_PER_UM, 2) for x in v]


def _rotary(cfg: MachineConfig, axis: int) -> bool:
    return axis in cfg.axes and cfg.axes[axis].params.kind != "T"


def _offsets(cfg: MachineConfig, axis: int, v: np.ndarray) -> list[float]:
    """Corrections of `axis`: µm on a linear axis, ° on a rotary one (docs/design.md §3)."""
    if _rotary(cfg, axis):
        return [round(float(x) / UNITS_PER_MM, 4) for x in v]
    return _um(v)


def tables(cfg: MachineConfig, axes: tuple[int, ...]) -> list[dict[str, Any]]:
    """Every configured compensation table in engineering units (positions in mm,
    corrections in µm; docs/design.md §3): curves (LSEC, cross, friction) and grids
    (plane; crosstalk mode 3 as scattered points)."""
    names = {a: cfg.axes[a].params.name for a in axes}
    out: list[dict[str, Any]] = []
    for a in axes:
        comp = cfg.axes[a].comp
        if comp is None:
            continue
        base = {"axis": a, "name": names[a]}
        if comp.lsec is not None and comp.lsec.valid:
            out.append(
                {
                    **base,
                    "kind": "lsec",
                    "title": f"{names[a]} leadscrew (LSEC)",
                    "x": _mm(comp.lsec.setpoint),
                    "x_axis": a,
                    "series": {
                        "positive": _offsets(cfg, a, comp.lsec.pos),
                        "negative": _offsets(cfg, a, comp.lsec.neg),
                    },
                    "x_unit": "°" if _rotary(cfg, a) else "mm",
                    "y_unit": "°" if _rotary(cfg, a) else "µm",
                }
            )
        if comp.cross is not None and comp.cross.valid:
            m = comp.cross.master_ax_nr
            out.append(
                {
                    **base,
                    "kind": "cross",
                    "title": f"{names[a]} cross over {names.get(m, m)} (CROSSC)",
                    "x": _mm(comp.cross.setpoint),
                    "x_axis": m,
                    "series": {"correction": _um(comp.cross.correction)},
                    "x_unit": "mm",
                    "y_unit": "µm",
                }
            )
        if comp.frict is not None and comp.frict.valid:
            out.append(
                {
                    **base,
                    "kind": "frict",
                    "title": f"{names[a]} friction (FRICT)",
                    "x": [float(v) for v in comp.frict.vin],
                    "x_axis": a,
                    "series": {"current": [float(v) for v in comp.frict.out]},
                    "x_unit": "velocity (list units)",
                    "y_unit": "current (list units)",
                }
            )
        if comp.plane is not None and comp.plane.valid:
            p = comp.plane
            ny, nx = p.table.shape
            out.append(
                {
                    **base,
                    "kind": "plane",
                    "title": f"{names[a]} plane over {names.get(p.master1_ax_nr)}/"
                    f"{names.get(p.master2_ax_nr)} (CC2)",
                    "x_axis": p.master1_ax_nr,
                    "y_axis": p.master2_ax_nr,
                    "x": _mm(p.start_position_master1 + p.interval1 * np.arange(nx)),
                    "y": _mm(p.start_position_master2 + p.interval2 * np.arange(ny)),
                    "z": [_um(row) for row in p.table],
                    "x_unit": "mm",
                    "z_unit": "µm",
                }
            )
        ct = comp.crosstalk
        if ct is not None and ct.valid and ct.mode == 3:
            out.append(
                {
                    **base,
                    "kind": "scatter",
                    "title": f"{names[a]} crosstalk mode 3 over "
                    f"{names.get(ct.master_pos1_ax_nr)}/{names.get(ct.master_pos2_ax_nr)}",
                    "x_axis": ct.master_pos1_ax_nr,
                    "y_axis": ct.master_pos2_ax_nr,
                    "x": _mm(ct.ax_1),
                    "y": _mm(ct.ax_2),
                    "z": _um(ct.corrections[:, 0]),
                    "x_unit": "mm",
                    "z_unit": "µm",
                }
            )
    return out
