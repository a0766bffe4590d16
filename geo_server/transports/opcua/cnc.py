"""OPC 40502 "CNC Systems" 1.00 (2017-06-19) for a machine, without any OPC UA library:
which value each mandatory variable of its `CncInterface` shows and where it comes from.

The types are the OPC Foundation's own NodeSet (`nodesets/Opc.Ua.CNC.NodeSet.xml`,
byte-identical to UA-Nodeset's `CNC/Opc.Ua.CNC.NodeSet.xml`, MIT licence in its header),
loaded by the server; the server instantiates them below each machine's object:

    Objects/<m>/CncInterface                       CncInterfaceType
        CncAxisList/<axis name>                    CncAxisType, one per configured axis
            <GROUP> (geo-server's namespace)       the axis' compensation objects: the
                                                   folders of Objects/<m>/Axes/<axis>/
        CncChannelList/Channel1                    CncChannelType, the NC channel
        CncSpindleList                             empty (the emulator has no spindle)

A *live* variable is read from the machine's snapshot like every other variable (and
monitored like them); a *constant* is what the emulator cannot have (a drive's torque,
program names of MDI text, overrides), present with its type and documented here.

Axis values (per axis, in mm on a linear axis, in ° on a rotary one; increments / 10 000,
docs/design.md §3.1):

| variable | source |
|---|---|
| `ActStatus` | Moving (1) while `SIM::velocity` ≠ 0, else InPosition (0) |
| `IsReferenced` | `SIM::homed` |
| `IsInactive` | not `SIM::drive_enable` |
| `IsRotational` | the axis kind (constant) |
| `PosDirect` `ActPos` | `TWIN::true_position`: where the axis is, as a direct scale sees it |
| `PosDirect` `CmdPos` | `SIM::command_position` |
| `PosIndirect` `ActPos` | `SIM::drive_actual_position`: the drive's (motor encoder's) position |
| `PosIndirect` `CmdPos` | `SIM::output_position`: the compensated position commanded to the drive |
| `RemDist` (both) | `SIM::target_position` − `SIM::command_position` |
| `PosDirect`, `PosIndirect` | a CncPositionDataType of their ActPos, CmdPos, RemDist |
| `ZeroOffset`, `ActLoad`, `ActPower`, `ActTorque`, `CmdTorque` | 0 (constants) |

Channel values: `ActProgramStatus` Running (1) while `SIM::program_running`, else Stopped
(0); `ActStatus` Active (0) while running, else Reset (2); `ActProgramBlock` (the texts
of the previous, the actual and the next block) an empty array: the emulator keeps
line numbers, not block texts; `PosTcpBcs<X…C>` and `PosTcpWcs<X…C>` the
positions of the axis of that name (no kinematics, no zero offsets: BCS = WCS = axis
positions), 0 where the machine has no such axis; operation mode MDA (NC text runs as
MDI), overrides 100 %, feed rates 0, program names "" (constants).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.snapshot import Snapshot
from geo_server.units import LINEAR, UNITS_PER_MM

#: the companion specification's namespace
CNC_URI = "http://opcfoundation.org/UA/CNC"
#: the OPC Foundation's NodeSet of it, as published
NODESET = Path(__file__).with_name("nodesets") / "Opc.Ua.CNC.NodeSet.xml"
#: NodeIds of its types in its namespace (the NodeSet's)
INTERFACE_TYPE, CHANNEL_TYPE, AXIS_TYPE = 1007, 1002, 1004
#: the instance below each machine's object, and its channel
INTERFACE, CHANNEL = "CncInterface", "Channel1"
AXIS_LIST, CHANNEL_LIST = "CncAxisList", "CncChannelList"
#: CncAxisStatus, CncChannelProgramStatus, CncChannelStatus, CncOperationMode
IN_POSITION, MOVING = 0, 1
STOPPED, RUNNING = 0, 1
ACTIVE, RESET = 0, 2
MDA = 1
#: the TCP positions a channel has (PosTcpBcs<name>, PosTcpWcs<name>)
TCP_AXES = ("X", "Y", "Z", "A", "B", "C")


@dataclass(frozen=True)
class Live:
    """A variable of a companion model read from the machine's snapshot."""

    path: tuple[str, ...]  # browse names from the model's instance (its name first)
    ua_type: str  # its values' built-in type ("Double", "Boolean", "Int32", "String", …)
    sources: tuple[ObjectDef, ...]  # the objects it is computed from
    read: Callable[[Snapshot], Any]
    #: a number a deadband applies to (not an enumeration, a flag or a structure)
    number: bool = False
    #: the model's structure its values are (`read` gives its fields in order), or ""
    structure: str = ""


#: constants: browse name -> value (wherever it is in the interface)
CONSTANTS: dict[str, Any] = {
    "ZeroOffset": 0.0,
    "ActLoad": 0.0,
    "ActPower": 0.0,
    "ActTorque": 0.0,
    "CmdTorque": 0.0,
    "IsVirtual": False,
    "ActFeedrate": 0.0,
    "CmdFeedrate": 0.0,
    "DryRunFeed": 0.0,
    "ActJogIncrement": 0.0,
    "ActOverride": 100.0,
    "CmdOverride": 100.0,
    "ActOperationMode": MDA,
    "CmdOperationMode": MDA,
    "FeedHold": False,
    "BlockMode": False,
    "ActMainProgramName": "",
    "ActMainProgramFile": "",
    "ActProgramName": "",
    "ActProgramFile": "",
    "Id": 1,
}
#: the unit of each analog variable (a position's is its axis'), for EngineeringUnits
UNITS: dict[str, str] = {
    "ActLoad": "%",
    "ActPower": "W",
    "ActTorque": "N·m",
    "CmdTorque": "N·m",
    "ActFeedrate": "mm/min",
    "CmdFeedrate": "mm/min",
    "DryRunFeed": "mm/min",
    "ActOverride": "%",
    "CmdOverride": "%",
    "ActJogIncrement": "mm",
    "ZeroOffset": "mm",
}
#: an SGN32 position's range in mm or ° (EURange of the positions and offsets)
POSITION_RANGE = (-(2.0**31) / UNITS_PER_MM, (2.0**31 - 1) / UNITS_PER_MM)
#: EURange of the other analog variables by unit: nominal, as a drive's data sheet
#: gives them (the values are constants here; a percent deadband needs a range)
RANGES: dict[str, tuple[float, float]] = {
    "%": (0.0, 100.0),
    "W": (0.0, 100_000.0),
    "N·m": (-10_000.0, 10_000.0),
    "mm/min": (0.0, 100_000.0),
    "mm": POSITION_RANGE,
}


