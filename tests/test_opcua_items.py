"""OPC UA as the specification says it, checked with asyncua's client (nobody here
wrote it) against values computed by hand from OPC 10000-4 (services), OPC 10000-8
(data access) and the OPC Foundation's table of unit codes (UNECE_to_OPCUA.csv):

- each monitored item samples at its own interval, whatever another session asked;
- a deadband compares with the value last notified (absolute, and percent of EURange);
- an item's values never go back in time;
- the server's BuildInfo, the units' UN/CEFACT codes, one unit per variable, the
  variable types of Part 8, and the status codes of Read, Write and Call.

Stepped mode: nothing runs until a test steps the machine, so every value is tied to a
cycle, not to time.
"""

from __future__ import annotations

import asyncio
import time
from importlib.metadata import version
from typing import Any

import pytest
from asyncua import ua
from test_opcua import Collect, client, node_of, options, run, started

from geo_server import access
from geo_server.service import ObjectService
from geo_server.transports.opcua import guard
from geo_server.transports.opcua.items import (
    ABSOLUTE,
    STATUS_VALUE,
    STATUS_VALUE_TIMESTAMP,
    ItemRule,
    Sample,
    cycles_of,
    rule_for,
)
from geo_server.transports.opcua.server import OpcUaInterface
from geo_server.transports.opcua.space import NAMESPACE_URI
from geo_server.transports.share import LoopShare

COUNT = "local/SIM/cycle_count"
COEF = "local/Axes/X/TEMPC/coefficient"


async def item(
    c: Any, handler: Collect, node: Any, sampling_ms: float, flt: Any = None
) -> tuple[Any, Any]:
    """A subscription of `handler` with one item of `node`: (the subscription, the
    item's id or the StatusCode that refused it)."""
    sub = await c.create_subscription(10, handler)
    request = ua.MonitoredItemCreateRequest(
        ItemToMonitor=ua.ReadValueId(NodeId=node.nodeid, AttributeId=ua.AttributeIds.Value),
        MonitoringMode=ua.MonitoringMode.Reporting,
        RequestedParameters=ua.MonitoringParameters(
            ClientHandle=1,  # (one item per subscription)
            SamplingInterval=sampling_ms,
            QueueSize=guard.MAX_QUEUE_SIZE,
            Filter=flt,
        ),
    )
    (made,) = await sub.create_monitored_items([request])
    return sub, made


def deadband(kind: int, value: float) -> ua.DataChangeFilter:
    return ua.DataChangeFilter(
        Trigger=ua.DataChangeTrigger.StatusValue, DeadbandType=kind, DeadbandValue=value
    )


