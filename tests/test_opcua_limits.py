"""OPC UA limits on what one client may ask (docs/security.md *OPC UA*; guard.py,
operations.py): operations per request, monitored items on any node, queue sizes,
subscriptions per session. Each attack below was answered in full before: a Read of
100 000 values (3.7 s of the event loop), a Browse of 6 000 nodes (10.7 s), a
TranslateBrowsePaths of 40 000 elements (3.5 s), 30 000 items on `i=2258`, items with
a queue of 100 000, one session taking every subscription.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.ua.uaerrors import UaStatusCodeError
from conftest import free_port, geo_server_running
from support.probes import modbus_read

from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions
from geo_server.transports.opcua import guard, operations
from geo_server.transports.opcua.metering import RequestMeter
from geo_server.transports.opcua.server import OPCUA_NICE, OpcUaInterface, OpcUaOptions
from geo_server.transports.opcua.space import NAMESPACE_URI
from geo_server.transports.share import LoopShare

TIMEOUT = 30.0
TEMPC = "local/Axes/X/TEMPC/coefficient"
TOO_MANY = ua.StatusCodes.BadTooManyOperations
#: what tells a server that hangs from one that stops (not a figure: it stops in
#: milliseconds, bench/opcua_attacks.py measures it)
HANG_S = 20.0


def serve(
    service: ObjectService,
    scenario: Callable[[Client, OpcUaInterface], Awaitable[None]],
    **kw: Any,
) -> None:
    async def bounded() -> None:
        iface = OpcUaInterface(
            {"local": service},
            OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", **{"companion_models": False, **kw}),
        )
        await iface.start()
        try:
            async with Client(iface.endpoint, timeout=10) as c:
                await scenario(c, iface)
        finally:
            await iface.close()

    asyncio.run(asyncio.wait_for(bounded(), TIMEOUT))


def value_of(node: ua.NodeId) -> ua.ReadValueId:
    rv = ua.ReadValueId()
    rv.NodeId = node
    rv.AttributeId = ua.AttributeIds.Value
    return rv


async def held(share: LoopShare, request: Awaitable[Any]) -> asyncio.Future[Any]:
    """`request` sent, once the server holds it for `share` (a hold counted); not done."""
    holds = share.holds
    waiting = asyncio.ensure_future(request)
    for _ in range(500):  # (the server looks at the share when the request arrives)
        if share.holds > holds:
            break
        await asyncio.sleep(0.01)
    assert share.holds > holds and not waiting.done()
    return waiting


async def read_until_held(
    share: LoopShare, read: Callable[[], Awaitable[Any]]
) -> asyncio.Future[Any]:
    """Reads (each made by `read()`) one after the other until the server holds one
    for `share`: that one, not done. The server charges a Read on its own thread after
    answering it, so the client cannot know the burst is used up before a Read is held."""
    for _ in range(1000):
        holds = share.holds
        waiting = asyncio.ensure_future(read())
        while not waiting.done() and share.holds == holds:
            await asyncio.sleep(0.005)
        if not waiting.done():
            return waiting
        await waiting
    raise AssertionError("no Read was held")


async def refused(call: Awaitable[Any]) -> int:
    with pytest.raises(UaStatusCodeError) as err:
        await call
    return err.value.code


# ---------------------------------------------------------------- on the wire, sans I/O


def test_counts_are_read_from_the_bytes_before_anything_is_decoded() -> None:
    """Bodies written by hand from Part 6 §5.2 (little endian): a Read's NodesToRead
    count follows MaxAge (Double) and TimestampsToReturn (Int32); a Browse's follows its
    View (a two-byte NodeId, a DateTime, a UInt32) and RequestedMaxReferencesPerNode.
    Only the counts are there: nothing after them is needed to refuse."""
    most = operations.OPERATION_LIMITS["MaxNodesPerRead"]
    read = struct.pack("<dii", 0.0, 2, most + 1)
    over = operations.excess("ReadRequest", read)
    assert over is not None and (over.limit, over.count, over.most) == (
        "MaxNodesPerRead",
        most + 1,
        most,
    )
    assert operations.excess("ReadRequest", struct.pack("<dii", 0.0, 2, most)) is None
    assert operations.excess("ReadRequest", struct.pack("<dii", 0.0, 2, -1)) is None  # null
    browse = bytes([0x00, 0x00]) + struct.pack("<qIIi", 0, 0, 0, 100_000)
    over = operations.excess("BrowseRequest", browse)
    assert over is not None and over.limit == "MaxNodesPerBrowse" and over.count == 100_000
    with pytest.raises(operations.Malformed):
        operations.excess("ReadRequest", b"\0" * 10)


def test_the_elements_of_browse_paths_are_counted_across_paths() -> None:
    """TranslateBrowsePathsToNodeIds: one path (StartingNode i=84 as a two-byte NodeId)
    of `MAX_PATH_ELEMENTS`+1 elements, each (ReferenceTypeId i=33, IsInverse,
    IncludeSubtypes, TargetName 0:"A") written out by hand."""
    element = bytes([0x00, 33, 0, 1]) + struct.pack("<Hi", 0, 1) + b"A"
    most = operations.MAX_PATH_ELEMENTS

    def body(n: int) -> bytes:
        return struct.pack("<i", 1) + bytes([0x00, 84]) + struct.pack("<i", n) + element * n

    assert operations.excess("TranslateBrowsePathsToNodeIdsRequest", body(most)) is None
    over = operations.excess("TranslateBrowsePathsToNodeIdsRequest", body(most + 1))
    assert over is not None and over.count == most + 1


# ---------------------------------------------------------------- a live server


def test_each_operation_limit_is_advertised_and_is_the_one_enforced(
    service: ObjectService,
) -> None:
    """What `ServerCapabilities/OperationLimits` says is what the server takes: a Read of
    MaxNodesPerRead values is answered, one more is BadTooManyOperations (before: 10 000
    advertised, 100 000 answered)."""

    async def scenario(c: Client, iface: OpcUaInterface) -> None:
        limits = c.get_node(ua.NodeId(ua.ObjectIds.Server_ServerCapabilities_OperationLimits))
        advertised = {}
        for node in await limits.get_children():
            advertised[(await node.read_browse_name()).Name] = await node.read_value()
        assert advertised == operations.OPERATION_LIMITS
        ns = await c.get_namespace_index(NAMESPACE_URI)
        most = advertised["MaxNodesPerRead"]
        params = ua.ReadParameters(NodesToRead=[value_of(ua.NodeId(TEMPC, ns))] * most)
        got = await c.uaclient.read(params)
        assert len(got) == most and got[0].Value.Value == 4000.0
        params.NodesToRead.append(value_of(ua.NodeId(TEMPC, ns)))
        assert await refused(c.uaclient.read(params)) == TOO_MANY

    serve(service, scenario)


def test_the_bombs_are_refused_and_the_session_goes_on(service: ObjectService) -> None:
    """The attack's requests, each past its limit: Read of 100 000, Browse of 6 000,
    Write of 20 000, Call of 10 000, TranslateBrowsePaths of one path of 40 000
    elements: each BadTooManyOperations, and the same session reads on."""

    async def scenario(c: Client, iface: OpcUaInterface) -> None:
        ns = await c.get_namespace_index(NAMESPACE_URI)
        tempc = ua.NodeId(TEMPC, ns)
        clock = ua.NodeId(ua.ObjectIds.Server_ServerStatus_CurrentTime)  # (1.7 MB: < 4 MiB)
        read = ua.ReadParameters(NodesToRead=[value_of(clock)] * 100_000)
        assert await refused(c.uaclient.read(read)) == TOO_MANY
        desc = ua.BrowseDescription(NodeId=ua.NodeId("local", ns), ResultMask=63)
        browse = ua.BrowseParameters(NodesToBrowse=[desc] * 6_000)
        assert await refused(c.uaclient.browse(browse)) == TOO_MANY
        value = ua.DataValue(ua.Variant(4000.0, ua.VariantType.Double))
        write = ua.WriteParameters(
            NodesToWrite=[ua.WriteValue(tempc, ua.AttributeIds.Value, None, value)] * 20_000
        )
        assert await refused(c.uaclient.write(write)) == TOO_MANY
        call = ua.CallMethodRequest(ObjectId=ua.NodeId(2253), MethodId=ua.NodeId(11492))
        assert await refused(c.uaclient.call([call] * 10_000)) == TOO_MANY
        element = ua.RelativePathElement(
            ReferenceTypeId=ua.NodeId(33), TargetName=ua.QualifiedName("Server", 0)
        )
        path = ua.BrowsePath(
            StartingNode=ua.NodeId(84), RelativePath=ua.RelativePath(Elements=[element] * 40_000)
        )
        assert await refused(c.uaclient.translate_browsepaths_to_nodeids([path])) == TOO_MANY
        assert await c.get_node(tempc).read_value() == 4000.0

    serve(service, scenario)


def test_items_on_the_servers_own_nodes_count_against_the_caps(service: ObjectService) -> None:
    """Items on `i=2258` (CurrentTime) count like items on the machine's variables:
    past the session's cap they are BadTooManyMonitoredItems (before: 30 000 taken)."""

    async def scenario(c: Client, iface: OpcUaInterface) -> None:
        sub = await c.create_subscription(100, None)
        clock = c.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_CurrentTime))
        got = await sub.subscribe_data_change([clock] * 12)
        codes = [h if isinstance(h, ua.StatusCode) else None for h in got]
        assert codes[:10] == [None] * 10
        assert [c.value for c in codes[10:] if c is not None] == [
            ua.StatusCodes.BadTooManyMonitoredItems
        ] * 2

    serve(service, scenario, max_monitored_items_per_session=10)


