"""OPC 40502 "CNC Systems" and OPC 40501 "Machine Tools", checked against the OPC
Foundation's own definitions.

- The NodeSets the server loads are the ones the OPC Foundation publishes (their SHA-256,
  UA-Nodeset: CNC 1.00 of 2017-06-19, DI 1.04.0, Machinery 1.03.0, IA 1.01.2, Machine
  Tool 1.01.1).
- This test reads the XML itself (not through the server's code), lists every mandatory
  node of `CncInterfaceType`, `CncAxisType`, `CncChannelType` and `MachineToolType` (their
  supertypes' and their declarations' types' included, across the files), and has
  node-opcua's client (another stack, nobody here wrote it) find each on the running
  server by its browse path, with the declared type and, for a variable, a Good value.
- The axis values are those of ADS reads (pyads) of the same cycle, in mm (increments /
  10 000, docs/design.md §3.1).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyads
import pytest
from asyncua import Client, ua
from conftest import run_in
from test_ads_server import TIMEOUT, next_netid, start_server

from geo_server import access
from geo_server.client.ads_client import close_port_first
from geo_server.service import ObjectService
from geo_server.transports.opcua import cnc, machinetool
from geo_server.transports.opcua.server import OpcUaInterface, OpcUaOptions

NODE_DIR = Path(__file__).parent / "node"
NODE = shutil.which("node")
INSTALLED = (NODE_DIR / "node_modules" / "node-opcua-client").is_dir()
REQUIRED = os.environ.get("GEO_SERVER_REQUIRE_NODE") == "1"
#: the published files' SHA-256 (OPCFoundation/UA-Nodeset: CNC/, DI/, Machinery/, IA/ at
#: a2d4ae8 (2024-10-18); MachineTool/ at f484a8d, MachineTool-1.01.1-2022-07-04)
PUBLISHED_SHA256 = {
    "Opc.Ua.CNC.NodeSet.xml": "c81eb71541f5846c126b913bc00e768fd04c39e1edb0a0c92e9d1552bfa1d9d6",
    "Opc.Ua.Di.NodeSet2.xml": "ec376a3992f38740fd9263ec06e7560af2d56adb8ffdbd5f7ebc813ae0273fe5",
    "Opc.Ua.Machinery.NodeSet2.xml": (
        "f6f46f8c0c41ced2f4c6c7304728bcf989018c8013b6cc8e0fcaa23eefbc9931"
    ),
    "Opc.Ua.IA.NodeSet2.xml": "2a198ed96604eaf473d1ebfb4b29d745a7af8eed74c0f96ab1ac5f1fb71e4de9",
    "Opc.Ua.MachineTool.NodeSet2.xml": (
        "849b29895d096867856642c777b1f6b1c9854c9932354b10a45089d3af7f6e74"
    ),
}
UA = "http://opcfoundation.org/UA/"
CNC = "http://opcfoundation.org/UA/CNC"
MACHINERY = "http://opcfoundation.org/UA/Machinery/"
MACHINE_TOOL = "http://opcfoundation.org/UA/MachineTool/"
GEO_NS = "urn:geo-server:cnc"
XML_NS = {"u": "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"}
MANDATORY, HAS_SUBTYPE, HAS_TYPE, HAS_RULE = (f"{UA}|{i}" for i in (78, 45, 40, 37))
#: HasProperty, HasComponent, HasAddIn
HIERARCHICAL = {f"{UA}|46", f"{UA}|47", f"{UA}|17604"}
#: an Object's entry in the list of expected nodes (no DataType, no ValueRank)
OBJECT = ("UAObject", "", 0)
#: the built-in DataTypes whose values are Variants of that very type (Boolean … String,
#: NodeId, LocalizedText; not abstract ones nor structures, enumerations)
BUILTIN = {str(i) for i in (*range(1, 13), 17, 21)}
SIM_GROUP = 0x12F300  # the emulator's objects (docs/design.md §2.5)


class NodeSet:
    """The parts of NodeSet2 files this test needs, read with ElementTree: nodes keyed
    by `<namespace URI>|<id>` across the files."""

    def __init__(self, *paths: Path) -> None:
        #: key -> (its element, its file's namespace URIs and aliases)
        self.nodes: dict[str, tuple[Any, list[str], dict[str, str]]] = {}
        for path in paths:
            root = ET.parse(path).getroot()
            uris = [UA] + [u.text or "" for u in root.find("u:NamespaceUris", XML_NS) or []]
            aliases = {
                a.get("Alias") or "": a.text or "" for a in root.find("u:Aliases", XML_NS) or []
            }
            for el in root:
                if el.get("NodeId"):
                    self.nodes[self.key(el.get("NodeId"), uris, aliases)] = (el, uris, aliases)
        self.types = {
            self.name(k): k
            for k, (el, _, _) in self.nodes.items()
            if el.tag.endswith("}UAObjectType")
        }

    @staticmethod
    def key(nid: str, uris: list[str], aliases: dict[str, str]) -> str:
        """`<namespace URI>|<id>` of "ns=1;i=1004", "i=68" or an alias ("HasComponent")."""
        nid = aliases.get(nid, nid)
        index, ident = nid.split(";", 1) if nid.startswith("ns=") else ("ns=0", nid)
        return f"{uris[int(index[3:])]}|{ident.removeprefix('i=')}"

    def refs(self, key: str) -> list[tuple[str, bool, str]]:
        el, uris, aliases = self.nodes[key]
        found = el.find("u:References", XML_NS)
        return [
            (
                self.key(r.get("ReferenceType") or "", uris, aliases),
                r.get("IsForward") != "false",
                self.key(r.text or "", uris, aliases),
            )
            for r in (found if found is not None else [])
        ]

    def name(self, key: str) -> tuple[str, str]:
        """(namespace URI, name) of a node's BrowseName ("1:ActPos")."""
        el, uris, _ = self.nodes[key]
        text = el.get("BrowseName")
        index, _, name = text.partition(":") if ":" in text else ("0", "", text)
        return uris[int(index)], name

    def typedef(self, key: str) -> str:
        return next(t for r, fwd, t in self.refs(key) if r == HAS_TYPE and fwd)

    def _declared(self, key: str) -> dict[tuple[str, str], str]:
        """The mandatory children a node declares itself."""
        out = {}
        for ref, forward, target in self.refs(key):
            if forward and ref in HIERARCHICAL and target in self.nodes:
                rules = [t for r, _, t in self.refs(target) if r == HAS_RULE]
                if MANDATORY in rules:
                    out[self.name(target)] = target
        return out

    def _members(self, type_key: str) -> dict[tuple[str, str], str]:
        """The mandatory children of a type, its supertypes' included (a subtype's
        declaration of a name replaces its supertype's)."""
        chain = []
        key: str | None = type_key
        while key is not None and key in self.nodes:
            chain.append(key)
            up = [t for r, fwd, t in self.refs(key) if r == HAS_SUBTYPE and not fwd]
            key = up[0] if up else None
        out: dict[tuple[str, str], str] = {}
        for key in reversed(chain):
            out.update(self._declared(key))
        return out

    def mandatory(
        self, type_name: str, uri: str = CNC
    ) -> list[tuple[list[tuple[str, str]], str, str]]:
        """Every mandatory node below an instance of the type: (browse path, its
        TypeDefinition, its node class), from the type's declarations and, below each,
        from the declaration's own children and its type's."""
        out: list[tuple[list[tuple[str, str]], str, str]] = []

        def walk(children: dict[tuple[str, str], str], path: list[tuple[str, str]]) -> None:
            for name, decl in children.items():
                typed = self.typedef(decl)
                el, uris, aliases = self.nodes[decl]
                datatype = self.key(el.get("DataType"), uris, aliases) if el.get("DataType") else ""
                kind = (el.tag.split("}")[1], datatype, int(el.get("ValueRank", "-1")))
                out.append(([*path, name], typed, kind))
                if len(path) < 12:
                    walk({**self._members(typed), **self._declared(decl)}, [*path, name])

        walk(self._members(self.types[(uri, type_name)]), [])
        return out