@pytest.mark.slow
def test_each_item_samples_at_its_own_interval(service: ObjectService) -> None:
    """One session's 1 ms item (one cycle) beside another's 10 ms item of the same
    variable: each gets its own rate, and the slow one keeps it after the fast one is
    gone (before: both took the fastest and kept it)."""

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as fast_client, client(iface) as slow_client:
                ns = await fast_client.get_namespace_index(NAMESPACE_URI)
                fast, slow = Collect(), Collect()
                fast_sub, fast_id = await item(
                    fast_client, fast, node_of(fast_client, ns, COUNT), 1.0
                )
                slow_sub, slow_id = await item(
                    slow_client, slow, node_of(slow_client, ns, COUNT), 10.0
                )
                queue = guard.MAX_QUEUE_SIZE
                (asked_fast,) = await fast_sub.modify_monitored_item(fast_id, 1.0, queue)
                (asked_slow,) = await slow_sub.modify_monitored_item(slow_id, 10.0, queue)
                revised = (asked_fast.RevisedSamplingInterval, asked_slow.RevisedSamplingInterval)
                assert revised == (1.0, 10.0)
                await fast.until(1, COUNT)
                await slow.until(1, COUNT)
                start = service.current().cycle
                for _ in range(4):  # (5 cycles at a time: within the item's queue)
                    access.step(service, 5)
                    await fast.until(len(fast.changes) + 5, COUNT)
                tens = [c for c in range(start + 1, start + 21) if c % 10 == 0]
                assert [v for v, _ in await slow.until(3, COUNT)][1:] == tens
                assert [v for _, v, _ in fast.changes[1:]] == list(range(start + 1, start + 21))
                await fast_sub.delete()
                access.step(service, 20)
                later = [c for c in range(start + 21, start + 41) if c % 10 == 0]
                assert [v for v, _ in await slow.until(5, COUNT)][3:] == later
                await asyncio.sleep(0.1)  # (a third value would have come with these)
                assert len(slow.changes) == 5
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_the_status_counts_the_items_their_samples_and_the_skipped(
    service: ObjectService,
) -> None:
    """`status()["opcua_items"]`: one item on the cycle count; five cycles stepped are
    five samples and five values notified. Then OPC UA's share of notifications is used
    up (its clock held 2 s back: about 2 s to wait) while six cycles are stepped: the
    sampling waits (before it takes any) and samples only the newest, the five before it counted in
    `samples_skipped` — what docs/security.md tells an operator to look for when the
    share is used up. (Before, these were counted on the interface and shown nowhere.)"""
    frozen: list[float | None] = [None]

    def clock() -> float:
        at = frozen[0]
        return time.monotonic() if at is None else at

    share = LoopShare(rate=0.1, burst=0.002, clock=clock)

    def counts() -> dict[str, int]:
        return dict(service.status()["opcua_items"])

    async def scenario() -> None:
        iface = OpcUaInterface({"local": service}, options(), notify_share=share)
        await iface.start()
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                seen = Collect()
                await item(c, seen, node_of(c, ns, COUNT), 1.0)
                await seen.until(1, COUNT)
                before = counts()
                assert before["items"] == 1
                start = service.current().cycle
                access.step(service, 5)
                await seen.until(6, COUNT)
                after = counts()
                assert after["samples"] - before["samples"] == 5
                assert after["notifications"] - before["notifications"] == 5
                frozen[0] = time.monotonic() - 2.0  # 0.2 s of the share short
                access.step(service, 6)  # (in a few ms: the sampling waits 2 s)
                got = await seen.until(7, COUNT)
                frozen[0] = None
                assert [v for v, _ in got][6:] == [start + 11]  # the newest only
                last = counts()
                assert last["samples_skipped"] - after["samples_skipped"] == 5
                assert last["samples"] - after["samples"] == 1
                assert last["samples_late"] == 0
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_an_item_of_a_fleets_copied_machine_is_sampled(default_cfg: Any) -> None:
    """The second machine of a shape is a copy made on first use (`guard.lazy_nodes`):
    an item of its cycle count is sampled like one of the first machine's, cycle for
    cycle. (When the items moved to monitoring.py they looked their variables up in
    the mapping of before the copies, which has the first machine's only: the second's
    item got its first value and no other.)"""
    from geo_server.machine.machine import Machine

    services = {
        name: ObjectService(Machine(default_cfg, cycle_s=0.001, homed=True))
        for name in ("m1", "m2")
    }

    async def scenario() -> None:
        iface = await started(services, options(make_all=False))
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                seen = Collect()
                await item(c, seen, node_of(c, ns, "m2/SIM/cycle_count"), 1.0)
                await seen.until(1, "m2/SIM/cycle_count")
                start = services["m2"].current().cycle
                access.step(services["m2"], 3)
                got = await seen.until(4, "m2/SIM/cycle_count")
                assert [v for v, _ in got][1:] == [start + 1, start + 2, start + 3]
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_a_deadband_compares_with_the_value_last_notified(service: ObjectService) -> None:
    """The coefficient creeps by 0.4 µm/m per cycle. An absolute deadband of 1.0 is
    passed at 1.2 and 2.4 (1.2 past the last notified each time); a percent deadband of
    0.01 % of its EURange (-10 000 … 10 000: 2.0) at 2.4. Before, each sample was
    compared with the previous one (0.4 apart): nothing after 0.0."""
    creep = [0.0, 0.4, 0.8, 1.2, 1.6, 2.0, 2.4]

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = node_of(c, ns, COEF)
                plain, absolute, percent = Collect(), Collect(), Collect()
                await item(c, plain, coef, 1.0)
                await item(c, absolute, coef, 1.0, deadband(1, 1.0))
                _, made = await item(c, percent, coef, 1.0, deadband(2, 0.01))
                assert isinstance(made, int)  # (an item id: made)
                for n, value in enumerate(creep, start=2):
                    await coef.write_value(ua.Variant(value, ua.VariantType.Double))
                    access.step(service, 1)
                    await plain.until(n, COEF)
                await asyncio.sleep(0.1)  # (the filtered ones come with the plain one)
                assert [v for _, v, _ in absolute.changes] == [4000.0, 0.0, 1.2, 2.4]
                assert [v for _, v, _ in percent.changes] == [4000.0, 0.0, 2.4]
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_deadbands_that_cannot_apply_are_refused(service: ObjectService) -> None:
    """OPC 10000-8 §6.2: a percent deadband needs an EURange and lies in 0-100 %
    (Bad_DeadbandFilterInvalid); OPC 10000-4 §7.22.2: a deadband on a value that is
    not a number is Bad_FilterNotAllowed."""

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                cases = [
                    ("local/Axes/X/SIM/command_position", deadband(2, 1.0), "BadDeadband"),
                    (COEF, deadband(2, 150.0), "BadDeadbandFilterInvalid"),
                    (COEF, deadband(1, -1.0), "BadDeadbandFilterInvalid"),
                    ("local/Axes/X/TEMPC/activated", deadband(1, 1.0), "BadFilterNotAllowed"),
                ]
                for path, flt, status in cases:
                    _, made = await item(c, Collect(), node_of(c, ns, path), 1.0, flt)
                    assert made.name.startswith(status), path
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_an_items_values_never_go_back_in_time(service: ObjectService) -> None:
    """A new item's first value is read when it is made; the samples of earlier cycles
    that are still being handed out must not follow it (before: up to ~250 ms back)."""

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                count = node_of(c, ns, COUNT)
                first = Collect()
                await item(c, first, count, 1.0)
                await first.until(1, COUNT)
                late = [Collect() for _ in range(5)]
                for handler in late:
                    access.step(service, 300)  # samples queue up meanwhile
                    await item(c, handler, count, 1.0)
                access.step(service, 1)
                for handler in late:
                    got = await handler.until(2, COUNT)
                    assert [t for _, t in got] == sorted(t for _, t in got)
                    assert [v for v, _ in got] == sorted(v for v, _ in got)
        finally:
            await iface.close()

    run(scenario)