def test_queue_sizes_are_revised_to_the_cap(service: ObjectService) -> None:
    """An item asking for a queue of 100 000 notifications gets `MAX_QUEUE_SIZE`, on
    Create and on Modify (before: granted; 1 000 such items held 430 MiB); one asking
    for 0 gets 1 (before: asyncua's largest, 10 000)."""

    async def scenario(c: Client, iface: OpcUaInterface) -> None:
        ns = await c.get_namespace_index(NAMESPACE_URI)
        sub = await c.create_subscription(100, None)
        item = ua.MonitoredItemCreateRequest()
        item.ItemToMonitor = value_of(ua.NodeId(TEMPC, ns))
        item.MonitoringMode = ua.MonitoringMode.Reporting
        item.RequestedParameters = ua.MonitoringParameters(
            ClientHandle=1, SamplingInterval=100, QueueSize=100_000, DiscardOldest=True
        )
        params = ua.CreateMonitoredItemsParameters(
            SubscriptionId=sub.subscription_id, ItemsToCreate=[item]
        )
        (created,) = await c.uaclient.create_monitored_items(params)
        assert created.StatusCode.is_good()
        assert created.RevisedQueueSize == guard.MAX_QUEUE_SIZE
        modify = ua.MonitoredItemModifyRequest(
            MonitoredItemId=created.MonitoredItemId,
            RequestedParameters=ua.MonitoringParameters(
                ClientHandle=1, SamplingInterval=100, QueueSize=100_000
            ),
        )
        (modified,) = await c.uaclient.modify_monitored_items(
            ua.ModifyMonitoredItemsParameters(
                SubscriptionId=sub.subscription_id, ItemsToModify=[modify]
            )
        )
        assert modified.RevisedQueueSize == guard.MAX_QUEUE_SIZE
        subs = iface.server.iserver.subscription_service.subscriptions
        items = subs[sub.subscription_id].monitored_item_srv._monitored_items
        assert [m.queue_size for m in items.values()] == [guard.MAX_QUEUE_SIZE]
        # Part 4 §5.12.1.5: a queue size of 0 (asyncua's client default) is a queue of one
        item.RequestedParameters.QueueSize = 0
        item.RequestedParameters.ClientHandle = 2
        (default,) = await c.uaclient.create_monitored_items(params)
        assert default.StatusCode.is_good() and default.RevisedQueueSize == 1

    serve(service, scenario)