@pytest.fixture(scope="module")
def nodeset() -> NodeSet:
    return NodeSet(cnc.NODESET, *(path for _, path in machinetool.NODESETS))


def test_the_nodesets_are_the_published_ones() -> None:
    files = [cnc.NODESET, *(path for _, path in machinetool.NODESETS)]
    sums = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in files}
    assert sums == PUBLISHED_SHA256


def test_the_mandatory_declarations_read_from_the_xml(nodeset: NodeSet) -> None:
    """The reading of the XML above finds what OPC 40502's tables list (a few by hand:
    CncAxisType's own and inherited from CncDriveType; CncPositionVariableType's)."""
    axis = {tuple(n for _, n in p): t for p, t, _ in nodeset.mandatory("CncAxisType")}
    assert axis[("PosDirect", "ActPos")] == f"{UA}|63"  # BaseDataVariableType
    assert axis[("PosIndirect",)] == f"{CNC}|2001"  # CncPositionVariableType
    assert axis[("IsReferenced",)] == f"{UA}|2365"  # DataItemType
    assert axis[("ActTorque",)] == f"{UA}|2368"  # AnalogItemType, from CncDriveType
    assert len(axis) > 30
    channel = {tuple(n for _, n in p) for p, _, _ in nodeset.mandatory("CncChannelType")}
    assert ("PosTcpBcsX", "RemDist") in channel and ("ActProgramStatus",) in channel
    found = nodeset.mandatory("MachineToolType", MACHINE_TOOL)
    tool = {tuple(n for _, n in p): t for p, t, _ in found}
    assert tool[("Identification",)] == f"{MACHINE_TOOL}|11"  # MachineToolIdentificationType
    assert tool[("Production", "ActiveProgram", "State", "CurrentState")] == f"{UA}|2760"
    assert ("Identification", "SerialNumber") in tool  # (from Machinery's type, via HasAddIn)


