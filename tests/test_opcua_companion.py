"""OPC 40502 "CNC Systems", checked against the OPC Foundation's own definition.

- The NodeSet the server loads is the one the OPC Foundation publishes (its SHA-256, UA-Nodeset
  `CNC/Opc.Ua.CNC.NodeSet.xml`, CNC 1.00 of 2017-06-19).
- This test reads that XML itself (not through the server's code), lists every mandatory
  instance declaration of `CncInterfaceType`, `CncAxisType` and `CncChannelType` (with
  their supertypes'), and has node-opcua's client (another stack, nobody here wrote it)
  find each on the running server by its browse path, with the declared type and, for a
  variable, a Good value.
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
from geo_server.transports.opcua import cnc
from geo_server.transports.opcua.server import OpcUaInterface, OpcUaOptions

NODE_DIR = Path(__file__).parent / "node"
NODE = shutil.which("node")
INSTALLED = (NODE_DIR / "node_modules" / "node-opcua-client").is_dir()
REQUIRED = os.environ.get("GEO_SERVER_REQUIRE_NODE") == "1"
#: the published file's SHA-256 (OPCFoundation/UA-Nodeset, CNC/Opc.Ua.CNC.NodeSet.xml)
PUBLISHED_SHA256 = "c81eb71541f5846c126b913bc00e768fd04c39e1edb0a0c92e9d1552bfa1d9d6"
UA = "http://opcfoundation.org/UA/"
CNC = "http://opcfoundation.org/UA/CNC"
GEO_NS = "urn:geo-server:cnc"
XML_NS = {"u": "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"}
MANDATORY, HAS_SUBTYPE, HAS_TYPE, HAS_RULE = "i=78", "i=45", "i=40", "i=37"
HIERARCHICAL = {"i=46", "i=47"}  # HasProperty, HasComponent
SIM_GROUP = 0x12F300  # the emulator's objects (docs/design.md §2.5)


class NodeSet:
    """The parts of a NodeSet2 file this test needs, read with ElementTree."""

    def __init__(self, path: Path) -> None:
        root = ET.parse(path).getroot()
        self.uris = [UA] + [u.text or "" for u in root.find("u:NamespaceUris", XML_NS) or []]
        self.aliases = {a.get("Alias"): a.text for a in root.find("u:Aliases", XML_NS) or []}
        self.nodes = {el.get("NodeId"): el for el in root if el.get("NodeId")}
        self.types = {
            self.name(el)[1]: nid
            for nid, el in self.nodes.items()
            if el.tag.endswith("}UAObjectType")
        }

    def refs(self, nid: str) -> list[tuple[str, bool, str]]:
        found = self.nodes[nid].find("u:References", XML_NS)
        out = []
        for ref in found if found is not None else []:
            kind = ref.get("ReferenceType") or ""
            out.append((self.aliases.get(kind, kind), ref.get("IsForward") != "false", ref.text))
        return out

    def name(self, el: Any) -> tuple[str, str]:
        """(namespace URI, name) of a node's BrowseName ("1:ActPos")."""
        text = el.get("BrowseName")
        index, _, name = text.partition(":") if ":" in text else ("0", "", text)
        return self.uris[int(index)], name

    def uri_id(self, nid: str) -> str:
        """`<namespace URI>|<numeric id>` of "ns=1;i=1004" or "i=68"."""
        nid = self.aliases.get(nid, nid)
        index = int(nid.split(";")[0][3:]) if nid.startswith("ns=") else 0
        return f"{self.uris[index]}|{nid.rsplit('i=', 1)[1]}"

    def mandatory(self, type_name: str) -> list[tuple[list[tuple[str, str]], str, str]]:
        """Every mandatory instance declaration below an instance of `type_name` (its
        supertypes' too): (browse path, its TypeDefinition, its node class)."""
        out: list[tuple[list[tuple[str, str]], str, str]] = []
        nid: str | None = self.types[type_name]
        while nid is not None and nid in self.nodes:
            self._walk(nid, [], out)
            up = [t for r, fwd, t in self.refs(nid) if r == HAS_SUBTYPE and not fwd]
            nid = up[0] if up else None
        return out

    def _walk(self, nid: str, path: list[tuple[str, str]], out: list[Any]) -> None:
        for ref, forward, target in self.refs(nid):
            if not forward or ref not in HIERARCHICAL or target not in self.nodes:
                continue
            child = self.refs(target)
            if not any(r == HAS_RULE and t == MANDATORY for r, _, t in child):
                continue
            typed = [t for r, _, t in child if r == HAS_TYPE]
            el = self.nodes[target]
            step = [*path, self.name(el)]
            out.append((step, self.uri_id(typed[0]), el.tag.split("}")[1]))
            self._walk(target, step, out)


@pytest.fixture(scope="module")
def nodeset() -> NodeSet:
    return NodeSet(cnc.NODESET)


def test_the_nodeset_is_the_published_one() -> None:
    assert hashlib.sha256(cnc.NODESET.read_bytes()).hexdigest() == PUBLISHED_SHA256


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
        (top, f"{CNC}|{cnc.INTERFACE_TYPE}", "UAObject"),
        ([(GEO_NS, "local"), (CNC, cnc.INTERFACE)], f"{CNC}|{cnc.INTERFACE_TYPE}", "UAObject"),
    ]
    wanted += [(top + p, t, c) for p, t, c in nodeset.mandatory("CncInterfaceType")]
    instances = [((CNC, cnc.AXIS_LIST), (GEO_NS, a), "CncAxisType") for a in "XYZC"]
    instances.append(((CNC, cnc.CHANNEL_LIST), (GEO_NS, cnc.CHANNEL), "CncChannelType"))
    for folder, name, type_name in instances:
        here = [*top, folder, name]
        wanted.append((here, f"{CNC}|{nodeset.types[type_name].rsplit('=', 1)[1]}", "UAObject"))
        wanted += [(here + p, t, c) for p, t, c in nodeset.mandatory(type_name)]
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
    for (path, type_id, node_class), got in zip(wanted, seen, strict=True):
        where = "/".join(n for _, n in path)
        if not got["found"]:
            problems.append(f"{where}: missing")
            continue
        if got["type"] != type_id:
            problems.append(f"{where}: type {got['type']}, not {type_id}")
        if node_class == "UAVariable" and (got.get("status") != "Good" or not got.get("hasValue")):
            problems.append(f"{where}: value {got.get('status')} {got.get('hasValue')}")
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
            return {**dict(zip(names, values, strict=True)), "C": await rotary.read_value()}

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