def test_one_session_cannot_take_every_subscription(service: ObjectService) -> None:
    """A session's subscriptions past `SUBSCRIPTIONS_PER_SESSION` are
    BadTooManySubscriptions; another session still gets one. A publishing interval
    of 0 is revised to `MIN_PUBLISHING_MS`."""

    async def scenario(c: Client, iface: OpcUaInterface) -> None:
        params = ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=0,
            RequestedLifetimeCount=30,
            RequestedMaxKeepAliveCount=10,
            PublishingEnabled=True,
        )
        first = await c.uaclient.create_subscription(params, lambda _r: None)
        assert first.RevisedPublishingInterval == guard.MIN_PUBLISHING_MS
        for _ in range(guard.SUBSCRIPTIONS_PER_SESSION - 1):
            await c.uaclient.create_subscription(params, lambda _r: None)
        code = await refused(c.uaclient.create_subscription(params, lambda _r: None))
        assert code == ua.StatusCodes.BadTooManySubscriptions
        async with Client(iface.endpoint, timeout=10) as other:
            await other.create_subscription(100, None)

    serve(service, scenario)


# ---------------------------------------------------------------- stopping


@pytest.mark.slow
@pytest.mark.parametrize("reads", [False, True], ids=["client-not-reading", "client-reading"])
def test_sigterm_stops_the_server_during_a_browse_bomb(
    tmp_path: Path, lists_copy: Path, reads: bool
) -> None:
    """`geo-server run` with a client that keeps 300 Browse requests in flight (read or
    not; every 15th of 6 000 nodes, the others at the limit): SIGTERM ends it, exit 0,
    while the requests are still in flight (before: never while the client did not
    read). How long the stop takes is a benchmark's (bench/opcua_attacks.py: the issue
    asks for 2 s); the bound here only tells a hang from a stop."""
    endpoint = f"opc.tcp://127.0.0.1:{free_port()}"
    args = ["run", str(lists_copy), "--homed", "--no-zenoh", "--no-ads", "--no-modbus"]
    args += ["--opcua-endpoint", endpoint, "--status-period", "60"]
    with geo_server_running(args, tmp_path, "opcua: ready") as proc:

        async def attack() -> None:
            c = Client(endpoint, timeout=30)
            await c.connect()
            if not reads:
                c.uaclient.protocol.transport.pause_reading()
            desc = ua.BrowseDescription(
                NodeId=ua.NodeId(ua.ObjectIds.ObjectsFolder),
                BrowseDirection=ua.BrowseDirection.Both,
                ResultMask=63,
            )
            most = operations.OPERATION_LIMITS["MaxNodesPerBrowse"]
            at_limit = ua.BrowseParameters(NodesToBrowse=[desc] * most)
            bomb = ua.BrowseParameters(NodesToBrowse=[desc] * 6_000)
            pending = [
                asyncio.ensure_future(c.uaclient.browse(bomb if i % 15 == 0 else at_limit))
                for i in range(300)
            ]
            # The stop comes as the first answer does (a client that reads) or after
            # 0.5 s (one that does not): either way with requests in flight, counted
            # before the signal, since a closed connection fails every pending one.
            await asyncio.wait(pending, timeout=0.5, return_when=asyncio.FIRST_COMPLETED)
            in_flight = sum(not p.done() for p in pending)
            proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):  # (a hang: asserted below)
                await asyncio.to_thread(proc.wait, HANG_S)
            assert in_flight > 0
            for p in pending:
                p.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
            c.uaclient.disconnect_socket()

        asyncio.run(asyncio.wait_for(attack(), TIMEOUT))
        assert proc.returncode == 0, proc.returncode