@pytest.mark.realtime
@pytest.mark.slow
@pytest.mark.skipif(
    not REQUIRED and (NODE is None or not INSTALLED),
    reason="node or tests/node/node_modules/node-opcua-client missing (npm ci --prefix tests/node)",
)
def test_every_mandatory_node_is_there_for_node_opcua(
    loop_thread: asyncio.AbstractEventLoop,
    service: ObjectService,
    nodeset: NodeSet,
    tmp_path: Path,
) -> None:
    assert NODE is not None and INSTALLED, "GEO_SERVER_REQUIRE_NODE=1 but no node-opcua-client"
    top = [(CNC, cnc.INTERFACE)]
    wanted: list[tuple[list[tuple[str, str]], str, str]] = [
        (top, f"{CNC}|{cnc.INTERFACE_TYPE}", OBJECT),
        ([(GEO_NS, "local"), (CNC, cnc.INTERFACE)], f"{CNC}|{cnc.INTERFACE_TYPE}", OBJECT),
    ]
    wanted += [(top + p, t, c) for p, t, c in nodeset.mandatory("CncInterfaceType")]
    instances = [((CNC, cnc.AXIS_LIST), (GEO_NS, a), "CncAxisType") for a in "XYZC"]
    instances.append(((CNC, cnc.CHANNEL_LIST), (GEO_NS, cnc.CHANNEL), "CncChannelType"))
    for folder, name, type_name in instances:
        here = [*top, folder, name]
        wanted.append((here, nodeset.types[(CNC, type_name)], OBJECT))
        wanted += [(here + p, t, c) for p, t, c in nodeset.mandatory(type_name)]
    tool = [(MACHINERY, "Machines"), (GEO_NS, "local")]
    wanted.append((tool, nodeset.types[(MACHINE_TOOL, "MachineToolType")], OBJECT))
    wanted += [(tool + p, t, c) for p, t, c in nodeset.mandatory("MachineToolType", MACHINE_TOOL)]
    paths = tmp_path / "paths.json"
    paths.write_text(json.dumps([p for p, _, _ in wanted]), encoding="utf-8")

    iface = OpcUaInterface({"local": service}, OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0"))
    run_in(loop_thread, iface.start(), timeout=60)
    try:
        r = subprocess.run(
            [NODE, str(NODE_DIR / "opcua_companion_check.js"), iface.endpoint, str(paths)],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=NODE_DIR,
        )
    finally:
        run_in(loop_thread, iface.close())
    assert r.returncode == 0, r.stderr
    result = [line for line in r.stdout.splitlines() if line.startswith("RESULT ")]
    assert result, r.stdout + r.stderr
    seen = json.loads(result[-1].removeprefix("RESULT "))
    assert len(seen) == len(wanted) > 150
    problems = []
    for (path, type_id, (node_class, datatype, rank)), got in zip(wanted, seen, strict=True):
        where = "/".join(n for _, n in path)
        if not got["found"]:
            problems.append(f"{where}: missing")
            continue
        if got["type"] != type_id:
            problems.append(f"{where}: type {got['type']}, not {type_id}")
        if node_class != "UAVariable":
            continue
        if got.get("status") != "Good" or not got.get("hasValue"):
            problems.append(f"{where}: value {got.get('status')} {got.get('hasValue')}")
        if datatype and got["dataType"] != datatype:
            problems.append(f"{where}: DataType {got['dataType']}, not {datatype}")
        if got["isArray"] != (rank >= 1):
            problems.append(f"{where}: an array {got['isArray']}, ValueRank {rank}")
        builtin = datatype.startswith(f"{UA}|") and datatype.split("|")[1] in BUILTIN
        if builtin and got["variantType"] != int(datatype.split("|")[1]):
            problems.append(f"{where}: a value of type {got['variantType']}, not {datatype}")
    assert problems == []


@pytest.fixture
def plc(loop_thread: asyncio.AbstractEventLoop, service: ObjectService) -> Iterator[Any]:
    srv = start_server(loop_thread, service)
    conn = pyads.Connection(next_netid(), 551, srv.address)
    conn.open()
    conn.set_timeout(int(TIMEOUT * 1000))
    yield conn
    close_port_first(conn)
    run_in(loop_thread, srv.close())


@pytest.mark.slow
def test_the_axis_values_are_the_ads_values_of_the_same_cycle(
    loop_thread: asyncio.AbstractEventLoop, service: ObjectService, plc: Any
) -> None:
    """X moves towards 10 mm; after 40 cycles (stepped: nothing runs between the reads)
    each CNC value is its ADS object's in mm (the simulation's objects, index group
    0x12F300, offsets (axis << 16) | ID: command position 0x01, target 0x02, velocity
    0x03, output 0x06, drive actual 0x0F)."""
    access.write_name(service, "SIM::target_position", 1, 100_000)
    access.step(service, 40)

    def ads(ident: int) -> int:
        return int(plc.read(SIM_GROUP, (1 << 16) | ident, pyads.PLCTYPE_DINT))

    command, target, velocity = ads(0x01), ads(0x02), ads(0x03)
    output, drive = ads(0x06), ads(0x0F)
    assert 0 < command < target == 100_000 and velocity != 0

    iface = OpcUaInterface({"local": service}, OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0"))
    run_in(loop_thread, iface.start(), timeout=60)

    async def read() -> dict[str, Any]:
        async with Client(iface.endpoint, timeout=10) as c:
            ns = await c.get_namespace_index(GEO_NS)
            x = f"local/{cnc.INTERFACE}.{cnc.AXIS_LIST}.X"
            names = [
                "PosDirect.CmdPos",
                "PosDirect.RemDist",
                "PosIndirect.CmdPos",
                "PosIndirect.ActPos",
                "ActStatus",
                "IsReferenced",
                "IsRotational",
            ]
            nodes = [c.get_node(ua.NodeId(f"{x}.{n}", ns)) for n in names]
            values = [dv.Value.Value for dv in await c.read_attributes(nodes)]
            rotary = c.get_node(
                ua.NodeId(f"local/{cnc.INTERFACE}.{cnc.AXIS_LIST}.C.IsRotational", ns)
            )
            tool = "local/MachineTool"
            serial = c.get_node(ua.NodeId(f"{tool}.Identification.SerialNumber", ns))
            state = c.get_node(ua.NodeId(f"{tool}.Production.ActiveProgram.State.CurrentState", ns))
            return {
                **dict(zip(names, values, strict=True)),
                "C": await rotary.read_value(),
                "serial": await serial.read_value(),
                "state": (await state.read_value()).Text,
            }

    try:
        got = asyncio.run(read())
    finally:
        run_in(loop_thread, iface.close())
    assert got["PosDirect.CmdPos"] == command / 10_000
    assert got["PosDirect.RemDist"] == (target - command) / 10_000
    assert got["PosIndirect.CmdPos"] == output / 10_000
    assert got["PosIndirect.ActPos"] == drive / 10_000
    assert got["ActStatus"] == 1  # Moving
    assert (got["IsReferenced"], got["IsRotational"], got["C"]) == (True, False, True)
    # the Machine Tool model: the machine's name is its serial number; no NC program runs
    assert (got["serial"], got["state"]) == ("local", "Ended")


@pytest.mark.slow
def test_the_models_are_read_only_and_each_machine_has_its_own(default_cfg: Any) -> None:
    """Two machines of one shape (the second's nodes are a copy of the first's): a
    write of a model's constant is refused (Bad_NotWritable; with --opcua-read-only
    Bad_UserAccessDenied) and changes nothing; each machine has its own serial number
    and channel; a position variable is the CncPositionDataType of its three parts."""
    from geo_server.machine.machine import Machine

    services = {
        name: ObjectService(Machine(default_cfg, cycle_s=0.001, homed=True))
        for name in ("mill", "lathe")
    }
    access.write_name(services["lathe"], "SIM::target_position", 1, 100_000)
    access.step(services["lathe"], 30)

    async def scenario(read_only: bool) -> dict[str, Any]:
        options = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", read_only=read_only)
        iface = OpcUaInterface(services, options)
        await iface.start()
        try:
            async with Client(iface.endpoint, timeout=10) as c:
                ns = await c.get_namespace_index(GEO_NS)

                def node(path: str) -> Any:
                    return c.get_node(ua.NodeId(path, ns))

                override = "lathe/CncInterface.CncChannelList.Channel1.CmdOverride"
                write = ua.WriteValue(
                    NodeId=ua.NodeId(override, ns),
                    AttributeId=ua.AttributeIds.Value,
                    Value=ua.DataValue(ua.Variant(55.5, ua.VariantType.Double)),
                )
                (status,) = await c.uaclient.write(ua.WriteParameters(NodesToWrite=[write]))
                x = "lathe/CncInterface.CncAxisList.X"
                level = await node(f"{x}.PosDirect.ActPos").get_user_access_level()
                return {
                    "status": status.name,
                    "override": await node(override.replace("lathe", "mill")).read_value(),
                    "writable": ua.AccessLevel.CurrentWrite in level,
                    "serials": [
                        await node(f"{m}/MachineTool.Identification.SerialNumber").read_value()
                        for m in services
                    ],
                    "channel": await node(f"{x}.ActChannel").read_value(),
                    "position": await node(f"{x}.PosDirect").read_value(),
                    "parts": [
                        await node(f"{x}.PosDirect.{p}").read_value()
                        for p in ("ActPos", "CmdPos", "RemDist")
                    ],
                }
        finally:
            await iface.close()

    got = asyncio.run(scenario(read_only=False))
    assert got["status"] == "BadNotWritable"
    assert (got["override"], got["writable"]) == (100.0, False)
    assert got["serials"] == ["mill", "lathe"]
    assert got["channel"].Identifier == "lathe/CncInterface.CncChannelList.Channel1"
    position = got["position"]
    assert [position.ActPos, position.CmdPos, position.RemDist] == got["parts"]
    command = round(got["parts"][1] * 10_000)  # (increments)
    assert 0 < command < 100_000 and got["parts"][2] == (100_000 - command) / 10_000
    assert asyncio.run(scenario(read_only=True))["status"] == "BadUserAccessDenied"


@pytest.mark.slow
def test_a_fleets_copies_are_made_on_first_use_and_reached_every_way(default_cfg: Any) -> None:
    """Three machines of one shape: the second's and third's nodes are not made at the
    start (issue 46 #7: a fleet of 500 spent 15 s copying them), yet a client finds
    every machine under Objects and in the Machinery Machines folder, reaches the
    third's coefficient by browse names (TranslateBrowsePaths) and reads 4000.0, and
    finds the second's object with the same children as the first's. (`make_all` off:
    nothing made in the background meanwhile; with it, below, all are made.)"""
    from geo_server.machine.machine import Machine

    names = ("m1", "m2", "m3")
    services = {n: ObjectService(Machine(default_cfg, cycle_s=0.001, homed=True)) for n in names}

    async def scenario() -> dict[str, Any]:
        options = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", make_all=False)
        iface = OpcUaInterface(services, options)
        await iface.start()
        nodes = iface.server.iserver.aspace._nodes  # (asyncua's own dict: what is made)

        def made(name: str) -> bool:
            return dict.__contains__(nodes, ua.NodeId(f"{name}/Axes/X/TEMPC/coefficient", iface.ns))

        try:
            before = [made(n) for n in names]
            async with Client(iface.endpoint, timeout=10) as c:
                ns = await c.get_namespace_index(GEO_NS)
                machinery = await c.get_namespace_index(MACHINERY)
                objects = [q.Name for q in await _browse_names(c.nodes.objects)]
                folder = await c.nodes.objects.get_child(f"{machinery}:Machines")
                tools = [q.Name for q in await _browse_names(folder)]
                path = [f"{ns}:{part}" for part in ("m3", "Axes", "X", "TEMPC", "coefficient")]
                value = await (await c.nodes.objects.get_child(path)).read_value()
                first, second = (c.get_node(ua.NodeId(n, ns)) for n in ("m1", "m2"))
                children = [
                    sorted(q.Name for q in await _browse_names(node)) for node in (first, second)
                ]
            return {
                "before": before,
                "after": [made(n) for n in names],
                "objects": objects,
                "tools": tools,
                "value": value,
                "children": children,
            }
        finally:
            await iface.close()

    got = asyncio.run(scenario())
    assert got["before"] == [True, False, False]
    assert set(names) <= set(got["objects"]) and set(names) <= set(got["tools"])
    assert got["value"] == 4000.0
    assert got["children"][0] == got["children"][1] and "Axes" in got["children"][0]
    assert got["after"] == [True, True, True]


@pytest.mark.slow
def test_once_serving_a_fleets_copies_are_made_in_the_background(default_cfg: Any) -> None:
    """With `make_all` (the default) the machines no request touched are made once the
    server serves, each readable; a request across the fleet then makes none itself."""
    from geo_server.machine.machine import Machine

    names = ("m1", "m2", "m3", "m4")
    services = {n: ObjectService(Machine(default_cfg, cycle_s=0.001, homed=True)) for n in names}

    async def scenario() -> list[Any]:
        iface = OpcUaInterface(services, OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0"))
        await iface.start()
        nodes = iface.server.iserver.aspace._nodes

        def all_made() -> bool:
            return all(
                dict.__contains__(nodes, ua.NodeId(f"{n}/Axes/X/TEMPC/coefficient", iface.ns))
                for n in names
            )

        try:
            for _ in range(1000):  # (a few machines: a fraction of a second)
                if all_made():
                    break
                await asyncio.sleep(0.01)
            assert all_made()
            async with Client(iface.endpoint, timeout=10) as c:
                ns = await c.get_namespace_index(GEO_NS)
                ids = [ua.NodeId(f"{n}/Axes/X/TEMPC/coefficient", ns) for n in names]
                return [await c.get_node(i).read_value() for i in ids]
        finally:
            await iface.close()

    assert asyncio.run(scenario()) == [4000.0] * 4


async def _browse_names(node: Any) -> list[Any]:
    return [await child.read_browse_name() for child in await node.get_children()]


@pytest.mark.slow
def test_the_machines_messages_are_events_of_its_machine_tool(service: ObjectService) -> None:
    """OPC 40501 Notification/Messages: a warning or error of the machine's list is a
    NotificationEventType event there, with its text, a Severity (error 700, warning 400)
    and the manual's error ID as Identifier."""

    class Events:
        def __init__(self) -> None:
            self.got: list[Any] = []
            self.arrived = asyncio.Event()

        def event_notification(self, event: Any) -> None:
            self.got.append(event)
            self.arrived.set()

    async def scenario() -> list[Any]:
        iface = OpcUaInterface({"local": service}, OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0"))
        await iface.start()
        try:
            async with Client(iface.endpoint, timeout=10) as c:
                ns = await c.get_namespace_index(GEO_NS)
                mt = await c.get_namespace_index(MACHINE_TOOL)
                messages = c.get_node(ua.NodeId("local/MachineTool.Notification.Messages", ns))
                handler = Events()
                sub = await c.create_subscription(10, handler)
                await sub.subscribe_events(messages, c.get_node(ua.NodeId(35, mt)))
                service.report("cooling water low", severity="warning", error_id=990123)
                access.step(service, 1)
                while not handler.got:
                    handler.arrived.clear()
                    await handler.arrived.wait()
                return handler.got
        finally:
            await iface.close()

    # (the start loads five NodeSets: seconds of CPU, more on a loaded runner)
    (event,) = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert event.Message.Text == "cooling water low"
    assert (event.Severity, event.Identifier, event.SourceName) == (400, "990123", "local")


def test_a_stop_during_the_models_import_does_not_wait_for_it(
    service: ObjectService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGTERM while the companion models load (seconds, tens of them on a loaded host:
    a fleet's CI teardown waited past 10 s, stress check): the server closes and its
    loop ends without waiting for the import, which goes on alone, in a daemon thread
    that the process's exit ends. Here the import blocks until the test lets it go."""
    import threading

    from geo_server.transports.opcua import companions

    importing, release = threading.Event(), threading.Event()

    async def blocked_import(server: Any, closing: Any) -> None:
        importing.set()
        release.wait()  # (in the import's own thread; the test releases it at the end)

    monkeypatch.setattr(companions, "add", blocked_import)
    opts = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", companion_models=True, background=True)

    async def start_and_close() -> None:
        iface = OpcUaInterface({"local": service}, opts)
        await iface.start()
        await asyncio.to_thread(importing.wait, 30)
        assert importing.is_set() and iface.starting is not None
        assert not iface.starting.done()  # (still importing: the stop comes now)
        await iface.close()

    # the loop's run ends (asyncio.run waits for its default executor's workers): a
    # thread of the test runs it, so that the old wait would not hang the test
    ended = threading.Event()
    runner = threading.Thread(
        target=lambda: (asyncio.run(start_and_close()), ended.set()), daemon=True
    )
    runner.start()
    try:
        runner.join(30)  # (the test's patience; the close does not wait for the import)
        assert ended.is_set(), "the loop waited for the companion models' import"
    finally:
        release.set()
        runner.join(30)


#: a fresh process's address space after `companions.add`: its digest (every node's
#: references and attributes, times left out: two processes start at other times) and
#: whether asyncua's XML import ran
SPACE = """
import asyncio, hashlib, json, re
from asyncua import Server, ua
from geo_server.transports.opcua import companions
from geo_server.transports.opcua.server import NAMESPACE_URI

imported = []
TIME = r"datetime\\.datetime\\([^)]*\\)"


async def main():
    server = Server()
    await server.init()
    await server.register_namespace(NAMESPACE_URI)
    real = server.import_xml

    async def import_xml(*args, **kwargs):
        imported.append(args[0])
        return await real(*args, **kwargs)

    server.import_xml = import_xml
    await companions.add(server, lambda: False)
    nodes = server.iserver.aspace._nodes
    h = hashlib.sha256()
    for nodeid in sorted(nodes, key=repr):
        values = sorted(
            (int(a), repr(v.value and v.value.Value), repr(v.value and v.value.StatusCode))
            for a, v in nodes[nodeid].attributes.items()
        )
        refs = sorted(repr(r) for r in nodes[nodeid].references)
        h.update(re.sub(TIME, "T", repr((nodeid, values, refs))).encode())
    made = nodes[ua.NodeId(2001, 3)].attributes[ua.AttributeIds.Value].value.Value.Value
    print(json.dumps({
        "digest": h.hexdigest(), "nodes": len(nodes), "imported": len(imported),
        "made": type(made).__name__,
    }))


asyncio.run(main())
"""


@pytest.mark.slow
def test_the_nodeset_cache_restores_what_asyncuas_import_makes(tmp_path: Path) -> None:
    """Issue 46 #7: the companion models' import (3-6 s of a start) is restored from a
    cache. Each in a fresh process: asyncua's import of the five NodeSets writes the
    cache; the next start reads it and imports nothing, and its address space is the
    import's node by node (references, attributes, values; the CNC model's structure
    values of the class asyncua makes). A cache cut short is imported again and
    rewritten."""
    env = os.environ | {"GEO_SERVER_JIT_CACHE": str(tmp_path / "cache")}

    def space() -> dict[str, Any]:
        r = subprocess.run(
            [sys.executable, "-c", SPACE], env=env, capture_output=True, text=True, timeout=120
        )
        assert r.returncode == 0, r.stderr
        return dict(json.loads(r.stdout.splitlines()[-1]))

    imported = space()
    assert imported["imported"] == 5 and imported["made"] == "CncPositionDataType"
    (cached,) = (tmp_path / "cache" / "opcua-nodesets").glob("companions-*.pickle")
    restored = space()
    assert restored == imported | {"imported": 0}
    size = cached.stat().st_size
    cached.write_bytes(cached.read_bytes()[: size // 2])
    assert space() == imported
    assert cached.stat().st_size == size


@pytest.mark.slow
def test_a_warmed_cache_is_the_one_a_server_restores(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, service: ObjectService
) -> None:
    """An image fills the cache when it is built (`companions.warm`, Containerfile): a
    server started afterwards restores from it and imports no NodeSet."""
    cache = tmp_path / "cache"
    warm = "import asyncio; from geo_server.transports.opcua import companions as c; "
    warm += "asyncio.run(c.warm())"
    env = os.environ | {"GEO_SERVER_JIT_CACHE": str(cache)}
    r = subprocess.run([sys.executable, "-c", warm], env=env, capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr
    (cached,) = (cache / "opcua-nodesets").glob("companions-*.pickle")
    monkeypatch.setenv("GEO_SERVER_JIT_CACHE", str(cache))
    from asyncua import Server

    async def refused(*args: Any, **kwargs: Any) -> None:
        raise AssertionError(f"imported {args}")

    monkeypatch.setattr(Server, "import_xml", refused)

    async def scenario() -> str:
        iface = OpcUaInterface({"local": service}, OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0"))
        await iface.start()
        try:
            async with Client(iface.endpoint, timeout=10) as c:
                axis_type = ua.NodeId(1004, await c.get_namespace_index(CNC))
                return str((await c.get_node(axis_type).read_browse_name()).Name)
        finally:
            await iface.close()

    assert asyncio.run(asyncio.wait_for(scenario(), 60)) == "CncAxisType"  # (the XML's)
    assert list((cache / "opcua-nodesets").glob("companions-*.pickle")) == [cached]


def _fresh_space() -> Any:
    """asyncua's standard address space with geo-server's namespaces, as a server has
    it before the companion models (`OpcUaInterface._init_and_build`)."""
    from asyncua import Server

    from geo_server.transports.opcua.space import APPLICATION_URI, NAMESPACE_URI

    async def made() -> Any:
        server = Server()
        await server.init()
        await server.set_application_uri(APPLICATION_URI)
        await server.register_namespace(NAMESPACE_URI)
        return server

    return asyncio.run(made())


def test_a_nodeset_cache_others_can_write_is_never_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The cache is a pickle: one planted where another user can write would run its
    code as the server's user. Planted at the very name the server would read, in a
    cache folder writable by others, it is not read: the NodeSets are imported."""
    import pickle

    from geo_server.transports.opcua import companions

    server = _fresh_space()
    uris = list(asyncio.run(server.get_namespace_array()))
    monkeypatch.setenv("GEO_SERVER_JIT_CACHE", str(tmp_path / "safe"))
    name = companions._cache_path(uris).name  # type: ignore[union-attr]
    marker = tmp_path / "ran"

    class Planted:
        def __reduce__(self) -> Any:
            return (os.system, (f"touch {marker}",))

    unsafe = tmp_path / "unsafe"
    (unsafe / "opcua-nodesets").mkdir(parents=True)
    (unsafe / "opcua-nodesets" / name).write_bytes(pickle.dumps(Planted()))
    unsafe.chmod(0o777)
    monkeypatch.setenv("GEO_SERVER_JIT_CACHE", str(unsafe))
    assert companions._cache_path(uris) is None
    asyncio.run(companions.add(server, lambda: False))
    assert not marker.exists()
    assert asyncio.run(server.get_namespace_index(CNC)) == 3  # (imported)


def test_a_restore_that_fails_takes_the_cache_away(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A cache read whole whose restore then fails (a class asyncua could not make) has
    changed the address space half: that start fails, and the cache is removed so the
    next start imports instead of failing the same way."""
    from geo_server.transports.opcua import companions

    monkeypatch.setenv("GEO_SERVER_JIT_CACHE", str(tmp_path / "cache"))
    server = _fresh_space()
    path = companions._cache_path(list(asyncio.run(server.get_namespace_array())))
    assert path is not None
    path.write_bytes(b"x")
    monkeypatch.setattr(companions, "_read", lambda p: companions._Added([], {}, {}, []))

    async def broken(server: Any, added: Any) -> None:
        raise AttributeError("CncPositionDataType")

    monkeypatch.setattr(companions, "_restore", broken)
    with pytest.raises(AttributeError):
        asyncio.run(companions.add(server, lambda: False))
    assert not path.exists()


def test_a_cache_of_another_address_space_is_not_restored() -> None:
    """`_fits`: nodes it would add that are there already, or older nodes whose
    references are not as they were before the import, mean another address space."""
    from geo_server.transports.opcua.companions import _Added, _fits

    class Node:
        def __init__(self, refs: int) -> None:
            self.references = [object()] * refs

    nodes = {"a": Node(2)}
    assert _fits(nodes, _Added([], {"b": Node(0)}, {"a": (2, [])}, []))
    assert not _fits(nodes, _Added([], {"a": Node(0)}, {}, []))  # (there already)
    assert not _fits(nodes, _Added([], {}, {"a": (3, [])}, []))  # (other references)
    assert not _fits(nodes, _Added([], {}, {"c": (0, [])}, []))  # (no such node)
