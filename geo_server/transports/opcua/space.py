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

#: The namespace of every geo-server node (README *OPC UA*): stable across versions.
NAMESPACE_URI = "urn:geo-server:cnc"
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

    @property
    def readable(self) -> bool:
        return self.obj.readable

    @property
    def writable(self) -> bool:
        return self.obj.writable

    @property
    def unit(self) -> str:
        """The unit without the manual's brackets (`µm/m`); "" for `[-]`."""
        text = self.obj.unit.strip().removeprefix("[").removesuffix("]").strip()
        return "" if text == "-" else text

    @property
    def eu_range(self) -> tuple[float, float] | None:
        """(low, high) of the documented range, else of the type; None when unbounded
        (REAL64 without a range, STRING) or not a number."""
        obj = self.obj
        if obj.type.name in ("STRING", "BOOLEAN"):
            return None
        lo = obj.type.lo if obj.min is None else obj.min
        hi = obj.type.hi if obj.max is None else obj.max
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return None
        return float(lo), float(hi)

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
    machine: str, dictionary: Dictionary, axis_names: Mapping[int, str]
) -> list[VariableSpec]:
    """Every variable of one machine (`axis_names`: axis number -> name, in order)."""
    out: list[VariableSpec] = []
    for obj in dictionary.objects:
        group, field = field_parts(obj)
        ua_type = UA_TYPES[obj.type.name]
        path: tuple[str, ...]
        if obj.scope == "axis":
            for axis, name in axis_names.items():
                path = (AXES, name, group, field)
                out.append(VariableSpec("/".join((machine, *path)), path, obj, axis, ua_type))
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
