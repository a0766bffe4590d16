"""The guard in front of asyncua's server (docs/security.md, *OPC UA*; docs/design.md
§9.1, *The OPC UA guard*).

asyncua's server is written for a trusted network: sequential authentication tokens that
any connection may present, a session that may move to another secure channel before
its user is checked, a discovery registry anyone may fill, frames buffered whatever size
their header claims. This module is the one place that knows asyncua's server internals;
it changes them for one server instance only, never for the process:

- `start` replaces `Server.start` (its body, with `GuardedBinaryServer`): every
  connection gets a `GuardedProtocol`, which refuses a frame at its header (an unknown
  type, a chunk larger than the receive buffer, a Hello whose buffers are below the
  spec's 8192 bytes) and a `GuardedProcessor`, which closes a session with its channel.
- `guard` hooks the internal server: session ids and authentication tokens from a
  cryptographic random source, at most `SESSIONS_PER_CONNECTION` sessions per connection,
  a session only ever activated on the channel that created it, failed logins slowing
  the next attempt from that address (`LoginThrottle`), a password only inside an
  encrypted channel or an encrypted token, RegisterServer refused (not a discovery
  server), subscriptions answered only to the session that owns them.

`ASYNCUA_START` is the hash of the `Server.start` this replaces: tests/test_opcua_guard.py
fails on an asyncua whose start changed, so the copy is looked at again.
"""

from __future__ import annotations

import asyncio
import hashlib
import inspect
import logging
import secrets
import uuid
from typing import Any

from asyncua import Server
from asyncua import ua as _ua
from asyncua.common.utils import ServiceError
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.uaprocessor import UaProcessor

from geo_server.transports.opcua.logins import LoginThrottle

log = logging.getLogger("geo_server.opcua")
ua: Any = _ua  # (asyncua's types: used as the wire's values, not checked here)

#: sha256 of `inspect.getsource(asyncua.Server.start)` that `start` copies (asyncua 2.1)
ASYNCUA_START = "0e7d0b97d12c9075cbbca20bf115f77b371aab02997bc61bb302b607755b6579"

#: Part 6 §7.1.2.3: a Hello's ReceiveBufferSize and SendBufferSize are at least 8192
MIN_BUFFER = 8192
#: the largest request message this server takes (its chunks are at most the receive
#: buffer, 65535 bytes): a Write or Call of the operation limit fits many times over
MAX_REQUEST = 4 * 1024 * 1024
#: sessions one connection may hold at once (asyncua serves one per secure channel)
SESSIONS_PER_CONNECTION = 1
_MESSAGE_TYPES = (b"HEL", b"OPN", b"MSG", b"CLO")
_NONE_POLICY = "http://opcfoundation.org/UA/SecurityPolicy#None"


def asyncua_start_hash() -> str:
    return hashlib.sha256(inspect.getsource(Server.start).encode()).hexdigest()


def _address(name: Any) -> str:
    """The client's host from asyncua's session name (the connection's peer name)."""
    return str(name[0]) if isinstance(name, tuple) and name else str(name)


def _random_id() -> Any:
    return ua.NodeId(uuid.UUID(bytes=secrets.token_bytes(16)), 1, ua.NodeIdType.Guid)


def guard(server: Any, throttle: LoginThrottle) -> None:
    """Hook `server`'s internal server (this instance only; see the module)."""
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
        _guard_session(session, iserver, throttle, sessions)
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
    session: Any, iserver: Any, throttle: LoginThrottle, sessions: dict[Any, int]
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


class GuardedProtocol(OPCUAProtocol):
    """One connection: a frame is refused at its header, before its body is read; while
    the client does not read its answers (the transport's write buffer is over its high
    mark), its requests are neither read nor processed, and after `unread_close_s` it is
    closed — what one client can make the server hold is one answer and the buffer."""

    unread_close_s = 10.0

    def connection_made(self, transport: Any) -> None:
        self._writable = asyncio.Event()
        self._writable.set()
        self._unread: asyncio.TimerHandle | None = None
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
        if self.transport is not None and not self.transport.is_closing():
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
        return bool(await super()._process_one_msg(header, buf))

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

    def _make_protocol(self) -> GuardedProtocol:
        protocol = GuardedProtocol(
            iserver=self.iserver,
            policies=self._policies,
            clients=self.clients,
            closing_tasks=self.closing_tasks,
            limits=self.limits,
        )
        protocol.unread_close_s = self.unread_close_s
        return protocol


async def start(server: Any, unread_close_s: float = 10.0) -> None:
    """`Server.start` of asyncua 2.1 (`ASYNCUA_START`) with the guarded transport, and
    requests bounded by `MAX_REQUEST`; a client that reads no answers for
    `unread_close_s` is closed."""
    limits = server.limits
    limits.max_message_size = MAX_REQUEST
    limits.max_chunk_count = MAX_REQUEST // limits.max_recv_buffer + 1
    await server._setup_server_nodes()
    await server.iserver.start()
    try:
        host, port = server._get_bind_socket_info()
        server.bserver = GuardedBinaryServer(server.iserver, host, port, limits)
        server.bserver.unread_close_s = unread_close_s
        server.bserver.set_policies(server._policies)
        await server.bserver.start()
    except Exception:
        await server.iserver.stop()
        raise


__all__ = ["asyncua_start_hash", "guard", "start"]
