"""OPC 40501 "Machine Tools" 1.01.1 (2022-07-04) for a machine, without any OPC UA
library: what its `MachineToolType` instance in the Machinery `Machines` folder shows.

The types are the OPC Foundation's NodeSets (`nodesets/`, byte-identical to UA-Nodeset's,
MIT licence in their headers), loaded in the order they need each other: DI 1.04.0
(2022-11-03), Machinery 1.03.0 (2023-08-01), IA 1.01.2 (2024-02-28), Machine Tool 1.01.1.
Machine Tool 1.02 needs the Machinery Jobs model and through it ISA-95 Job Control, which
asyncua cannot load; 1.01.1 is the newest version that loads.

    Objects/Machines/<m>                           MachineToolType (its node id
                                                   `<m>/MachineTool`)
        Identification                             Manufacturer "geo-server", SerialNumber
                                                   the machine's name, ProductInstanceUri
                                                   urn:geo-server:<host>:<m>
        Monitoring/MachineTool/OperationMode       Automatic (1) while an NC program runs,
                                                   else Manual (0)
        Production/ActiveProgram                   Name "MDI" while NC text runs (the
                                                   emulator runs NC text as MDI), else "";
                                                   NumberInList 0; State: Running (1)
                                                   while it runs, else Ended (2)
        Notification/Messages                      the machine's warnings and errors as
                                                   NotificationEventType events (Message
                                                   with file and line, Severity 700 for an
                                                   error and 400 for a warning, Identifier
                                                   the manual's error ID)
        Equipment                                  present, empty (no optional parts)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from geo_server.dictionary import Dictionary
from geo_server.events import Event
from geo_server.transports.opcua.cnc import Live, either

FOLDER = Path(__file__).with_name("nodesets")
#: (namespace URI, NodeSet file), in the order they are loaded
NODESETS: tuple[tuple[str, Path], ...] = (
    ("http://opcfoundation.org/UA/DI/", FOLDER / "Opc.Ua.Di.NodeSet2.xml"),
    ("http://opcfoundation.org/UA/Machinery/", FOLDER / "Opc.Ua.Machinery.NodeSet2.xml"),
    ("http://opcfoundation.org/UA/IA/", FOLDER / "Opc.Ua.IA.NodeSet2.xml"),
    ("http://opcfoundation.org/UA/MachineTool/", FOLDER / "Opc.Ua.MachineTool.NodeSet2.xml"),
)
MACHINERY_URI, MACHINE_TOOL_URI = NODESETS[1][0], NODESETS[3][0]
#: MachineToolType, and the Machines folder (Machinery), in their namespaces
MACHINE_TOOL_TYPE, MACHINES_FOLDER = 13, 1001
#: MessagesType (Notification/Messages) and NotificationEventType (its events)
MESSAGES_TYPE, NOTIFICATION_EVENT_TYPE = 38, 35
#: an event's Severity (OPC 10000-5 §6.4.2: 1-1000) by the message's severity
SEVERITY = {"error": 700, "warning": 400}
#: the instance's name in its node id (below the machine's)
INSTANCE = "MachineTool"
#: MachineOperationModeEnumeration
MANUAL, AUTOMATIC = 0, 1
#: ProductionProgramStateMachineType's states: (name, StateNumber, the state's NodeId)
RUNNING, ENDED = ("Running", 1, 5041), ("Ended", 2, 5038)
MANUFACTURER = "geo-server"
#: what the active program is called while NC text runs
MDI = "MDI"


def identification(machine: str, host: str) -> dict[str, Any]:
    """The Identification values of a machine on `host` (its name is its serial
    number; its URI names the host too, to be unique beyond it: OPC 10000-100)."""
    return {
        "Manufacturer": MANUFACTURER,
        "SerialNumber": machine,
        "ProductInstanceUri": f"urn:geo-server:{host}:{machine}",
    }


def live_variables(dictionary: Dictionary) -> list[Live]:
    """The live variables of a machine's MachineTool instance (`Live.path` from it)."""
    running = dictionary.by_name("SIM::program_running")
    program = (INSTANCE, "Production", "ActiveProgram")
    state = (*program, "State", "CurrentState")
    return [
        Live(
            (INSTANCE, "Monitoring", "MachineTool", "OperationMode"),
            "Int32",
            (running,),
            either(running, AUTOMATIC, MANUAL),
        ),
        Live((*program, "Name"), "String", (running,), either(running, MDI, "")),
        Live(state, "LocalizedText", (running,), either(running, RUNNING[0], ENDED[0])),
        Live((*state, "Number"), "UInt32", (running,), either(running, RUNNING[1], ENDED[1])),
        Live((*state, "Id"), "NodeId", (running,), either(running, RUNNING[2], ENDED[2])),
    ]


def notification(event: Event) -> tuple[str, int, str]:
    """(Message, Severity, Identifier) of the NotificationEventType event of a warning
    or error of the machine's list (`geo-client errors`): the text with its file and
    line, and the manual's error ID."""
    d = event.diagnostic
    where = f" ({d.file}:{d.line})" if d.file else ""
    return f"{d.message}{where}", SEVERITY.get(d.severity, 400), str(d.error_id)


__all__ = [
    "AUTOMATIC",
    "ENDED",
    "INSTANCE",
    "MACHINERY_URI",
    "MACHINES_FOLDER",
    "MACHINE_TOOL_TYPE",
    "MACHINE_TOOL_URI",
    "MANUAL",
    "MESSAGES_TYPE",
    "NODESETS",
    "NOTIFICATION_EVENT_TYPE",
    "RUNNING",
    "SEVERITY",
    "identification",
    "live_variables",
    "notification",
]
