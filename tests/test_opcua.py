"""The OPC UA interface (README *OPC UA*) with a client nobody here wrote: asyncua's.

Each test runs a server and its clients on one event loop, on 127.0.0.1 with an
ephemeral port, against the default machine in stepped mode: nothing runs until a test
steps it, so every notification and write is tied to a cycle, not to time.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto import cert_gen
from asyncua.ua.uaerrors import UaStatusCodeError
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from geo_server import access
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService
from geo_server.transports.opcua import guard, logins
from geo_server.transports.opcua.certs import CERT_FILE, KEY_FILE
from geo_server.transports.opcua.plug import cert_folder
from geo_server.transports.opcua.server import (
    STATUS,
    OpcUaInterface,
    OpcUaOptions,
    source_time,
)
from geo_server.transports.opcua.space import METHODS, NAMESPACE_URI, machine_variables

TIMEOUT = 30.0
#: a start with the companion models: five NodeSets loaded (about 3 s of CPU, three
#: times that next to two busy processes), on top of a scenario's TIMEOUT
MODELS_START_S = 60.0


def run(scenario: Callable[[], Awaitable[None]], limit: float = TIMEOUT) -> None:
    async def bounded() -> None:
        await asyncio.wait_for(scenario(), limit)

    asyncio.run(bounded())


def options(**kw: Any) -> OpcUaOptions:
    """Options on an ephemeral port; without the companion models unless asked (their
    NodeSets take about 3 s to load, and these tests are about the rest; the models
    are tested in tests/test_opcua_companion.py and by the fleet test here)."""
    return OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", **{"companion_models": False, **kw})


async def started(services: dict[str, ObjectService], opts: OpcUaOptions) -> OpcUaInterface:
    iface = OpcUaInterface(services, opts)
    await iface.start()
    return iface


def client(iface: OpcUaInterface, **kw: Any) -> Client:
    c = Client(iface.endpoint, timeout=10)
    if "user" in kw:
        c.set_user(kw["user"])
        c.set_password(kw["password"])
    return c


def node_of(c: Client, ns: int, path: str) -> Any:
    return c.get_node(ua.NodeId(path, ns))


# ---------------------------------------------------------------------- address space


@pytest.mark.slow
def test_browse_every_variable_with_its_attributes(service: ObjectService) -> None:
    """Browsing Objects/local finds every object of every axis (the ADS symbol names),
    each with its type, access, unit, range, description, ADS address and value."""
    names = {int(a): n for a, n in service.status()["axis_names"].items()}
    kind = service.info.dictionary.by_name("SIM::axis_type")
    kinds = {a: int(service.current().value(kind, a)) for a in names}
    specs = {
        s.node_id: s for s in machine_variables("local", service.info.dictionary, names, kinds)
    }

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                root = await c.nodes.objects.get_child(f"{ns}:local")
                found: dict[str, Any] = {}

                async def walk(node: Any) -> None:
                    for child in await node.get_children():
                        cls = await child.read_node_class()
                        if cls == ua.NodeClass.Variable:
                            found[child.nodeid.Identifier] = child
                        elif cls == ua.NodeClass.Object and "Cnc" not in child.nodeid.Identifier:
                            await walk(child)  # (the CNC model: tests/test_opcua_companion.py)

                await walk(root)
                assert set(found) == set(specs)
                snap = service.current()
                # each attribute of every variable in batches of the advertised limits
                # (MaxNodesPerRead 100, MaxNodesPerBrowse 20), as an efficient client
                # reads: about 150 requests instead of 2300, so the check does not
                # depend on how busy the host is
                ids = sorted(found)
                nodes = [found[i] for i in ids]

                async def read(attr: Any, of: list[Any]) -> list[Any]:
                    out: list[Any] = []
                    for k in range(0, len(of), 100):
                        out += await c.read_attributes(of[k : k + 100], attr)
                    return out

                A = ua.AttributeIds
                types = await read(A.DataType, nodes)
                levels = await read(A.AccessLevel, nodes)
                descs = await read(A.Description, nodes)
                values = await read(A.Value, nodes)
                refs: list[Any] = []
                for k in range(0, len(nodes), 20):
                    refs += [r for _, r in await c.browse_nodes(nodes[k : k + 20])]
                has_property = ua.NodeId(ua.ObjectIds.HasProperty)
                has_type = ua.NodeId(ua.ObjectIds.HasTypeDefinition)
                props_of = [
                    [x for x in r.References if x.IsForward and x.ReferenceTypeId == has_property]
                    for r in refs
                ]
                flat = [c.get_node(x.NodeId) for props in props_of for x in props]
                prop_values = iter(await read(A.Value, flat))
                for i, node_id in enumerate(ids):
                    spec = specs[node_id]
                    vtype = getattr(ua.VariantType, spec.ua_type)
                    assert types[i].Value.Value == ua.NodeId(vtype.value), node_id
                    level = ua.AccessLevel.parse_bitfield(levels[i].Value.Value)
                    assert (ua.AccessLevel.CurrentRead in level) == spec.readable
                    assert (ua.AccessLevel.CurrentWrite in level) == spec.writable
                    assert spec.obj.source in descs[i].Value.Value.Text
                    props = {x.BrowseName.Name: next(prop_values).Value.Value for x in props_of[i]}
                    assert props["AdsAddress"] == spec.ads_address
                    (kind,) = [
                        x.NodeId for x in refs[i].References if x.ReferenceTypeId == has_type
                    ]
                    assert kind == ua.NodeId(getattr(ua.ObjectIds, spec.type_definition))
                    if spec.unit:
                        assert props["EngineeringUnits"].DisplayName.Text == spec.unit
                    if spec.eu_range:
                        r = props["EURange"]
                        assert (r.Low, r.High) == spec.eu_range
                    dv = values[i]
                    if spec.readable:
                        assert dv.StatusCode.is_good(), node_id
                        assert dv.Value.VariantType == vtype
                        assert dv.Value.Value == snap.value(spec.obj, spec.axis)
                        assert dv.SourceTimestamp == source_time(snap)
                    else:
                        assert dv.StatusCode.value == ua.StatusCodes.BadNotReadable
                coef = found["local/Axes/X/TEMPC/coefficient"]
                props = {(await p.read_browse_name()).Name: p for p in await coef.get_properties()}
                assert (await props["EURange"].read_value()).High == 10000.0
                assert await props["AdsAddress"].read_value() == "port 551, 0x120300:0x10043"
                # the twin's and the volumetric compensation's objects are there too
                assert "local/TWIN/ambient_temperature" in found
                assert "local/Axes/X/VOLC/correction" in found
                assert "local/COM/cnc_interpr_vol_comp_file_w" in found
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_a_fleet_serves_each_machine_under_its_name(default_cfg) -> None:
    services = {
        name: ObjectService(Machine(default_cfg, cycle_s=0.001, homed=True))
        for name in ("mill", "lathe")
    }

    async def scenario() -> None:
        iface = await started(services, options(companion_models=True))
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                mill = node_of(c, ns, "mill/Axes/X/TEMPC/coefficient")
                lathe = node_of(c, ns, "lathe/Axes/X/TEMPC/coefficient")
                await mill.write_value(ua.Variant(11.0, ua.VariantType.Double))
                for s in services.values():
                    access.step(s, 1)
                assert await mill.read_value() == 11.0
                assert await lathe.read_value() == 4000.0

                # the second machine's nodes are a copy of the first's (same shape):
                # the same tree, each node its own, names and references its machine's
                async def tree(node: Any, out: dict[str, Any]) -> dict[str, Any]:
                    """Every node below `node`, a level at a time, 20 nodes per Browse
                    (the server's MaxNodesPerBrowse): a few dozen requests, not one
                    per node (on a loaded runner those took longer than the test)."""
                    level = [node.nodeid]
                    while level:
                        found = []
                        for at in range(0, len(level), 20):
                            asked = [
                                ua.BrowseDescription(
                                    NodeId=n,
                                    BrowseDirection=ua.BrowseDirection.Forward,
                                    ReferenceTypeId=ua.NodeId(ua.ObjectIds.HierarchicalReferences),
                                    IncludeSubtypes=True,
                                    ResultMask=63,
                                )
                                for n in level[at : at + 20]
                            ]
                            params = ua.BrowseParameters(NodesToBrowse=asked)
                            for result in await c.uaclient.browse(params):
                                for ref in result.References:
                                    if ref.NodeId.Identifier in out:
                                        continue  # (a CNC axis organizes its folders)
                                    out[ref.NodeId.Identifier] = (
                                        ref.BrowseName.Name,
                                        ref.NodeClass,
                                    )
                                    found.append(ua.NodeId(ref.NodeId.Identifier, ns))
                        level = found
                    return out

                mill_tree = await tree(node_of(c, ns, "mill"), {})
                lathe_tree = await tree(node_of(c, ns, "lathe"), {})
                assert len(mill_tree) > 500
                assert {
                    k.replace("lathe", "mill", 1): v for k, v in lathe_tree.items()
                } == mill_tree
                own = await node_of(c, ns, "lathe/Axes/X").read_attribute(ua.AttributeIds.NodeId)
                assert own.Value.Value == ua.NodeId("lathe/Axes/X", ns)
                parent = await node_of(c, ns, "lathe/Axes").get_parent()
                assert parent.nodeid == ua.NodeId("lathe", ns)
                assert (await parent.read_browse_name()).Name == "lathe"
                tops = [
                    (await n.read_browse_name()).Name for n in await c.nodes.objects.get_children()
                ]
                assert tops.count("mill") == tops.count("lathe") == 1
                machinery = await c.get_namespace_index("http://opcfoundation.org/UA/Machinery/")
                folder = await c.nodes.objects.get_child(f"{machinery}:Machines")
                tools = {
                    (await n.read_browse_name()).Name: n.nodeid.Identifier
                    for n in await folder.get_children()
                }
                assert tools == {"mill": "mill/MachineTool", "lathe": "lathe/MachineTool"}
                args = await node_of(c, ns, "lathe/RunNc/InputArguments").read_value()
                assert [a.Name for a in args] == ["text"]
                cnc_x = "lathe/CncInterface.CncAxisList.X"
                channel = await node_of(c, ns, f"{cnc_x}.ActChannel").read_value()
                assert channel == ua.NodeId("lathe/CncInterface.CncChannelList.Channel1", ns)
                (coef,) = [  # the X axis' compensation, found from the CNC axis
                    n
                    for n in await node_of(c, ns, cnc_x).get_children()
                    if n.nodeid.Identifier == "lathe/Axes/X/TEMPC"
                ]
                assert await (await coef.get_child(f"{ns}:coefficient")).read_value() == 4000.0
        finally:
            await iface.close()

    run(scenario, TIMEOUT + MODELS_START_S)


# ---------------------------------------------------------------------- reads and writes


@pytest.mark.slow
def test_write_goes_through_the_service_with_its_checks(service: ObjectService) -> None:
    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = node_of(c, ns, "local/Axes/X/TEMPC/coefficient")
                await coef.write_value(ua.Variant(12.5, ua.VariantType.Double))
                access.step(service, 1)  # applied by the next cycle, as every interface's write
                assert await coef.read_value() == 12.5
                assert access.read_name(service, "TEMPC::coefficient", 1) == 12.5

                async def refused(node: Any, variant: ua.Variant) -> int:
                    with pytest.raises(UaStatusCodeError) as err:
                        await node.write_value(variant)
                    return err.value.code

                bad = ua.StatusCodes
                d = ua.VariantType.Double
                assert await refused(coef, ua.Variant(1e6, d)) == bad.BadOutOfRange
                assert await refused(coef, ua.Variant(float("nan"), d)) == bad.BadOutOfRange
                assert await refused(coef, ua.Variant(5, ua.VariantType.Int32)) == (
                    bad.BadTypeMismatch
                )
                assert await refused(coef, ua.Variant("5", ua.VariantType.String)) == (
                    bad.BadTypeMismatch
                )
                assert await refused(coef, ua.Variant([1.0, 2.0], d)) == bad.BadTypeMismatch
                actual = node_of(c, ns, "local/Axes/X/TEMPC/actual_offset")
                assert await refused(actual, ua.Variant(1, ua.VariantType.Int32)) == (
                    bad.BadNotWritable
                )
                feed = node_of(c, ns, "local/Axes/X/SIM/feed")
                assert await refused(feed, ua.Variant(0, ua.VariantType.Int32)) == (
                    bad.BadOutOfRange
                )
                # other attributes of our variables are not writable
                with pytest.raises(UaStatusCodeError) as err:
                    await coef.write_attribute(
                        ua.AttributeIds.DisplayName,
                        ua.DataValue(ua.Variant(ua.LocalizedText("x"))),
                    )
                assert err.value.code == bad.BadNotWritable
                access.step(service, 1)
                assert access.read_name(service, "TEMPC::coefficient", 1) == 12.5  # none applied
                # an anonymous session is not an administrator: the server's own nodes
                # keep their access levels
                with pytest.raises(UaStatusCodeError):
                    await c.nodes.server.write_attribute(
                        ua.AttributeIds.DisplayName,
                        ua.DataValue(ua.Variant(ua.LocalizedText("x"))),
                    )
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_writes_of_one_request_are_applied_in_one_cycle(service: ObjectService) -> None:
    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                nodes = [node_of(c, ns, f"local/Axes/{a}/TEMPC/offset_0") for a in "XYZ"]
                values = [ua.DataValue(ua.Variant(v, ua.VariantType.Int32)) for v in (1, 2, 3)]
                bad = node_of(c, ns, "local/Axes/X/TEMPC/coefficient")
                results = await c.uaclient.write_attributes(
                    [n.nodeid for n in (*nodes, bad)],
                    [*values, ua.DataValue(ua.Variant(1e9, ua.VariantType.Double))],
                    ua.AttributeIds.Value,
                )
                assert [r.name for r in results] == ["Good"] * 3 + ["BadOutOfRange"]
                cycle = access.step(service, 1).cycle
                assert [access.read_name(service, "TEMPC::offset_0", a) for a in (1, 2, 3)] == [
                    1,
                    2,
                    3,
                ]
                assert cycle == service.current().cycle
        finally:
            await iface.close()

    run(scenario)


def test_the_status_codes_of_the_error_table() -> None:
    """The status codes of the README's table, by the ADS code they stand for."""
    assert STATUS[0x706] == "BadOutOfRange"
    assert STATUS[0x719] == "BadTimeout"
    assert STATUS[0x707] == "BadResourceUnavailable"


# ---------------------------------------------------------------------- subscriptions


class Collect:
    """An asyncua subscription handler that keeps every data change."""

    def __init__(self) -> None:
        self.changes: list[tuple[str, Any, Any]] = []
        self.arrived = asyncio.Event()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        dv = data.monitored_item.Value
        self.changes.append((node.nodeid.Identifier, val, dv.SourceTimestamp))
        self.arrived.set()

    async def until(self, count: int, node_id: str) -> list[tuple[Any, Any]]:
        while len([c for c in self.changes if c[0] == node_id]) < count:
            self.arrived.clear()
            await self.arrived.wait()
        return [(v, t) for n, v, t in self.changes if n == node_id]


@pytest.mark.slow
def test_one_notification_per_sampled_cycle_with_its_time(service: ObjectService) -> None:
    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                count = node_of(c, ns, "local/SIM/cycle_count")
                coef = node_of(c, ns, "local/Axes/X/TEMPC/coefficient")
                every5 = node_of(c, ns, "local/Axes/Y/SIM/command_position")
                handler = Collect()
                sub = await c.create_subscription(
                    ua.CreateSubscriptionParameters(RequestedPublishingInterval=10), handler
                )
                # a queue for each sample between two Publish responses (Part 4
                # §5.12.1.5: the default of 0 or 1 keeps only the newest)
                queue = guard.MAX_QUEUE_SIZE
                await sub.subscribe_data_change([count, coef], sampling_interval=1, queuesize=queue)
                await sub.subscribe_data_change(every5, sampling_interval=5, queuesize=queue)
                first = service.current().cycle
                await handler.until(1, "local/SIM/cycle_count")  # the initial value
                samples: list[Any] = []
                for _ in range(10):
                    samples.append(access.step(service, 1))
                got = await handler.until(11, "local/SIM/cycle_count")
                assert [v for v, _ in got] == [first + i for i in range(11)]
                assert [t for _, t in got[1:]] == [source_time(s) for s in samples]
                # a value that does not change is not notified again
                assert len([x for x in handler.changes if x[0].endswith("coefficient")]) == 1
                await coef.write_value(ua.Variant(3.5, ua.VariantType.Double))
                access.step(service, 1)
                got = await handler.until(2, "local/Axes/X/TEMPC/coefficient")
                assert got[-1][0] == 3.5
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_sampling_interval_in_whole_cycles(service: ObjectService) -> None:
    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                count = node_of(c, ns, "local/SIM/cycle_count")
                handler = Collect()
                sub = await c.create_subscription(10, handler)
                queue = guard.MAX_QUEUE_SIZE  # (each sample, not only the newest)
                await sub.subscribe_data_change(count, sampling_interval=5, queuesize=queue)
                await handler.until(1, "local/SIM/cycle_count")
                access.step(service, 10)
                got = await handler.until(3, "local/SIM/cycle_count")
                assert [v % 5 for v, _ in got[1:]] == [0, 0]
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_one_read_request_is_answered_from_one_cycle(
    service: ObjectService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The values of one Read request come from one snapshot, as an ADS sum read's: here
    every observation of the machine is followed by a cycle, so values taken one by one
    would each come from another cycle."""
    real, real_if_due = service.current, service.current_if_due

    def current(**kw: Any) -> Any:
        snap = real(**kw)
        service.stepper().step(1)  # the next observation sees the next cycle
        return snap

    def current_if_due() -> Any:  # (what OPC UA asks first: §9.1)
        snap = real_if_due()
        service.stepper().step(1)
        return snap

    monkeypatch.setattr(service, "current", current)
    monkeypatch.setattr(service, "current_if_due", current_if_due)

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                paths = ["SIM/cycle_count", "Axes/X/TEMPC/coefficient", "SIM/overruns"]
                nodes = [node_of(c, ns, f"local/{p}") for p in paths]
                values = await c.read_attributes(nodes)
                assert len({v.SourceTimestamp for v in values}) == 1
                then = await c.read_attributes(nodes[:1])
                assert then[0].Value.Value == values[0].Value.Value + 1
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_an_item_with_a_deadband_beside_a_plain_one(service: ObjectService) -> None:
    """An item with a filter of its own (an absolute deadband of 1.5) is notified by
    asyncua's rules; a plain item of the same variable gets every change beside it."""

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = node_of(c, ns, "local/Axes/X/TEMPC/coefficient")
                name = "local/Axes/X/TEMPC/coefficient"
                plain, banded = Collect(), Collect()
                sub = await c.create_subscription(10, plain)
                await sub.subscribe_data_change(coef, sampling_interval=1)
                await (await c.create_subscription(10, banded)).deadband_monitor(coef, 1.5)
                await plain.until(1, name)
                await banded.until(1, name)
                for n, value in enumerate((3.0, 3.5, 10.0), start=2):
                    await coef.write_value(ua.Variant(value, ua.VariantType.Double))
                    access.step(service, 1)
                    await plain.until(n, name)
                assert [v for v, _ in await plain.until(4, name)] == [4000.0, 3.0, 3.5, 10.0]
                assert [v for v, _ in await banded.until(3, name)] == [4000.0, 3.0, 10.0]
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_monitored_items_are_bounded_per_session_and_in_total(service: ObjectService) -> None:
    async def scenario() -> None:
        opts = options(max_monitored_items_per_session=3, max_monitored_items=5)
        iface = await started({"local": service}, opts)
        try:
            async with client(iface) as a, client(iface) as b:
                ns = await a.get_namespace_index(NAMESPACE_URI)
                paths = [
                    f"local/Axes/{x}/TEMPC/{f}" for x in "XYZ" for f in ("offset_0", "coefficient")
                ]

                async def monitor(c: Client, which: list[str]) -> list[str]:
                    sub = await c.create_subscription(50, Collect())
                    params = ua.CreateMonitoredItemsParameters(
                        SubscriptionId=sub.subscription_id,
                        TimestampsToReturn=ua.TimestampsToReturn.Both,
                        ItemsToCreate=[
                            ua.MonitoredItemCreateRequest(
                                ItemToMonitor=ua.ReadValueId(
                                    NodeId=ua.NodeId(p, ns), AttributeId=ua.AttributeIds.Value
                                ),
                                MonitoringMode=ua.MonitoringMode.Reporting,
                                RequestedParameters=ua.MonitoringParameters(
                                    ClientHandle=i, SamplingInterval=1, QueueSize=10
                                ),
                            )
                            for i, p in enumerate(which)
                        ],
                    )
                    results = await c.uaclient.create_monitored_items(params)
                    return [r.StatusCode.name for r in results]

                assert await monitor(a, paths[:4]) == ["Good"] * 3 + ["BadTooManyMonitoredItems"]
                assert await monitor(b, paths[:3]) == ["Good"] * 2 + ["BadTooManyMonitoredItems"]
            # the sessions are gone: their items no longer count
            async with client(iface) as c:
                assert await monitor(c, paths[:3]) == ["Good"] * 3
        finally:
            await iface.close()

    run(scenario)


# ---------------------------------------------------------------------- methods


@pytest.mark.slow
def test_every_method_with_results_and_errors(service: ObjectService, lists_copy: Path) -> None:
    from geo_server.listfile import load_machine

    own = ObjectService(Machine(load_machine(lists_copy), cycle_s=0.001, homed=True))

    async def scenario() -> None:
        iface = await started({"local": own, "shipped": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                root = node_of(c, ns, "local")

                async def call(name: str, *args: Any) -> dict[str, Any]:
                    return json.loads(await root.call_method(f"{ns}:{name}", *args))

                async def refused(node: Any, name: str, *args: Any) -> str:
                    with pytest.raises(UaStatusCodeError) as err:
                        await node.call_method(f"{ns}:{name}", *args)
                    return ua.StatusCode(err.value.code).name

                names = {(await m.read_browse_name()).Name for m in await root.get_methods()}
                assert names == {m.name for m in METHODS}
                assert (await call("Reload"))["ok"] is True
                access.step(own, 1)
                assert (await call("Save"))["ok"] is True
                assert (await call("Reset"))["command"] == "reset"
                assert (await call("RunNc", "G01 X10 F1000"))["command"] == "nc"
                injected = await call("InjectFault", "zenoh:error=0x707")
                fault_id = injected["injected"]["id"]
                cleared = await call("ClearFaults", str(fault_id))
                assert [f["id"] for f in cleared["cleared"]] == [fault_id]
                assert (await call("ClearFaults", "all"))["cleared"] == []
                # the same errors as every interface, as status codes
                assert await refused(root, "RunNc", "G01 X") == "BadSyntaxError"
                assert await refused(root, "InjectFault", "nonsense") == "BadInvalidArgument"
                assert await refused(root, "ClearFaults", "x" * 100) == "BadInvalidArgument"
                assert await refused(root, "RunNc") == "BadArgumentsMissing"
                assert await refused(root, "Reset", "extra") == "BadTooManyArguments"
                assert await refused(root, "RunNc", ua.Variant(5, ua.VariantType.Int32)) == (
                    "BadTypeMismatch"
                )
                # the shipped default machine is never saved
                shipped = node_of(c, ns, "shipped")
                assert await refused(shipped, "Save") == "BadInternalError"
        finally:
            await iface.close()

    run(scenario)


# ---------------------------------------------------------------------- security


@pytest.mark.slow
def test_read_only_refuses_writes_and_methods(service: ObjectService) -> None:
    async def scenario() -> None:
        iface = await started({"local": service}, options(read_only=True))
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = node_of(c, ns, "local/Axes/X/TEMPC/coefficient")
                assert ua.AccessLevel.CurrentWrite not in await coef.get_user_access_level()
                assert ua.AccessLevel.CurrentWrite in await coef.get_access_level()
                with pytest.raises(UaStatusCodeError) as err:
                    await coef.write_value(ua.Variant(1.0, ua.VariantType.Double))
                assert err.value.code == ua.StatusCodes.BadUserAccessDenied
                with pytest.raises(UaStatusCodeError) as err:
                    await node_of(c, ns, "local").call_method(f"{ns}:Reset")
                assert err.value.code == ua.StatusCodes.BadUserAccessDenied
                assert await coef.read_value() == 4000.0
                # each method says so before it is called (OPC 10000-3 §5.7: for this
                # user), while it stays a method of the machine
                for method in METHODS:
                    node = node_of(c, ns, f"local/{method.name}")
                    user = await node.read_attribute(ua.AttributeIds.UserExecutable)
                    anyone = await node.read_attribute(ua.AttributeIds.Executable)
                    assert (user.Value.Value, anyone.Value.Value) == (False, True)
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_user_and_password(service: ObjectService, tmp_path: Path) -> None:
    async def scenario() -> None:
        opts = options(user="op", password="s3cret", cert_dir=tmp_path)
        iface = await started({"local": service}, opts)
        try:
            for kw in (
                {},
                {"user": "op", "password": "wrong"},
                {"user": "x", "password": "s3cret"},
            ):
                with pytest.raises(UaStatusCodeError) as err:
                    async with client(iface, **kw):
                        pass
                assert err.value.code in (
                    ua.StatusCodes.BadIdentityTokenRejected,
                    ua.StatusCodes.BadUserAccessDenied,
                    ua.StatusCodes.BadIdentityTokenInvalid,
                )
            # three failures from this address: the next login waits out the backoff
            # (LOGIN_BACKOFF_FIRST_S · 2², the bound the guard sets), then is taken
            await asyncio.sleep(logins.LOGIN_BACKOFF_FIRST_S * 4)
            async with client(iface, user="op", password="s3cret") as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                assert await node_of(c, ns, "local/Axes/X/TEMPC/coefficient").read_value() == 4000.0
        finally:
            await iface.close()

    run(scenario)


def _client_certificate(folder: Path) -> tuple[Path, Path]:
    key = cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key,
        "urn:geo-server:test-client",
        {"organizationName": "test"},
        [],
        extended=[ExtendedKeyUsageOID.CLIENT_AUTH],
    )
    cert_path, key_path = folder / "client.der", folder / "client.pem"
    cert_path.write_bytes(cert.public_bytes(Encoding.DER))
    key_path.write_bytes(cert_gen.dump_private_key_as_pem(key))
    return cert_path, key_path


@pytest.mark.slow
def test_sign_and_encrypt_with_a_certificate_made_once(
    service: ObjectService, tmp_path: Path
) -> None:
    folder = tmp_path / "opcua"
    client_cert, client_key = _client_certificate(tmp_path)

    async def scenario() -> None:
        iface = await started({"local": service}, options(cert_dir=folder, encrypt_only=True))
        try:
            made = (folder / CERT_FILE).read_bytes()
            assert (folder / KEY_FILE).stat().st_mode & 0o077 == 0
            plain = client(iface)
            with pytest.raises(Exception):  # no unencrypted endpoint  # noqa: B017
                async with plain:
                    pass
            c = client(iface)
            await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{client_cert},{client_key}")
            async with c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = node_of(c, ns, "local/Axes/X/TEMPC/coefficient")
                await coef.write_value(ua.Variant(7.0, ua.VariantType.Double))
                access.step(service, 1)
                assert await coef.read_value() == 7.0
        finally:
            await iface.close()
        # a second start keeps the certificate clients may have trusted
        again = await started({"local": service}, options(cert_dir=folder))
        await again.close()
        assert (folder / CERT_FILE).read_bytes() == made

    run(scenario)


def test_certificate_folder_never_inside_the_shipped_machine(lists_copy: Path) -> None:
    from geo_server.paths import default_startup_list

    assert cert_folder(lists_copy) == lists_copy.parent / "opcua"
    shipped = cert_folder(default_startup_list())
    assert default_startup_list().parent not in shipped.parents
    assert shipped.name == "opcua"


@pytest.mark.slow
def test_connections_past_the_cap_are_closed_and_the_rest_served(service: ObjectService) -> None:
    """Idle sockets that never say Hello hold at most `max_connections`; a client past
    them is refused, and served again once they are gone (docs/security.md)."""

    async def scenario() -> None:
        iface = await started({"local": service}, options(max_connections=3))
        try:
            idle = [await asyncio.open_connection("127.0.0.1", iface.port) for _ in range(3)]
            with pytest.raises(Exception):  # noqa: B017 (closed at once: asyncua's own error)
                async with client(iface):
                    pass
            for _, writer in idle:
                writer.close()
                await writer.wait_closed()
            # the server notices the closes on its next loop turns (its own thread)
            deadline = asyncio.get_running_loop().time() + TIMEOUT
            while asyncio.get_running_loop().time() < deadline:
                try:
                    async with client(iface) as c:
                        ns = await c.get_namespace_index(NAMESPACE_URI)
                        node = node_of(c, ns, "local/Axes/X/TEMPC/coefficient")
                        assert await node.read_value() == 4000.0
                        return
                except (OSError, UaStatusCodeError, TimeoutError):
                    await asyncio.sleep(0.01)
            raise AssertionError("never served after the idle connections closed")
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_background_start_checks_the_port_first(service: ObjectService) -> None:
    """`geo-server run` starts OPC UA in the background; a taken port is still found at
    once (and the start says how it ended)."""
    import socket

    async def scenario() -> None:
        with socket.socket() as taken:
            taken.bind(("127.0.0.1", 0))
            taken.listen()
            port = taken.getsockname()[1]
            iface = OpcUaInterface(
                {"local": service},
                OpcUaOptions(endpoint=f"opc.tcp://127.0.0.1:{port}", background=True),
            )
            with pytest.raises(OSError):
                await iface.start()
        ended: list[BaseException | None] = []
        iface = OpcUaInterface({"local": service}, options(background=True))
        iface.on_started = ended.append
        await iface.start()
        assert iface.starting is not None
        await iface.starting
        assert ended == [None]
        async with client(iface) as c:
            ns = await c.get_namespace_index(NAMESPACE_URI)
            assert await node_of(c, ns, "local/SIM/cycle_count").read_value() >= 0
        await iface.close()

    run(scenario)


def test_a_certificate_for_every_address_names_the_loopback_ones(tmp_path: Path) -> None:
    """Bound to 0.0.0.0 (the container image), clients on the host reach the server at
    127.0.0.1 (docs/container.md) and compare that with the certificate's names: they
    are in it; bound to 127.0.0.1, only that one (review)."""
    from cryptography import x509

    from geo_server.transports.opcua.certs import ensure_certificate

    def addresses(host: str) -> set[str]:
        cert, _ = ensure_certificate(tmp_path / host, "urn:geo-server:server", host)
        alt = x509.load_der_x509_certificate(cert.read_bytes()).extensions.get_extension_for_class(
            x509.SubjectAlternativeName
        )
        return {str(ip) for ip in alt.value.get_values_for_type(x509.IPAddress)}

    assert addresses("0.0.0.0") == {"0.0.0.0", "127.0.0.1", "::1"}
    assert addresses("127.0.0.1") == {"127.0.0.1"}