# ---------------------------------------------------------------- a fleet's loop shares


def test_a_fleets_opcua_requests_draw_on_their_machines_share() -> None:
    """Two machines on one OPC UA server, machine a with a share whose clock stands
    still: a's Reads of 100 values use its 2 ms burst up, so the connection's next
    Read waits (a hold) for as long as the clock stands, while another client's Read of
    machine b is answered; when the clock moves on, a's Read is answered too. Before,
    OPC UA drew on no share: a flood on one machine took the loop from every other."""
    now = [0.0]
    fleet_share = LoopShare(rate=0.1, burst=0.002, clock=lambda: now[0])
    services = {
        name: ObjectService(Machine(load_machine(default_startup_list()), homed=True))
        for name in ("a", "b")
    }

    async def scenario() -> None:
        options = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", companion_models=False)
        iface = OpcUaInterface(services, options, {"a": fleet_share})
        share = iface.machine_shares["a"]  # (OPC UA's own thread: a share of it)
        # a's fleet rate (a tenth), at most half of OPC UA's fifth: a flood of a's
        # leaves the other machines' clients the other half
        assert (iface.loop_share.rate, share.rate, share.burst) == (0.2, 0.1, 0.002)
        await iface.start()
        try:
            async with (
                Client(iface.endpoint, timeout=10) as flood,
                Client(iface.endpoint, timeout=10) as other,
            ):
                ns = await flood.get_namespace_index(NAMESPACE_URI)
                most = operations.OPERATION_LIMITS["MaxNodesPerRead"]
                of_a = value_of(ua.NodeId("a/Axes/X/TEMPC/coefficient", ns))
                params = ua.ReadParameters(NodesToRead=[of_a] * most)
                waiting = await read_until_held(share, lambda: flood.uaclient.read(params))
                b = other.get_node(ua.NodeId("b/Axes/X/TEMPC/coefficient", ns))
                assert await b.read_value() == 4000.0
                assert not waiting.done()
                now[0] += 1.0  # the share is back
                got = await waiting
                assert got[0].Value.Value == 4000.0
                now[0] += 1.0  # (its CloseSession waits for the share too)
        finally:
            await iface.close()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