def test_the_rule_of_an_item_by_hand() -> None:
    """`ItemRule` without a server: the cases above and the triggers of Part 4 §7.22.2."""
    rule = ItemRule(every=10, deadband=1.0)
    nan = float("nan")
    assert not ItemRule().notifies(Sample(0, nan, 1), Sample(0, nan, 2))  # NaN stays NaN
    assert rule.notifies(Sample(0, 1.0, 1), Sample(0, nan, 2))  # into NaN: once
    assert rule.notifies(Sample(0, nan, 1), Sample(0, 1.0, 2))  # and out of it
    # with a deadband, StatusValueTimestamp behaves as StatusValue
    banded = rule_for(1, STATUS_VALUE_TIMESTAMP, ABSOLUTE, 1.0, numeric=True, eu_range=None)
    assert isinstance(banded, ItemRule) and banded.trigger == STATUS_VALUE
    # no interval (NaN) is the fastest, infinity the slowest (an hour); -1 the
    # subscription's publishing interval, unless that is not a number
    assert cycles_of(nan, 500.0, 1.0) == cycles_of(-1.0, nan, 1.0) == 1
    assert cycles_of(float("inf"), 500.0, 1.0) == 3_600_000
    assert cycles_of(-1.0, 500.0, 1.0) == 500
    last = Sample(0, 1.0, 100)
    assert not rule.notifies(last, Sample(0, 1.9, 101))  # within the deadband
    assert rule.notifies(last, Sample(0, 2.1, 101))
    assert rule.notifies(last, Sample(0x80000000, 1.0, 101))  # a status change
    assert not rule.notifies(last, Sample(0, 9.0, 99))  # older than the last
    assert not ItemRule(trigger=0).notifies(last, Sample(0, 9.0, 101))  # Status only
    assert ItemRule(trigger=2).notifies(last, Sample(0, 1.0, 101))  # a new timestamp
    assert not ItemRule().notifies(last, Sample(0, 1.0, 101))


