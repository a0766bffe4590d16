"""What an HMI shows, as data: which objects make each compensation's columns, and the
JSON the web HMI sends (docs/web.md). Pure functions of a snapshot and the machine's
configuration; the terminal HMI (`geo_clients.hmi`) uses the same table."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.model import MachineConfig
from geo_server.snapshot import Snapshot
from geo_server.units import ACHS_TYP, LINEAR, ROTARY, raw_unit, raw_unit_on, show


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
#: Trends: field -> title and unit (linear axes, rotary axes) on the web page.
TRENDS: dict[str, tuple[str, str, str]] = {
    "total_offset": ("Total offset", "µm", "°"),
    "residual": ("Residual error (twin)", "µm", "°"),
    "sensor_temperature": ("Sensor temperature (twin)", "°C", "°C"),
}
#: Trends of a machine without a twin (no `twin.toml` beside its start-up list).
TRENDS_WITHOUT_TWIN = ("total_offset",)


def writable_tempc(dictionary: Dictionary) -> list[ObjectDef]:
    """The TEMPC objects an HMI may edit: every writable one (000 p.21–23)."""
    return [o for o in dictionary.objects if o.key_group == "tempc" and "w" in o.access]


def object_info(obj: ObjectDef) -> dict[str, Any]:
    """What the page's editor needs to know of an object: its unit and range."""
    return {
        "name": obj.name,
        "field": obj.key_field,
        "type": obj.type.name,
        "unit": raw_unit(obj),
        "rotary_unit": raw_unit_on(obj, ROTARY),
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
        #: the twin's objects are only shown for a machine that has one
        self.has_twin = cfg.twin is not None
        by = dictionary.by_name
        self.fields = [(f, by(n)) for f, n in AXIS_FIELDS if f != "axis_type"]
        if self.has_twin:
            self.fields += [(f, by(n)) for f, n in TWIN_FIELDS]
        self.trend_fields = tuple(TRENDS) if self.has_twin else TRENDS_WITHOUT_TWIN
        fields = dict(self.fields)
        self._trend_objects = [fields[f] for f in self.trend_fields]
        self.tempc = [(o.key_field, o) for o in writable_tempc(dictionary)]
        #: the TEMPC objects that also have an engineering value (offset_0, position_0)
        self.tempc_shown = [(f, o) for f, o in self.tempc if o.quantity]
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
        """One axis of a push: its values, TEMPC parameters and compensation columns."""
        out: dict[str, Any] = {f: self.shown(o, snap.value(o, axis), axis) for f, o in self.fields}
        out["tempc"] = {f: snap.value(o, axis) for f, o in self.tempc}
        out["tempc_shown"] = {
            f: str(show(o, out["tempc"][f], self.kind[axis])) for f, o in self.tempc_shown
        }
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
        """The `live` message: `t` in seconds since the epoch (the trends' time axis)."""
        return {
            "type": "live",
            "t": round(t, 3),
            "cycle": snap.cycle,
            "axes": {str(a): self.axis(snap, a) for a in self.axes},
        }

    def trend_point(self, live: dict[str, Any]) -> list[float]:
        """One trend sample: per axis, each trend field (µm / °, °C)."""
        return [float(live["axes"][str(a)][f]) for a in self.axes for f in self.trend_fields]

    def trend_sample(self, snap: Snapshot) -> list[float]:
        """`trend_point(push(snap, t))` without the rest of the push (every sample takes
        this; a fleet of machines at rest takes one a second each while nobody
        watches). `trend_point` is its readable reference (tests/test_web_hmi.py)."""
        return [
            float(self.shown(o, snap.value(o, a), a))
            for a in self.axes
            for o in self._trend_objects
        ]


class Trends:
    """The trend samples of the last `seconds` (a ring: samples come at the push rate
    while somebody watches, more slowly while nobody does)."""

    def __init__(self, series: int, seconds: float = 600.0, rate: float = 10.0) -> None:
        self.seconds = seconds
        self.samples: deque[tuple[float, list[float]]] = deque(maxlen=int(seconds * rate) + 1)
        self.series = series

    def add(self, t: float, values: list[float]) -> None:
        self.samples.append((t, values))
        while self.samples and self.samples[0][0] < t - self.seconds:
            self.samples.popleft()

    def as_json(self) -> dict[str, Any]:
        """Column by column: `t` and one list per series (axis-major, field-minor)."""
        t = [s[0] for s in self.samples]
        cols = [[s[1][i] for s in self.samples] for i in range(self.series)]
        return {"t": t, "series": cols}