class _Connection:
    """A connection as `RequestMeter` knows it: any object it can refer to weakly."""

    def __init__(self, name: str) -> None:
        self.name = name


class _Ticking:
    """A share's clock that stands until `ticking`, then moves a second on at each look
    (each look finds the share back: the order is the tags' alone), and the order the
    connections' requests were let in."""

    def __init__(self) -> None:
        self.now = 0.0
        self.ticking = False
        self.order: list[str] = []
        self.let_in = asyncio.Event()

    def clock(self) -> float:
        if self.ticking:
            self.now += 1.0
        return self.now

    def entered(self, conn: _Connection) -> None:
        self.order.append(conn.name)
        self.let_in.set()

    async def first(self, meter: RequestMeter, share: LoopShare, n: int = 11) -> list[str]:
        """Once two connections are held (each counted once), the clock moves on: the
        first `n` let in."""
        while meter.waiting < 2:
            await asyncio.sleep(0)
        assert share.holds == 2 and self.order == []
        self.ticking = True
        while len(self.order) < n:
            await self.let_in.wait()
            self.let_in.clear()
        return self.order[:n]


def test_held_requests_are_let_in_in_fair_order() -> None:
    """`RequestMeter` without a server (start-time fair queuing, metering.py): while
    OPC UA's share is used up, `dear` keeps requests of 10 ms of processor time coming
    and `cheap` requests of 1 ms; both queued from the start. Let in by their tags, the
    cheap one runs ten requests for each of the dear one's: among the first eleven
    (tags below 9.5 ms) exactly one is dear's; in the order they came (or turn about)
    it would be six. Then a third connection that had asked nothing queues one request
    behind both: it goes before either's next one. The share's holds count each queued
    request once."""
    t = _Ticking()
    share = LoopShare(rate=0.5, burst=0.002, clock=t.clock)
    meter = RequestMeter(share, {})
    dear, cheap, once = _Connection("dear"), _Connection("cheap"), _Connection("once")

    async def scenario() -> None:
        share.charge(0.003)  # used up (a millisecond short), and the clock stands

        async def connection(conn: _Connection, cost: float, requests: int) -> None:
            for _ in range(requests):
                tickets = await meter.let_in(conn, [], lambda: None)
                t.entered(conn)
                meter.end(tickets, time.thread_time() - cost)

        both = [
            asyncio.ensure_future(connection(dear, 0.010, 5)),
            asyncio.ensure_future(connection(cheap, 0.001, 30)),
        ]
        assert (await t.first(meter, share)).count("dear") == 1, t.order
        t.ticking = False  # (held again: the next request of each waits)
        share.charge(0.003)
        while meter.waiting < 2:
            await asyncio.sleep(0)
        third = asyncio.ensure_future(connection(once, 0.001, 1))
        while meter.waiting < 3:
            await asyncio.sleep(0)
        seen = len(t.order)
        t.ticking = True
        await asyncio.gather(*both, third)
        assert t.order[seen] == "once", t.order[seen:]
        meter.close()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


def test_a_machines_held_requests_are_let_in_in_fair_order_too() -> None:
    """In a fleet, a machine's share of OPC UA (`RequestMeter.machines`) holds its
    connections in the same fair order as OPC UA's own share: while machine m1's share
    is used up, `flood` keeps requests of 10 ms of m1's processor time coming and
    `client` requests of 1 ms of it. Let in by their tags, among the first eleven
    exactly one is the flood's. (Before, each held connection slept on its own until
    m1's share was back and all went together: a client reading a machine beside a
    flood on it waited for every flooding connection's request, several seconds in a
    fleet of 30 with 4 flooding connections, and asyncua's client gave its connection
    up.) OPC UA's own share is not what holds them here (`rate` 1, a large burst)."""
    t = _Ticking()
    m1 = LoopShare(rate=0.1, burst=0.002, clock=t.clock)
    meter = RequestMeter(LoopShare(rate=1.0, burst=100.0), {"m1": m1})
    flood, client = _Connection("flood"), _Connection("client")

    async def scenario() -> None:
        async def connection(conn: _Connection, cost: float, requests: int) -> None:
            charged: list[str] = ["m1"]  # (its last request read m1)
            for _ in range(requests):
                tickets = await meter.let_in(conn, charged, lambda: None)
                t.entered(conn)
                began = RequestMeter.begin(tickets)
                RequestMeter.touch("m1")
                charged = meter.end(tickets, began - cost)

        assert meter.gates(["m1"]) == [meter.machines["m1"], meter.fair]
        m1.charge(0.003)  # used up, and the clock stands
        both = [
            asyncio.ensure_future(connection(flood, 0.010, 5)),
            asyncio.ensure_future(connection(client, 0.001, 30)),
        ]
        assert (await t.first(meter, m1)).count("flood") == 1, t.order
        await asyncio.gather(*both)
        assert m1.status["loop_s"] > 0.079  # (5 · 10 ms + 30 · 1 ms, charged to m1)
        # a request is charged to a machine's share at most what makes it wait after
        # one as long as OPC UA's own would (its burst over its rate: 0.05 / 1.0 s):
        # 0.1 · 0.05 s = 5 ms of m1's, though it took 0.5 s
        meter.overall.burst = 0.05
        before = m1.status["loop_s"]
        began = RequestMeter.begin()
        RequestMeter.touch("m1")
        meter.end(await meter.let_in(client, [], lambda: None), began - 0.5)
        assert m1.status["loop_s"] - before == pytest.approx(0.005)
        meter.close()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


