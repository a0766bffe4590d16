"""The OPC UA address space of one machine, generated from the object dictionary
(README *OPC UA*), without any OPC UA library: a plan the server turns into nodes.

    Objects/<machine>/Axes/<axis name>/<GROUP>/<field>    per-axis objects
    Objects/<machine>/<GROUP>/<field>                     machine-wide objects
    Objects/<machine>/<method>                            Reload, Save, RunNc, Reset,
                                                          InjectFault, ClearFaults

`<GROUP>` and `<field>` are the parts of the ADS symbol name (`GEO.X.TEMPC.coefficient`
is `Objects/<m>/Axes/X/TEMPC/coefficient`; `symbols.symbol_name`), so no name is typed
twice. Node ids are strings in the namespace `NAMESPACE_URI`: the path below `Objects`
joined with `/` (`ns=<i>;s=local/Axes/X/TEMPC/coefficient`); the namespace index is
whatever the server's NamespaceArray says (2 for a geo-server), the URI never changes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.units import LINEAR, raw_unit_on

#: The namespace of every geo-server node (README *OPC UA*): stable across versions.
NAMESPACE_URI = "urn:geo-server:cnc"
#: the server's ApplicationUri (namespace 1, and its certificate's)
APPLICATION_URI = "urn:geo-server:server"
#: The folder of the per-axis objects under each machine.
AXES = "Axes"
#: Dictionary type -> OPC UA built-in type name (`ua.VariantType` member).
UA_TYPES: dict[str, str] = {
    "BOOLEAN": "Boolean",
    "UNS16": "UInt16",
    "UNS32": "UInt32",
    "SGN32": "Int32",
    "REAL64": "Double",
    "STRING": "String",
}


@dataclass(frozen=True)
class VariableSpec:
    """One variable node: an object of one axis (axis 0: machine-wide)."""

    node_id: str  # the string identifier, also the browse path below Objects
    path: tuple[str, ...]  # folders below the machine's object, then the variable's name
    obj: ObjectDef
    axis: int
    ua_type: str
    axis_type: int = LINEAR  # its axis' kind (`units.LINEAR`, `ROTARY`, `SPINDLE`)

    @property
    def readable(self) -> bool:
        return self.obj.readable

    @property
    def writable(self) -> bool:
        return self.obj.writable

    @property
    def unit(self) -> str:
        """The one unit of its values on its axis (`µm/m`; `°/s²` on a rotary axis
        where the dictionary gives `mm/s² | °/s²`); "" for `[-]`."""
        return raw_unit_on(self.obj, self.axis_type)

    @property
    def analog(self) -> bool:
        """A number with a unit: a measured or set quantity (OPC 10000-8 §5.3.2),
        not a flag, a counter, a mode or a text."""
        return self.ua_type not in ("Boolean", "String") and bool(self.unit)

    @property
    def eu_range(self) -> tuple[float, float] | None:
        """(low, high) of an analog value's documented range (the dictionary's min and
        max, from the manual); None without one."""
        obj = self.obj
        if not self.analog or obj.min is None or obj.max is None:
            return None
        if not (math.isfinite(obj.min) and math.isfinite(obj.max)):
            return None
        return float(obj.min), float(obj.max)

    @property
    def type_definition(self) -> str:
        """Its VariableType (OPC 10000-8 §5.3.2): AnalogItemType (EURange mandatory)
        where the range is documented, BaseAnalogType for other analog values,
        BaseDataVariableType for the rest."""
        if self.eu_range is not None:
            return "AnalogItemType"
        return "BaseAnalogType" if self.analog else "BaseDataVariableType"

    @property
    def description(self) -> str:
        """The dictionary's description, citing the manual (docs/design.md §1)."""
        return f"{self.obj.description} Source: {self.obj.source}."

    @property
    def ads_address(self) -> str:
        """The raw ADS address: `port 551, 0x120300:0x10043`."""
        obj = self.obj
        return f"port {obj.ams_port}, 0x{obj.index_group:X}:0x{obj.index_offset(self.axis):X}"


@dataclass(frozen=True)
class MethodSpec:
    """A command as a method of the machine's object: (argument name, OPC UA type,
    description) in, one String out (the command's result as JSON)."""

    name: str
    inputs: tuple[tuple[str, str, str], ...]
    description: str


#: The commands every interface has (docs/design.md §7), as OPC UA methods.
METHODS: tuple[MethodSpec, ...] = (
    MethodSpec("Reload", (), "Reload the list files: validated, swapped at once or rejected."),
    MethodSpec("Save", (), "Write the live parameters back into the machine's own lists."),
    MethodSpec("RunNc", (("text", "String", "NC lines, run as MDI"),), "Run NC text."),
    MethodSpec("Reset", (), "CNC reset: program stopped, axes stopped."),
    MethodSpec(
        "InjectFault",
        (("fault", "String", "a fault in the text form of docs/faults.md"),),
        "Inject a fault (docs/faults.md).",
    ),
    MethodSpec(
        "ClearFaults",
        (("id", "String", 'a fault id, or "all"'),),
        "Clear one injected fault or all of them.",
    ),
)


def field_parts(obj: ObjectDef) -> tuple[str, str]:
    """(GROUP, field) as in the ADS symbol name (`TEMPC`, `coefficient`)."""
    group = obj.key_group.upper()
    field = obj.key_field
    prefix = obj.key_group + "_"
    return group, field[len(prefix) :] if field.startswith(prefix) else field


def machine_variables(
    machine: str,
    dictionary: Dictionary,
    axis_names: Mapping[int, str],
    axis_types: Mapping[int, int] | None = None,
) -> list[VariableSpec]:
    """Every variable of one machine (`axis_names`: axis number -> name, in order;
    `axis_types`: axis number -> `SIM::axis_type`, linear where not given)."""
    kinds = axis_types or {}
    out: list[VariableSpec] = []
    for obj in dictionary.objects:
        group, field = field_parts(obj)
        ua_type = UA_TYPES[obj.type.name]
        path: tuple[str, ...]
        if obj.scope == "axis":
            for axis, name in axis_names.items():
                path = (AXES, name, group, field)
                node_id = "/".join((machine, *path))
                kind = kinds.get(axis, LINEAR)
                out.append(VariableSpec(node_id, path, obj, axis, ua_type, kind))
        else:
            path = (group, field)
            out.append(VariableSpec("/".join((machine, *path)), path, obj, 0, ua_type))
    if len({v.node_id for v in out}) != len(out):
        raise ValueError("two objects map to one OPC UA node")
    return out


__all__ = [
    "AXES",
    "METHODS",
    "NAMESPACE_URI",
    "UA_TYPES",
    "MethodSpec",
    "VariableSpec",
    "field_parts",
    "machine_variables",
]