def position_unit(kind: int) -> str:
    return "mm" if kind == LINEAR else "°"


def live_variables(dictionary: Dictionary, axes: Mapping[int, tuple[str, int]]) -> list[Live]:
    """The live variables of a machine's CncInterface (`axes`: axis number -> (name,
    `SIM::axis_type`))."""
    by = dictionary.by_name
    command, target, velocity = (
        by("SIM::command_position"),
        by("SIM::target_position"),
        by("SIM::velocity"),
    )
    out: list[Live] = []
    for axis, (name, _) in axes.items():
        here = (INTERFACE, AXIS_LIST, name)
        out += [
            Live((*here, "ActStatus"), "Int32", (velocity,), _status(velocity, axis)),
            Live(
                (*here, "IsReferenced"),
                "Boolean",
                (by("SIM::homed"),),
                _flag("SIM::homed", by, axis),
            ),
            Live(
                (*here, "IsInactive"),
                "Boolean",
                (by("SIM::drive_enable"),),
                _not("SIM::drive_enable", by, axis),
            ),
        ]
        for group, actual, commanded in (
            ("PosDirect", by("TWIN::true_position"), command),
            ("PosIndirect", by("SIM::drive_actual_position"), by("SIM::output_position")),
        ):
            out += _position((*here, group), actual, commanded, target, command, axis)
    by_name = {name: axis for axis, (name, _) in axes.items()}
    program = by("SIM::program_running")
    channel = (INTERFACE, CHANNEL_LIST, CHANNEL)
    out += [
        Live(
            (*channel, "ActProgramStatus"), "Int32", (program,), either(program, RUNNING, STOPPED)
        ),
        Live((*channel, "ActStatus"), "Int32", (program,), either(program, ACTIVE, RESET)),
    ]
    for system in ("Bcs", "Wcs"):
        for letter in TCP_AXES:
            number = by_name.get(letter)
            if number is not None:
                tcp = (*channel, f"PosTcp{system}{letter}")
                out += _position(tcp, command, command, target, command, number)
    return out


def _position(
    group: tuple[str, ...],
    actual: ObjectDef,
    commanded: ObjectDef,
    target: ObjectDef,
    command: ObjectDef,
    axis: int,
) -> list[Live]:
    """ActPos, CmdPos and RemDist of one CncPositionVariableType, in mm or °, and the
    variable itself: a CncPositionDataType of the three."""
    parts = (
        _scaled(actual, axis),
        _scaled(commanded, axis),
        _remaining(target, command, axis),
    )
    sources = (actual, commanded, target, command)
    return [
        Live((*group, "ActPos"), "Double", (actual,), parts[0], number=True),
        Live((*group, "CmdPos"), "Double", (commanded,), parts[1], number=True),
        Live((*group, "RemDist"), "Double", (target, command), parts[2], number=True),
        Live(group, "ExtensionObject", sources, _all(parts), structure="CncPositionDataType"),
    ]


def _all(parts: tuple[Callable[[Snapshot], Any], ...]) -> Callable[[Snapshot], Any]:
    return lambda snap: tuple(part(snap) for part in parts)


def _scaled(obj: ObjectDef, axis: int) -> Callable[[Snapshot], Any]:
    return lambda snap: float(snap.value(obj, axis)) / UNITS_PER_MM


def _remaining(target: ObjectDef, command: ObjectDef, axis: int) -> Callable[[Snapshot], Any]:
    return lambda snap: (snap.value(target, axis) - snap.value(command, axis)) / UNITS_PER_MM


def _status(velocity: ObjectDef, axis: int) -> Callable[[Snapshot], Any]:
    return lambda snap: MOVING if snap.value(velocity, axis) else IN_POSITION


def _flag(name: str, by: Callable[[str], ObjectDef], axis: int) -> Callable[[Snapshot], Any]:
    obj = by(name)
    return lambda snap: bool(snap.value(obj, axis))


def _not(name: str, by: Callable[[str], ObjectDef], axis: int) -> Callable[[Snapshot], Any]:
    obj = by(name)
    return lambda snap: not snap.value(obj, axis)


def either(flag: ObjectDef, yes: Any, no: Any) -> Callable[[Snapshot], Any]:
    """A value read as `yes` while the machine-wide flag is set, else `no`."""
    return lambda snap: yes if snap.value(flag, 0) else no


__all__ = [
    "AXIS_LIST",
    "AXIS_TYPE",
    "CHANNEL",
    "CHANNEL_LIST",
    "CHANNEL_TYPE",
    "CNC_URI",
    "CONSTANTS",
    "INTERFACE",
    "INTERFACE_TYPE",
    "NODESET",
    "POSITION_RANGE",
    "RANGES",
    "TCP_AXES",
    "UNITS",
    "Live",
    "either",
    "live_variables",
    "position_unit",
]