def test_a_machines_queue_waits_for_the_request_it_let_in_to_begin() -> None:
    """A connection a machine's share let in may still wait at OPC UA's own (both used
    up): the machine's queue lets the next in only once that request began and then ran
    for a burst (or ended), not a burst after it was let in. (Before, it let one in
    every 2 ms, the machine share's burst: the whole queue got past the machine before
    any request of it was charged, and each then ran on the machine's share.) Three
    connections held at m1; m1 back, OPC UA's share still used up: one passes m1,
    two still wait there, also after a hundred of m1's bursts."""
    m1_back = [False]
    m1 = LoopShare(rate=0.1, burst=0.002, clock=lambda: 1000.0 if m1_back[0] else 0.0)
    overall = LoopShare(rate=0.2, burst=0.05, clock=lambda: 0.0)
    meter = RequestMeter(overall, {"m1": m1})
    conns = [_Connection(f"c{i}") for i in range(3)]

    async def scenario() -> None:
        m1.charge(0.003)
        overall.charge(0.06)  # (both used up; OPC UA's clock stands for good)
        waiting = [asyncio.ensure_future(meter.let_in(c, ["m1"], lambda: None)) for c in conns]
        while meter.machines["m1"].waiting < 3:
            await asyncio.sleep(0)
        m1_back[0] = True
        while meter.fair.waiting < 1:
            await asyncio.sleep(0)
        await asyncio.sleep(100 * m1.burst)  # (its dispatcher's timeouts come first)
        assert (meter.machines["m1"].waiting, meter.fair.waiting) == (2, 1)
        meter.close()
        await asyncio.gather(*waiting, return_exceptions=True)

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


