"""The guard in front of asyncua's server (docs/security.md, *OPC UA*; docs/design.md
§9.1, *The OPC UA guard*).

asyncua's server is written for a trusted network: sequential authentication tokens that
any connection may present, a session that may move to another secure channel before
its user is checked, a discovery registry anyone may fill, frames buffered whatever size
their header claims. This module knows asyncua's transport and sessions (internals.py
the rest: the address space, the services and subscriptions the interface hooks); it
changes them for one server instance only, never for the process:

- `start` replaces `Server.start` (its body, with `GuardedBinaryServer`): every
  connection gets a `GuardedProtocol`, which refuses a frame at its header (an unknown
  type, a chunk larger than the receive buffer, a Hello whose buffers are below the
  spec's 8192 bytes) and a `GuardedProcessor`, which closes a session with its channel.
- `guard` hooks the internal server: session ids and authentication tokens from a
  cryptographic random source, at most `SESSIONS_PER_CONNECTION` sessions per connection,
  a session only ever activated on the channel that created it, failed logins slowing
  the next attempt from that address (`LoginThrottle`), a password only inside an
  encrypted channel or an encrypted token, RegisterServer refused (not a discovery
  server), subscriptions answered only to the session that owns them, and a
  subscription's periodic publishing drawn on OPC UA's share for notifications.

`internals.RELIED_ON` holds the hash of the `Server.start` this replaces and of every
asyncua function it subclasses or hooks: tests/test_opcua_internals.py fails on an asyncua
where one changed, so the copy and the hooks are looked at again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import secrets
import time
import uuid
from collections.abc import Callable
from typing import Any

from asyncua import ua as _ua
from asyncua.common.utils import ServiceError
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.uaprocessor import UaProcessor

from geo_server.transports.opcua import operations
from geo_server.transports.opcua.logins import LoginThrottle
from geo_server.transports.opcua.metering import RequestMeter, Ticket
from geo_server.transports.share import LoopShare

log = logging.getLogger("geo_server.opcua")
ua: Any = _ua  # (asyncua's types: used as the wire's values, not checked here)

#: Part 6 §7.1.2.3: a Hello's ReceiveBufferSize and SendBufferSize are at least 8192
MIN_BUFFER = 8192
#: the largest request message this server takes (its chunks are at most the receive
#: buffer, 65535 bytes): a Write or Call of the operation limit fits many times over
MAX_REQUEST = 4 * 1024 * 1024
#: sessions one connection may hold at once (asyncua serves one per secure channel)
SESSIONS_PER_CONNECTION = 1
#: subscriptions one session may hold (BadTooManySubscriptions past it), so one client
#: cannot take the server's whole `OpcUaOptions.max_subscriptions`
SUBSCRIPTIONS_PER_SESSION = 16
#: the notifications a monitored item keeps between two Publish responses (its
#: RevisedQueueSize; asyncua's default cap is 10 000, 1 000 items then held 430 MiB)
MAX_QUEUE_SIZE = 16
#: Publish responses a subscription keeps until the client acknowledges them
MAX_UNACKED = 64
#: the shortest publishing interval (ms) a subscription gets (asyncua granted 0: a
#: publish loop that never sleeps)
MIN_PUBLISHING_MS = 10.0
#: the longest (seconds) a subscription's publishing waits for OPC UA's share of
#: notifications (`_metered_publishing`): twice a second at least, whatever the others do
PUBLISH_HOLD_MAX = 0.5
_MESSAGE_TYPES = (b"HEL", b"OPN", b"MSG", b"CLO")
_NONE_POLICY = "http://opcfoundation.org/UA/SecurityPolicy#None"


class MadeOnUse(dict[Any, Any]):
    """A dict whose misses ask `materialize(key)` to make what the key belongs to and
    look again: asyncua's `AddressSpace._nodes` with a fleet's copied machines made on
    first use (`lazy_nodes`), and the interface's variables alike
    (`OpcUaInterface._vars`). asyncua's own `load_aspace_shelf` swaps the same dict for
    a mapping that loads nodes when first asked for; its `AddressSpace` looks nodes up
    with `[]`, `get` and `in`. Iterating sees what is made so far."""

    def __init__(self, made: dict[Any, Any], materialize: Callable[[Any], bool]) -> None:
        super().__init__(made)
        self._materialize = materialize

    def __missing__(self, node_id: Any) -> Any:
        if self._materialize(node_id) and dict.__contains__(self, node_id):
            return dict.__getitem__(self, node_id)
        raise KeyError(node_id)

    def get(self, node_id: Any, default: Any = None) -> Any:
        try:
            return self[node_id]
        except KeyError:
            return default

    def __contains__(self, node_id: object) -> bool:
        return dict.__contains__(self, node_id) or (
            self._materialize(node_id) and dict.__contains__(self, node_id)
        )


def lazy_nodes(server: Any, materialize: Callable[[Any], bool]) -> None:
    """From now on, `server`'s address space makes a node it does not have yet with
    `materialize(node_id)` (True: made) when it is first asked for (`MadeOnUse`)."""
    aspace = server.iserver.aspace
    nodes = aspace._nodes
    if isinstance(nodes, MadeOnUse):
        nodes._materialize = materialize
        return
    if type(nodes) is not dict:  # (an asyncua that changed its address space)
        raise RuntimeError(f"asyncua's address space keeps its nodes in a {type(nodes)}")
    aspace._nodes = MadeOnUse(nodes, materialize)


def _address(name: Any) -> str:
    """The client's host from asyncua's session name (the connection's peer name)."""
    return str(name[0]) if isinstance(name, tuple) and name else str(name)


def _random_id() -> Any:
    return ua.NodeId(uuid.UUID(bytes=secrets.token_bytes(16)), 1, ua.NodeIdType.Guid)


def guard(server: Any, throttle: LoginThrottle, publishing: LoopShare) -> None:
    """Hook `server`'s internal server (this instance only; see the module);
    `publishing`: the share subscriptions publish on (`_metered_publishing`)."""
    iserver: Any = server.iserver
    create = iserver.create_session
    sessions: dict[Any, int] = {}  # connection (peer name) -> its open sessions

    def create_session(name: Any, external: bool = False) -> Any:
        """(asyncua's processor: `create_session(self.name, external=True)`)"""
        if not external:
            return create(name, external=False)
        if sessions.get(name, 0) >= SESSIONS_PER_CONNECTION:
            raise ServiceError(ua.StatusCodes.BadTooManySessions)
        session = create(name, external=True)
        iserver.unregister_external_session(session)  # (made under a sequential token)
        session.session_id, session.auth_token = _random_id(), _random_id()
        iserver.register_external_session(session)
        sessions[name] = sessions.get(name, 0) + 1
        _guard_session(session, iserver, throttle, sessions, publishing)
        return session

    def refuse(*_args: Any, **_kwargs: Any) -> Any:
        raise ServiceError(ua.StatusCodes.BadServiceUnsupported)

    iserver.create_session = create_session
    # a session is activated only on the secure channel that created it (Part 4 §5.6.3
    # lets a client move it, proving the same user; refused here: clients then create a
    # new one, and a token another connection learnt is worth nothing)
    iserver.lookup_external_session = lambda _token: None
    iserver.register_server = refuse  # not a discovery server
    iserver.register_server2 = refuse


def _guard_session(
    session: Any,
    iserver: Any,
    throttle: LoginThrottle,
    sessions: dict[Any, int],
    publishing: LoopShare,
) -> None:
    activate, close = session.activate_session, session.close_session
    address = _address(session.name)

    def activate_session(params: Any, peer_certificate: Any) -> Any:
        token = params.UserIdentityToken
        if isinstance(token, ua.UserNameIdentityToken) and not _protected(token, peer_certificate):
            raise ServiceError(ua.StatusCodes.BadIdentityTokenInvalid)
        if not throttle.allowed(address):
            throttle.failed(address)
            raise ServiceError(ua.StatusCodes.BadUserAccessDenied)
        try:
            result = activate(params, peer_certificate)
        except ServiceError as exc:
            if exc.code in _LOGIN_FAILURES:
                throttle.failed(address)
            raise
        throttle.succeeded(address)
        return result

    async def close_session(delete_subs: bool = True) -> None:
        left = sessions.get(session.name, 0) - 1
        if left > 0:
            sessions[session.name] = left
        else:
            sessions.pop(session.name, None)
        session.close_session = close  # (once)
        await close(True)  # a session's subscriptions never outlive it here

    session.activate_session = activate_session
    session.close_session = close_session
    _own_subscriptions(session, iserver)
    _bound_subscriptions(session, iserver, publishing)


_LOGIN_FAILURES = (
    ua.StatusCodes.BadUserAccessDenied,
    ua.StatusCodes.BadIdentityTokenInvalid,
    ua.StatusCodes.BadIdentityTokenRejected,
)


def _protected(token: Any, peer_certificate: Any) -> bool:
    """A password travels encrypted: inside a signed and encrypted channel (the client
    showed its certificate), or encrypted itself with the server's key (the policy of
    the unencrypted endpoint asks for that)."""
    return bool(peer_certificate) or bool(token.EncryptionAlgorithm)


def _own_subscriptions(session: Any, iserver: Any) -> None:
    """Operations on subscriptions by id answer only for the session's own: another
    session's id is `BadSubscriptionIdInvalid`, as an id that does not exist."""
    subs = iserver.subscription_service

    def mine(sid: Any) -> bool:
        sub = subs.subscriptions.get(sid)
        return sub is not None and sub.session_id == session.session_id

    delete, set_mode = session.delete_subscriptions, session.set_publishing_mode
    bad = ua.StatusCode(ua.StatusCodes.BadSubscriptionIdInvalid)

    async def delete_subscriptions(ids: list[Any]) -> list[Any]:
        own = [mine(i) for i in ids]
        done = iter(
            await delete([i for i, m in zip(ids, own, strict=True) if m]) if any(own) else ()
        )
        return [next(done) if m else bad for m in own]

    async def set_publishing_mode(params: Any) -> list[Any]:
        own = [mine(i) for i in params.SubscriptionIds]
        params.SubscriptionIds = [i for i, m in zip(params.SubscriptionIds, own, strict=True) if m]
        done = iter(await set_mode(params) if any(own) else ())
        return [next(done) if m else bad for m in own]

    for name in ("modify_subscription", "republish"):
        _check_id(session, name, mine)
    _check_items(session, "create_monitored_items", mine)
    _check_items(session, "modify_monitored_items", mine)
    _check_items(session, "set_monitoring_mode", mine)
    _check_items(session, "delete_monitored_items", mine)
    session.delete_subscriptions = delete_subscriptions
    session.set_publishing_mode = set_publishing_mode


def _bound_subscriptions(session: Any, iserver: Any, publishing: LoopShare) -> None:
    """At most `SUBSCRIPTIONS_PER_SESSION` subscriptions, published no faster than
    `MIN_PUBLISHING_MS` and on the share `publishing` (`_metered_publishing`); item queues
    revised to `MAX_QUEUE_SIZE` on Modify too (asyncua revises them on Create only)."""
    subs = iserver.subscription_service
    create, modify = session.create_subscription, session.modify_monitored_items
    create_items = session.create_monitored_items

    async def create_monitored_items(params: Any) -> Any:
        for item in params.ItemsToCreate:
            asked = item.RequestedParameters
            asked.QueueSize = _queue_size(int(asked.QueueSize))
        return await create_items(params)

    async def create_subscription(params: Any, *args: Any, **kwargs: Any) -> Any:
        held = sum(1 for s in subs.subscriptions.values() if s.session_id == session.session_id)
        if held >= SUBSCRIPTIONS_PER_SESSION:
            raise ServiceError(ua.StatusCodes.BadTooManySubscriptions)
        asked = float(params.RequestedPublishingInterval)
        # (NaN or infinity: the fastest allowed, as a negative interval; max() keeps NaN)
        params.RequestedPublishingInterval = (
            max(asked, MIN_PUBLISHING_MS) if math.isfinite(asked) else MIN_PUBLISHING_MS
        )
        result = await create(params, *args, **kwargs)
        made = subs.subscriptions.get(result.SubscriptionId)
        if made is not None:
            _metered_publishing(made, publishing)
        return result

    async def modify_monitored_items(params: Any) -> Any:
        results = await modify(params)
        sub = subs.subscriptions.get(params.SubscriptionId)
        items = {} if sub is None else sub.monitored_item_srv._monitored_items
        for item, result in zip(params.ItemsToModify, results, strict=True):
            size = _queue_size(int(item.RequestedParameters.QueueSize))
            result.RevisedQueueSize = size
            mdata = items.get(item.MonitoredItemId)
            if mdata is not None:
                mdata.queue_size = size
        return results

    session.create_subscription = create_subscription
    session.create_monitored_items = create_monitored_items
    session.modify_monitored_items = modify_monitored_items


def _metered_publishing(sub: Any, share: LoopShare) -> None:
    """`sub`'s periodic publishing drawn on `share`, OPC UA's share of its thread for
    notifications (`OpcUaOptions.loop_share`; its sampling draws on it too). Building and
    sending a Publish response is asyncua's pure Python, about 10 µs a notification: 1 000
    items on a value that changes every cycle, published every 10 ms, kept its thread
    busy without a pause (issue 44). A period that finds the share used up publishes
    nothing, unless the subscription's last period that did is `PUBLISH_HOLD_MAX` ago:
    the share is everyone's, and a subscription that publishes seldom (an HMI's, every
    second) must not wait for a flooding one's turn — nor a keep-alive for long. Held
    items keep their newest notifications, as many as their queue size (a queue of one:
    the newest value). A response to a Publish request that waited for results
    (`requestdata`) is that request's, charged to the request meter (`GuardedProtocol`).
    asyncua calls `publish_results` without a request only from the periodic loop and
    from `_trigger_publish`, which publishes only for an interval of 0 (never here:
    `MIN_PUBLISHING_MS`)."""
    publish = sub.publish_results
    last = [time.monotonic()]

    async def publish_results(requestdata: Any = None) -> bool:
        if requestdata is not None:
            return bool(await publish(requestdata))
        now = time.monotonic()
        if share.wait() > 0.0 and now - last[0] < PUBLISH_HOLD_MAX:
            return False
        last[0] = now
        began = time.thread_time()
        try:
            return bool(await publish())
        finally:
            share.charge(time.thread_time() - began)

    sub.publish_results = publish_results


def _queue_size(asked: int) -> int:
    """Part 4 §5.12.1.5: a requested queue size of 0 or 1 is a queue of one (asyncua
    gave 0 its largest queue); larger ones at most `MAX_QUEUE_SIZE`."""
    return max(1, min(asked, MAX_QUEUE_SIZE))


def _check_id(session: Any, name: str, mine: Any) -> None:
    """`session.name(params, ...)` refused unless `params.SubscriptionId` is its own."""
    call = getattr(session, name)

    def checked(params: Any, *args: Any) -> Any:
        if not mine(params.SubscriptionId):
            raise ServiceError(ua.StatusCodes.BadSubscriptionIdInvalid)
        return call(params, *args)

    setattr(session, name, checked)


def _check_items(session: Any, name: str, mine: Any) -> None:
    call = getattr(session, name)

    async def checked(params: Any, *args: Any) -> Any:
        if not mine(params.SubscriptionId):
            raise ServiceError(ua.StatusCodes.BadSubscriptionIdInvalid)
        return await call(params, *args)

    setattr(session, name, checked)


# ---------------------------------------------------------------------- the transport


class GuardedProcessor(UaProcessor):
    """asyncua's request processor for one connection; its session ends with it (no
    session moves to another channel here, so none is kept for one)."""

    def _should_close_session_on_transport_loss(self) -> bool:
        return self.session is not None

    async def _process_message(self, typeid: Any, requesthdr: Any, seqhdr: Any, body: Any) -> Any:
        """A request past an operation limit is refused before it is decoded
        (`operations.excess`: BadTooManyOperations; a body too short for its counts:
        BadDecodingError)."""
        request = _REQUEST_NAMES.get(typeid)
        if request is not None and self.session is not None and self.session.is_activated():
            try:
                over = operations.excess(request, bytes(body.copy()))
            except operations.Malformed as exc:
                log.warning("opcua: %s: a %s refused: %s", self.name, request, exc)
                raise ServiceError(ua.StatusCodes.BadDecodingError) from None
            if over is not None:
                log.info("opcua: %s: a %s refused: %s", self.name, request, over)
                raise ServiceError(ua.StatusCodes.BadTooManyOperations)
        process: Any = super()._process_message  # (asyncua's, untyped)
        return await process(typeid, requesthdr, seqhdr, body)


#: the binary encoding id of each request whose operations are counted -> its name
_REQUEST_NAMES: dict[Any, str] = {
    ua.NodeId(getattr(ua.ObjectIds, f"{name}_Encoding_DefaultBinary")): name
    for name in operations.bounded_requests()
}


class GuardedProtocol(OPCUAProtocol):
    """One connection: a frame is refused at its header, before its body is read; while
    the client does not read its answers (the transport's write buffer is over its high
    mark), its requests are neither read nor processed, and after `unread_close_s` it is
    closed — what one client can make the server hold is one answer and the buffer."""

    unread_close_s = 10.0
    #: the loop time of each request charged to loop shares (metering.py)
    meter: RequestMeter

    def connection_made(self, transport: Any) -> None:
        self._writable = asyncio.Event()
        self._writable.set()
        self._unread: asyncio.TimerHandle | None = None
        self._held = False  # reading paused for a used-up share (`_process_one_msg`)
        self._charged: list[str] = []  # the machines whose shares its last request drew on
        super().connection_made(transport)
        if self.processor is not None:  # (None: refused at max_connections)
            processor: Any = GuardedProcessor(self.iserver, self.transport, self.limits)
            processor.set_policies(self.policies)
            self.processor = processor

    def pause_writing(self) -> None:
        self._writable.clear()
        if self.transport is not None:
            self.transport.pause_reading()
            loop = asyncio.get_running_loop()
            if self._unread is None:
                self._unread = loop.call_later(self.unread_close_s, self._close_unread)

    def resume_writing(self) -> None:
        self._writable.set()
        if self._unread is not None:
            self._unread.cancel()
            self._unread = None
        if self.transport is not None and not self.transport.is_closing() and not self._held:
            self.transport.resume_reading()

    def _close_unread(self) -> None:
        self._unread = None
        if self.transport is not None and not self._writable.is_set():
            log.warning(
                "opcua: closing %s: it read none of its answers for %g s",
                self.peer_name,
                self.unread_close_s,
            )
            self.transport.abort()  # (a graceful close would wait for the unread answers)

    async def _process_one_msg(self, header: Any, buf: Any) -> bool:
        await self._writable.wait()  # the next request once the client reads again
        # one request per turn of the loop: asyncua takes the queued requests of a
        # connection without ever yielding, so a burst of them held every interface
        await asyncio.sleep(0)
        meter = self.meter
        tickets = await self._wait_for_shares(meter)
        began = None
        try:
            await meter.take_turn()
            began = meter.begin(tickets)
            return bool(await super()._process_one_msg(header, buf))
        finally:
            self._charged = meter.end(tickets, began)

    async def _wait_for_shares(self, meter: RequestMeter) -> list[Ticket]:
        """Until the shares of the machines its last request touched, then OPC UA's
        own, let it in (`RequestMeter.let_in`: each in fair order while it is used up),
        the connection is neither read nor served (docs/design.md §13.1)."""
        try:
            return await meter.let_in(self, self._charged, self._hold)
        finally:
            if self._held:
                self._held = False
                transport = self.transport
                if transport is not None and not transport.is_closing() and self._writable.is_set():
                    transport.resume_reading()

    def _hold(self) -> None:
        if not self._held:
            self._held = True
            if self.transport is not None:
                self.transport.pause_reading()

    def connection_lost(self, ex: BaseException | None) -> None:
        if self._unread is not None:
            self._unread.cancel()
        self._writable.set()  # (the processing loop ends with the connection)
        super().connection_lost(ex)

    def data_received(self, data: bytes) -> None:
        problem = self._refused(
            self._buffer[:28] if len(self._buffer) >= 28 else self._buffer + data[:28]
        )
        if problem is not None:
            self._refuse(*problem)
            return
        super().data_received(data)
        if self.transport is not None and not self.transport.is_closing() and self._buffer:
            problem = self._refused(self._buffer[:28])
            if problem is not None:
                self._refuse(*problem)

    def _refused(self, head: bytes) -> tuple[int, str] | None:
        """Why the frame starting with `head` is refused, or None (also: not yet known)."""
        if len(head) < 8:
            return None
        kind, size = head[:3], int.from_bytes(head[4:8], "little")
        if kind not in _MESSAGE_TYPES:
            return ua.StatusCodes.BadTcpMessageTypeInvalid, f"message type {kind!r}"
        if size > self.limits.max_recv_buffer:
            return (
                ua.StatusCodes.BadTcpMessageTooLarge,
                f"a chunk of {size} bytes (the receive buffer is {self.limits.max_recv_buffer})",
            )
        if kind == b"HEL" and len(head) >= 20:
            receive, send = (int.from_bytes(head[i : i + 4], "little") for i in (12, 16))
            if min(receive, send) < MIN_BUFFER:
                return (
                    ua.StatusCodes.BadConnectionRejected,
                    f"buffer sizes {receive}/{send} below {MIN_BUFFER} (Part 6 §7.1.2.3)",
                )
        return None

    def _refuse(self, code: int, why: str) -> None:
        log.warning("opcua: %s refused: %s", self.peer_name, why)
        self._buffer = b""
        if self.transport is not None and not self.transport.is_closing():
            from asyncua.ua import ua_binary

            to_binary: Any = ua_binary.uatcp_to_binary
            err = ua.ErrorMessage(ua.StatusCode(code), why)
            self.transport.write(to_binary(ua.MessageType.Error, err))
            self.transport.close()


class GuardedBinaryServer(BinaryServer):
    unread_close_s = 10.0
    meter: RequestMeter

    def _make_protocol(self) -> GuardedProtocol:
        protocol = GuardedProtocol(
            iserver=self.iserver,
            policies=self._policies,
            clients=self.clients,
            closing_tasks=self.closing_tasks,
            limits=self.limits,
        )
        protocol.unread_close_s = self.unread_close_s
        protocol.meter = self.meter
        return protocol


async def advertise(server: Any, capabilities: dict[str, int]) -> None:
    """Write the limits into `Server/ServerCapabilities` (Part 5 §6.3.2, §6.3.11): the
    operation limits, the guard's own, and `capabilities` (name -> value) of the
    interface's options. asyncua advertised 10 000 operations and enforced none."""
    values = {f"OperationLimits_{k}": v for k, v in operations.OPERATION_LIMITS.items()}
    values |= {
        "MaxSubscriptionsPerSession": SUBSCRIPTIONS_PER_SESSION,
        "MaxMonitoredItemsQueueSize": MAX_QUEUE_SIZE,
    }
    values |= capabilities
    params = ua.WriteParameters()
    for name, value in values.items():
        node = ua.NodeId(getattr(ua.ObjectIds, f"Server_ServerCapabilities_{name}"))
        dv = ua.DataValue(ua.Variant(value, ua.VariantType.UInt32))
        params.NodesToWrite.append(ua.WriteValue(node, ua.AttributeIds.Value, None, dv))
    for name, status in zip(values, await server.iserver.isession.write(params), strict=True):
        if not status.is_good():
            raise RuntimeError(f"ServerCapabilities/{name}: {status}")


async def start(server: Any, unread_close_s: float, meter: RequestMeter) -> None:
    """`Server.start` of asyncua 2.1 (`internals.RELIED_ON`) with the guarded transport, and
    requests bounded by `MAX_REQUEST`; a client that reads no answers for
    `unread_close_s` is closed; `meter` charges requests to loop shares (metering.py)."""
    iserver = server.iserver
    iserver.max_monitored_item_queue_size = MAX_QUEUE_SIZE
    # Publish responses a client has not acknowledged, kept for Republish (asyncua:
    # 5000 of any size each)
    iserver.max_unacked_messages_per_subscription = MAX_UNACKED
    limits = server.limits
    limits.max_message_size = MAX_REQUEST
    limits.max_chunk_count = MAX_REQUEST // limits.max_recv_buffer + 1
    await server._setup_server_nodes()
    await server.iserver.start()
    try:
        host, port = server._get_bind_socket_info()
        server.bserver = GuardedBinaryServer(server.iserver, host, port, limits)
        server.bserver.unread_close_s = unread_close_s
        server.bserver.meter = meter
        server.bserver.set_policies(server._policies)
        await server.bserver.start()
    except Exception:
        await server.iserver.stop()
        raise


async def stop(server: Any) -> None:
    """`Server.stop` at once, whatever the clients do: their connections are aborted
    (a graceful close waits for the answers a client does not read), and the task
    asyncua uses to tick `ServerStatus/CurrentTime` is cancelled (`iserver.stop` waits
    for its one-second sleep)."""
    iserver = server.iserver
    for transport in list(iserver.asyncio_transports):
        transport.abort()
    ticking, iserver.time_task = iserver.time_task, None
    if ticking is not None:
        ticking.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await ticking
    await server.stop()


__all__ = ["advertise", "guard", "start", "stop"]