# ---------------------------------------------------------------------- what it says


@pytest.mark.slow
def test_build_info_units_and_variable_types(service: ObjectService) -> None:
    """BuildInfo names geo-server and its version. Each unit is one unit with its
    UN/CEFACT code, as the OPC Foundation's UNECE_to_OPCUA.csv gives them (UnitId is
    the code's characters as bytes; -1 where there is no code): X is linear, C rotary
    (the default machine). The variable types are Part 8's."""
    expected_units = {
        COEF: ("µm/m", 13625),  # 59: part per million
        "local/Axes/X/SIM/acceleration": ("mm/s²", 5059633),  # M41
        "local/Axes/C/SIM/acceleration": ("°/s²", 5059637),  # M45
        "local/Axes/X/SIM/velocity": ("µm/s", -1),  # (no common code)
        "local/Axes/C/SIM/velocity": ("0.001°/s", -1),
        "local/Axes/X/TEMPC/offset_0": ("0.1 µm", -1),
        "local/Axes/C/TEMPC/offset_0": ("0.0001°", -1),
        "local/TWIN/ambient_temperature": ("°C", 4408652),  # CEL
        "local/VOLC/tool_length": ("mm", 5066068),  # MMT
    }
    expected_types = {
        COEF: ua.ObjectIds.AnalogItemType,  # (a documented range: its EURange)
        "local/Axes/X/SIM/command_position": ua.ObjectIds.BaseAnalogType,
        COUNT: ua.ObjectIds.BaseDataVariableType,
        "local/Axes/X/TEMPC/activated": ua.ObjectIds.BaseDataVariableType,
    }

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                build = await c.get_node(
                    ua.NodeId(ua.ObjectIds.Server_ServerStatus_BuildInfo)
                ).read_value()
                assert (build.ProductName, build.ManufacturerName) == ("geo-server", "geo-server")
                assert build.SoftwareVersion == version("geo-server")
                ns = await c.get_namespace_index(NAMESPACE_URI)
                for path, (text, unit_id) in expected_units.items():
                    eu = await node_of(c, ns, f"{path}/EngineeringUnits").read_value()
                    assert (eu.DisplayName.Text, eu.UnitId) == (text, unit_id), path
                    assert eu.NamespaceUri == "http://www.opcfoundation.org/UA/units/un/cefact"
                for path, type_id in expected_types.items():
                    kind = await node_of(c, ns, path).read_type_definition()
                    assert kind == ua.NodeId(type_id), path
                span = await node_of(c, ns, f"{COEF}/EURange").read_value()
                assert (span.Low, span.High) == (-10000.0, 10000.0)  # (000 p.22)
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_read_write_and_call_answer_the_specified_codes(service: ObjectService) -> None:
    """Read keeps the timestamps asked for and honours IndexRange (OPC 10000-4 §5.10.2,
    §7.27); a Write of an unknown node is Bad_NodeIdUnknown (not Bad_UserAccessDenied);
    a method called on an object it does not belong to is Bad_MethodInvalid and does not
    run (§5.11.2)."""

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = ua.NodeId(COEF, ns)
                names = ua.NodeId("local/SIM/axis_names", ns)

                async def read(stamps: int, *items: tuple[Any, str]) -> list[Any]:
                    params = ua.ReadParameters(TimestampsToReturn=stamps)
                    for node_id, index_range in items:
                        params.NodesToRead.append(
                            ua.ReadValueId(
                                NodeId=node_id,
                                AttributeId=ua.AttributeIds.Value,
                                IndexRange=index_range,
                            )
                        )
                    return list(await c.uaclient.read(params))

                source, server, both, neither = [
                    (await read(kind, (coef, "")))[0] for kind in range(4)
                ]
                assert source.SourceTimestamp and not source.ServerTimestamp
                assert server.ServerTimestamp and not server.SourceTimestamp
                assert both.SourceTimestamp and both.ServerTimestamp
                assert not (neither.SourceTimestamp or neither.ServerTimestamp)
                part, scalar, bad, odd = await read(
                    2, (names, "0:2"), (coef, "0"), (coef, "2:1"), (names, "\u00b2")
                )
                assert part.Value.Value == "1=X"  # (SIM::axis_names is "1=X 2=Y 3=Z 4=C")
                assert scalar.StatusCode.value == ua.StatusCodes.BadIndexRangeNoData
                assert bad.StatusCode.value == ua.StatusCodes.BadIndexRangeInvalid
                assert odd.StatusCode.value == ua.StatusCodes.BadIndexRangeInvalid  # (a "²")

                write = ua.WriteValue(
                    NodeId=ua.NodeId("local/no/such/node", ns),
                    AttributeId=ua.AttributeIds.Value,
                    Value=ua.DataValue(ua.Variant(1.0, ua.VariantType.Double)),
                )
                (status,) = await c.uaclient.write(ua.WriteParameters(NodesToWrite=[write]))
                assert status.value == ua.StatusCodes.BadNodeIdUnknown

                reload_id = ua.NodeId("local/Reload", ns)
                wrong = ua.CallMethodRequest(
                    ObjectId=ua.NodeId("local/Axes", ns), MethodId=reload_id
                )
                unknown = ua.CallMethodRequest(
                    ObjectId=ua.NodeId("local/nothing", ns), MethodId=reload_id
                )
                done = await c.uaclient.call([wrong, unknown])
                assert [r.StatusCode.value for r in done] == [
                    ua.StatusCodes.BadMethodInvalid,
                    ua.StatusCodes.BadNodeIdUnknown,
                ]
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_modify_sampling_mode_and_odd_intervals(service: ObjectService) -> None:
    """ModifyMonitoredItems with an unknown item beside a known one answers each on its
    own (Bad_MonitoredItemIdInvalid; asyncua failed the whole request, half applied);
    an item in Sampling mode is not reported (Part 4 §5.12.1.3); a NaN publishing and
    sampling interval is revised, not an internal error."""

    async def scenario() -> None:
        iface = await started({"local": service}, options())
        try:
            async with client(iface) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                count = node_of(c, ns, COUNT)
                reported, sampled = Collect(), Collect()
                sub, made = await item(c, reported, count, 1.0)
                request = ua.MonitoredItemModifyRequest(
                    MonitoredItemId=made,
                    RequestedParameters=ua.MonitoringParameters(
                        ClientHandle=1, SamplingInterval=5.0, QueueSize=guard.MAX_QUEUE_SIZE
                    ),
                )
                unknown = ua.MonitoredItemModifyRequest(
                    MonitoredItemId=987654,
                    RequestedParameters=ua.MonitoringParameters(SamplingInterval=5.0),
                )
                done = await c.uaclient.modify_monitored_items(
                    ua.ModifyMonitoredItemsParameters(
                        SubscriptionId=sub.subscription_id, ItemsToModify=[request, unknown]
                    )
                )
                assert [r.StatusCode.value for r in done] == [
                    ua.StatusCodes.Good,
                    ua.StatusCodes.BadMonitoredItemIdInvalid,
                ]
                assert done[0].RevisedSamplingInterval == 5.0
                quiet = await c.create_subscription(
                    ua.CreateSubscriptionParameters(RequestedPublishingInterval=float("nan")),
                    sampled,
                )
                asked = ua.MonitoredItemCreateRequest(
                    ItemToMonitor=ua.ReadValueId(NodeId=count.nodeid, AttributeId=13),
                    MonitoringMode=ua.MonitoringMode.Sampling,
                    RequestedParameters=ua.MonitoringParameters(
                        ClientHandle=1, SamplingInterval=float("nan"), QueueSize=4
                    ),
                )
                (kept,) = await quiet.create_monitored_items([asked])
                assert isinstance(kept, int)  # (made, not BadInternalError)
                await reported.until(1, COUNT)
                access.step(service, 10)
                await reported.until(3, COUNT)  # (every 5th cycle now)
                await asyncio.sleep(0.1)
                assert sampled.changes == []
                # set to Reporting, it reports the value now (Part 4 §5.12.1.3)
                await quiet.set_monitoring_mode(ua.MonitoringMode.Reporting)
                got = await sampled.until(1, COUNT)
                assert got[0][0] == service.current().cycle
        finally:
            await iface.close()

    run(scenario)