def test_a_client_beside_a_flood_waits_for_one_request_of_each(
    service: ObjectService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Three connections each keep four Reads of 100 values in flight while OPC UA's
    share is used up (its clock stands still); a fourth client, connected before them,
    sends one Read of one value. When the clock moves on, the server answers at most
    one Read of each of the three before the fourth's (the order it ended them in,
    observed on the server: the clients' sockets may deliver in another). The three
    first read twice with the share free, so the fourth's own earlier requests are
    paid for in the queue's virtual time (metering.py). Measured before
    (bench/opcua_attacks.py's Read flood, and a client reading once every 0.1 s beside
    it): that client waited up to 2.4 s for one Read, and asyncua's client gave its
    connection up when its keep-alive probe waited a second; now at most 0.04 s. Here
    no client probes (`watchdog_intervall`): what is held is the test's to decide."""
    frozen: list[float | None] = [None]

    def clock() -> float:
        at = frozen[0]
        return time.monotonic() if at is None else at

    share = LoopShare(rate=0.1, burst=0.002, clock=clock)

    def client(iface: OpcUaInterface) -> Client:
        return Client(iface.endpoint, timeout=10, watchdog_intervall=3600.0)

    async def scenario() -> None:
        options = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", companion_models=False)
        iface = OpcUaInterface({"local": service}, options, loop_share=share)
        ended: list[int] = []  # the client port of each request the server ended
        end = iface.meter.end

        def recording(tickets: Any, began: float | None) -> Any:
            ended.append(tickets[-1].key.peer_name[1])
            return end(tickets, began)

        monkeypatch.setattr(iface.meter, "end", recording)
        await iface.start()
        try:
            async with (
                client(iface) as once,  # (first: its own requests are the oldest)
                client(iface) as f1,
                client(iface) as f2,
                client(iface) as f3,
            ):
                ns = await f1.get_namespace_index(NAMESPACE_URI)
                most = operations.OPERATION_LIMITS["MaxNodesPerRead"]
                tempc = value_of(ua.NodeId(TEMPC, ns))
                params = ua.ReadParameters(NodesToRead=[tempc] * most)
                for c in (f1, f2, f3, f1, f2, f3):
                    await c.uaclient.read(params)
                frozen[0] = time.monotonic() - 0.2  # 0.02 s of the share short
                flood = [
                    asyncio.ensure_future(c.uaclient.read(params))
                    for c in (f1, f2, f3)
                    for _ in range(4)
                ]
                while iface.meter.waiting < 3:  # (one held per connection)
                    await asyncio.sleep(0.01)
                single = ua.ReadParameters(NodesToRead=[tempc])
                mine = asyncio.ensure_future(once.uaclient.read(single))
                while iface.meter.waiting < 4:
                    await asyncio.sleep(0.01)
                ended.clear()
                frozen[0] = None
                assert (await mine)[0].Value.Value == 4000.0
                port = once.uaclient.protocol.transport.get_extra_info("sockname")[1]
                while port not in ended:  # (the server ends it after sending its answer)
                    await asyncio.sleep(0.01)
                before = ended[: ended.index(port)]
                assert len(before) == len(set(before)) <= 3, ended
                for got in await asyncio.gather(*flood):
                    assert got[0].Value.Value == 4000.0
        finally:
            await iface.close()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


def test_opcua_work_draws_on_its_share_of_the_loop(service: ObjectService) -> None:
    """One machine, OPC UA's share with a clock that stands still: after a Read past
    the burst, the next Read of any connection waits (a hold) until the clock moves on;
    ADS and Modbus, which draw on no OPC UA share, keep the rest of the loop. Before,
    a Read flood took 70 % of the loop and the ADS p99 went from 1 to 106 ms
    (bench/opcua_attacks.py)."""
    frozen: list[float | None] = [None]  # (the clock runs while the clients connect)

    def clock() -> float:
        return time.monotonic() if frozen[0] is None else frozen[0]

    share = LoopShare(rate=0.1, burst=0.002, clock=clock)
    now = [0.0]

    async def scenario() -> None:
        options = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", companion_models=False)
        iface = OpcUaInterface({"local": service}, options, loop_share=share)
        await iface.start()
        try:
            async with (
                Client(iface.endpoint, timeout=10) as first,
                Client(iface.endpoint, timeout=10) as second,
            ):
                ns = await first.get_namespace_index(NAMESPACE_URI)
                most = operations.OPERATION_LIMITS["MaxNodesPerRead"]
                params = ua.ReadParameters(NodesToRead=[value_of(ua.NodeId(TEMPC, ns))] * most)
                await asyncio.sleep(share.burst / share.rate)  # (a full burst)
                frozen[0] = now[0] = time.monotonic()
                first_held = await read_until_held(share, lambda: first.uaclient.read(params))
                waiting = await held(share, second.uaclient.read(params))
                await asyncio.sleep(0.05)
                assert not waiting.done() and not first_held.done()  # while the clock stands
                frozen[0] = None  # the clock runs, the share fills again
                assert (await waiting)[0].Value.Value == 4000.0
                assert (await first_held)[0].Value.Value == 4000.0
        finally:
            await iface.close()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


def test_publishing_draws_on_the_share_of_notifications(
    service: ObjectService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A subscription's Publish responses draw on OPC UA's share for notifications
    (guard.py `_metered_publishing`): while that share is used up no response goes out,
    then the item's newest value does — and however long it stays used up, a
    subscription publishes again `PUBLISH_HOLD_MAX` after its last publish (the share
    is everyone's: one that publishes seldom does not wait for a flood's turn). The item
    watches `i=2258` (CurrentTime), which asyncua itself writes every second, so only
    the publishing is held here, not our sampling. The share is used up by setting its
    clock 2 s back and holding it there (its only writer stays the OPC UA thread).
    Before, Publish responses drew on nothing: 1 000 items on a value changing every
    cycle, published every 10 ms, kept the OPC UA thread busy without a pause
    (bench/opcua_attacks.py `items`)."""
    frozen: list[float | None] = [None]

    def clock() -> float:
        at = frozen[0]
        return time.monotonic() if at is None else at

    share = LoopShare(rate=0.1, burst=0.002, clock=clock)

    async def scenario() -> None:
        options = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", companion_models=False)
        iface = OpcUaInterface({"local": service}, options, notify_share=share)
        await iface.start()
        got: asyncio.Queue[Any] = asyncio.Queue()

        class Handler:
            def datachange_notification(self, _node: Any, value: Any, _data: Any) -> None:
                got.put_nowait(value)

        try:
            async with Client(iface.endpoint, timeout=10) as c:
                sub = await c.create_subscription(50, Handler())
                now = c.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_CurrentTime))
                await sub.subscribe_data_change(now)
                await asyncio.wait_for(got.get(), 5)  # (its value when made)
                last = await asyncio.wait_for(got.get(), 5)  # (written a second later)
                # held as long as the share is used up
                monkeypatch.setattr(guard, "PUBLISH_HOLD_MAX", 60.0)
                holds = share.holds
                frozen[0] = time.monotonic() - 2.0  # 0.2 s of the share short
                await asyncio.sleep(2.5)  # two writes of CurrentTime, fifty periods
                assert got.empty() and share.holds > holds
                frozen[0] = None
                newest = await asyncio.wait_for(got.get(), 5)
                assert newest > last + datetime.timedelta(seconds=1.5)
                # at most `PUBLISH_HOLD_MAX` (0.5 s) after the last publish, used up or not
                monkeypatch.undo()
                frozen[0] = time.monotonic() - 2.0
                holds = share.holds
                after = await asyncio.wait_for(got.get(), 5)
                assert after > newest and share.holds > holds
        finally:
            await iface.close()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


def test_a_request_holding_asyncua_does_not_hold_the_other_interfaces() -> None:
    """asyncua runs on a thread and loop of its own: while an OPC UA Write to machine
    `held` cannot finish (its value's check does not return until the test releases
    it), Modbus of machine `free`, on the main loop, answers. Before, every OPC UA
    request ran on the loop ADS, Modbus and the web HMI share, so a request that took
    seconds held them all (issue 44 #7: a Browse of 10.7 s, an ADS read failing at
    5 s). The thread runs niced on Linux (docs/security.md, *No request holds the loop
    long*); the write itself is applied by the main loop (`_on_host`)."""
    armed, inside, release = threading.Event(), threading.Event(), threading.Event()

    class Held(ObjectService):
        def prepare_name(self, *args: Any, **kw: Any) -> Any:
            if armed.is_set():
                inside.set()
                release.wait(TIMEOUT)
            return super().prepare_name(*args, **kw)

    held = Held(Machine(load_machine(default_startup_list()), homed=True))
    free = ObjectService(Machine(load_machine(default_startup_list()), homed=True))

    async def scenario() -> None:
        options = OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", companion_models=False)
        opcua = OpcUaInterface({"held": held}, options)
        modbus = ModbusInterface(free, ModbusOptions(port=0))
        await opcua.start()
        await modbus.start()
        try:
            async with Client(opcua.endpoint, timeout=TIMEOUT) as client:
                ns = await client.get_namespace_index(NAMESPACE_URI)
                node = client.get_node(ua.NodeId("held/Axes/X/TEMPC/coefficient", ns))
                armed.set()
                value = ua.DataValue(ua.Variant(4100.0, ua.VariantType.Double))
                writing = asyncio.ensure_future(node.write_value(value))
                assert await asyncio.to_thread(inside.wait, TIMEOUT)  # the Write is held
                if sys.platform == "linux":  # (niced: the kernel lets the loop's thread in)
                    ours = [t for t in threading.enumerate() if t.name == "opcua"]
                    assert ours and all(_niceness(t.native_id) == OPCUA_NICE for t in ours)
                coefficient = free.info.dictionary.by_name("TEMPC::coefficient")
                assert await asyncio.to_thread(modbus_read, modbus.port, coefficient, TIMEOUT) == 0
                assert not writing.done()
                armed.clear()
                release.set()
                await writing  # (Good: a refusal raises; applied at the next cycle)
        finally:
            release.set()
            await modbus.close()
            await opcua.close()

    asyncio.run(asyncio.wait_for(scenario(), 2 * TIMEOUT))


def _niceness(native_id: int | None) -> int:
    stat = Path(f"/proc/self/task/{native_id}/stat").read_text()
    return int(stat[stat.rindex(")") + 2 :].split()[16])  # (field 19: nice)
