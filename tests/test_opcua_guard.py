"""The OPC UA guard (geo_server/transports/opcua/guard.py, docs/security.md *OPC UA*),
attacked the way a hostile local process would: raw frames on a socket, and asyncua's
own client driven below its session logic (another connection's token, a plaintext
password, a second session on one connection, another session's subscription).

Each of these attacks succeeded against the server before the guard.
"""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.ua.uaerrors import UaStatusCodeError

from geo_server.service import ObjectService
from geo_server.transports.opcua import logins
from geo_server.transports.opcua.logins import LoginThrottle
from geo_server.transports.opcua.server import OpcUaInterface, OpcUaOptions
from geo_server.transports.opcua.space import NAMESPACE_URI

TIMEOUT = 30.0
TEMPC = "local/Axes/X/TEMPC/coefficient"


def run(scenario: Callable[[], Awaitable[None]]) -> None:
    async def bounded() -> None:
        await asyncio.wait_for(scenario(), TIMEOUT)

    asyncio.run(bounded())


async def started(service: ObjectService, **kw: Any) -> OpcUaInterface:
    iface = OpcUaInterface(
        {"local": service},
        OpcUaOptions(endpoint="opc.tcp://127.0.0.1:0", **{"companion_models": False, **kw}),
    )
    await iface.start()
    return iface


def client(iface: OpcUaInterface, user: str | None = None, password: str | None = None) -> Client:
    c = Client(iface.endpoint, timeout=10)
    if user is not None and password is not None:
        c.set_user(user)
        c.set_password(password)
    return c


async def channel_only(iface: OpcUaInterface) -> Client:
    """A connection with a secure channel (None) and no session of its own."""
    c = Client(iface.endpoint, timeout=10)
    await c.connect_socket()
    await c.send_hello()
    await c.open_secure_channel()
    return c


def read_params(ns: int) -> Any:
    rv = ua.ReadValueId()
    rv.NodeId = ua.NodeId(TEMPC, ns)
    rv.AttributeId = ua.AttributeIds.Value
    params = ua.ReadParameters()
    params.NodesToRead = [rv]
    return params


def test_another_connection_cannot_use_a_session_token(
    service: ObjectService, tmp_path: Path
) -> None:
    """The attacker knows the victim's authentication token (guessed or sniffed), sends
    its own ActivateSession with it on its own channel (refused: wrong password), then
    reads and writes with it. Before: Good, and the write landed."""

    async def scenario() -> None:
        iface = await started(service, user="op", password="s3cret", cert_dir=tmp_path)
        try:
            async with client(iface, "op", "s3cret") as victim:
                ns = await victim.get_namespace_index(NAMESPACE_URI)
                token = victim.uaclient.protocol.authentication_token
                assert token.NodeIdType == ua.NodeIdType.Guid  # random, not 1001, 1002 …
                attacker = await channel_only(iface)
                try:
                    attacker.uaclient.protocol.authentication_token = token
                    params = ua.ActivateSessionParameters()
                    params.UserIdentityToken = ua.AnonymousIdentityToken()
                    with pytest.raises(UaStatusCodeError):
                        await attacker.uaclient.activate_session(params)
                    with pytest.raises(UaStatusCodeError) as err:
                        await attacker.uaclient.read(read_params(ns))
                    assert err.value.code in (
                        ua.StatusCodes.BadSessionIdInvalid,
                        ua.StatusCodes.BadUserAccessDenied,
                        ua.StatusCodes.BadSessionNotActivated,
                    )
                finally:
                    attacker.disconnect_socket()
                # the victim's session is untouched
                node = victim.get_node(ua.NodeId(TEMPC, ns))
                assert await node.read_value() == 4000.0
        finally:
            await iface.close()

    run(scenario)


def test_two_sessions_get_unrelated_tokens(service: ObjectService) -> None:
    async def scenario() -> None:
        iface = await started(service)
        try:
            async with client(iface) as a, client(iface) as b:
                ta = a.uaclient.protocol.authentication_token
                tb = b.uaclient.protocol.authentication_token
                assert ta.NodeIdType == tb.NodeIdType == ua.NodeIdType.Guid
                assert ta != tb
        finally:
            await iface.close()

    run(scenario)


def test_failed_logins_slow_the_next_attempt_and_are_logged_boundedly(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A clock that stands still: after n failures from an address its next attempt is
    refused unchecked until 0.05 s · 2^(n-1) (at most 2 s) has passed."""
    now = [100.0]
    t = LoginThrottle(clock=lambda: now[0])
    assert t.allowed("10.0.0.1")
    for _ in range(100):
        t.failed("10.0.0.1")
    assert not t.allowed("10.0.0.1") and t.allowed("10.0.0.2")
    now[0] += logins.LOGIN_BACKOFF_MAX_S - 0.001
    assert not t.allowed("10.0.0.1")
    now[0] += 0.002
    assert t.allowed("10.0.0.1")
    assert len([r for r in caplog.records if "failed login" in r.getMessage()]) == 1
    t.succeeded("10.0.0.1")
    t.failed("10.0.0.1")
    now[0] += logins.LOGIN_BACKOFF_FIRST_S - 0.001
    assert not t.allowed("10.0.0.1")


def test_guessing_passwords_on_the_wire_is_throttled(
    service: ObjectService, tmp_path: Path
) -> None:
    """Wrong passwords as fast as asyncua's client sends them, then the right one at
    once: refused (the throttle's clock stands still, so the backoff never ends); a new
    address would be let in."""
    frozen = [0.0]

    async def scenario() -> None:
        iface = OpcUaInterface(
            {"local": service},
            OpcUaOptions(
                endpoint="opc.tcp://127.0.0.1:0", user="op", password="s3cret", cert_dir=tmp_path
            ),
        )
        iface.login_throttle = LoginThrottle(clock=lambda: frozen[0])
        await iface.start()
        try:
            for password in ("a", "b", "s3cret"):
                with pytest.raises(UaStatusCodeError) as err:
                    async with client(iface, "op", password):
                        pass
                assert err.value.code == ua.StatusCodes.BadUserAccessDenied
            frozen[0] += logins.LOGIN_BACKOFF_MAX_S
            async with client(iface, "op", "s3cret") as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                assert await c.get_node(ua.NodeId(TEMPC, ns)).read_value() == 4000.0
        finally:
            await iface.close()

    run(scenario)


def test_a_plaintext_password_on_the_unencrypted_endpoint_is_refused(
    service: ObjectService, tmp_path: Path
) -> None:
    """The None endpoint's token policy asks for the password encrypted with the server's
    key: one sent as plain text is refused, the right one included."""

    async def scenario() -> None:
        iface = await started(service, user="op", password="s3cret", cert_dir=tmp_path)
        try:
            c = await channel_only(iface)
            try:
                created = await c.uaclient.create_session(ua.CreateSessionParameters(
                    EndpointUrl=iface.endpoint, SessionName="plain",
                    RequestedSessionTimeout=10_000,
                ))  # fmt: skip
                c.uaclient.protocol.authentication_token = created.AuthenticationToken
                params = ua.ActivateSessionParameters()
                params.UserIdentityToken = ua.UserNameIdentityToken(
                    PolicyId="username", UserName="op", Password=b"s3cret"
                )
                with pytest.raises(UaStatusCodeError) as err:
                    await c.uaclient.activate_session(params)
                assert err.value.code == ua.StatusCodes.BadIdentityTokenInvalid
            finally:
                c.disconnect_socket()
        finally:
            await iface.close()

    run(scenario)


def test_register_server_is_refused_and_nothing_is_kept(service: ObjectService) -> None:
    """geo-server is no discovery server: RegisterServer(2) without a session used to be
    kept, and handed to everyone by FindServers."""

    async def scenario() -> None:
        iface = await started(service, read_only=True)
        try:
            c = await channel_only(iface)
            try:
                rogue = ua.RegisteredServer(
                    ServerUri="urn:rogue", ProductUri="urn:rogue",
                    ServerNames=[ua.LocalizedText("rogue")], ServerType=ua.ApplicationType.Server,
                    DiscoveryUrls=["opc.tcp://10.0.0.66:4840"], IsOnline=True,
                )  # fmt: skip
                with pytest.raises(UaStatusCodeError) as err:
                    await c.uaclient.register_server(rogue)
                assert err.value.code == ua.StatusCodes.BadServiceUnsupported
                found = await c.uaclient.find_servers(ua.FindServersParameters())
                assert [s.ApplicationUri for s in found] == ["urn:geo-server:server"]
            finally:
                c.disconnect_socket()
        finally:
            await iface.close()

    run(scenario)


def _raw(port: int, frame: bytes) -> bytes:
    """Send `frame` on a new connection; what the server answers until it closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(frame)
        got = b""
        while True:
            part = s.recv(4096)
            if not part:
                return got
            got += part


def _hello(receive: int, send: int, declared: int | None = None) -> bytes:
    url = b"opc.tcp://127.0.0.1"
    body = struct.pack("<IIIII", 0, receive, send, 0, 0) + struct.pack("<i", len(url)) + url
    return b"HELF" + struct.pack("<I", declared or 8 + len(body)) + body


@pytest.mark.parametrize(
    ("frame", "code"),
    [
        # a MSG chunk that says it is 168 MiB: refused at its header, its body never read
        (b"MSGF" + struct.pack("<I", 168 << 20) + b"\0" * 16, ua.StatusCodes.BadTcpMessageTooLarge),
        # a Hello of 64 MiB
        (_hello(65535, 65535, declared=64 << 20), ua.StatusCodes.BadTcpMessageTooLarge),
        # a receive buffer of 25 bytes (a Read would come back in 150 000 chunks)
        (_hello(25, 65535), ua.StatusCodes.BadConnectionRejected),
        (b"XYZF" + struct.pack("<I", 32) + b"\0" * 24, ua.StatusCodes.BadTcpMessageTypeInvalid),
    ],
    ids=["msg-168MiB", "hel-64MiB", "hel-buffer-25", "unknown-type"],
)
def test_a_frame_is_refused_at_its_header(service: ObjectService, frame: bytes, code: int) -> None:
    """The server answers an ERR with the spec's code and closes, at once (before, it
    waited for 168 MiB, or acknowledged the tiny buffer)."""

    async def scenario() -> None:
        iface = await started(service)
        try:
            got = await asyncio.to_thread(_raw, iface.port, frame)
            assert got[:4] == b"ERRF", got[:16]
            assert struct.unpack("<I", got[8:12])[0] == code
        finally:
            await iface.close()

    run(scenario)


def test_one_session_per_connection(service: ObjectService) -> None:
    """A second CreateSession on a connection that has one is BadTooManySessions (before:
    a thousand sessions on one connection took every place from everyone)."""

    async def scenario() -> None:
        iface = await started(service)
        try:
            c = await channel_only(iface)
            try:
                params = ua.CreateSessionParameters(
                    EndpointUrl=iface.endpoint, SessionName="one", RequestedSessionTimeout=10_000
                )
                await c.uaclient.create_session(params)
                with pytest.raises(UaStatusCodeError) as err:
                    await c.uaclient.create_session(params)
                assert err.value.code == ua.StatusCodes.BadTooManySessions
            finally:
                c.disconnect_socket()
        finally:
            await iface.close()

    run(scenario)


def test_a_session_and_its_subscriptions_end_with_its_connection(service: ObjectService) -> None:
    """A client that drops its connection without CloseSession: its session and its
    subscriptions are gone (before, kept for a reactivation that nobody may make here,
    holding their monitored items)."""

    async def scenario() -> None:
        iface = await started(service)
        try:
            iserver = iface.server.iserver
            c = client(iface)
            await c.connect()
            ns = await c.get_namespace_index(NAMESPACE_URI)
            sub = await c.create_subscription(100, None)
            await sub.subscribe_data_change(c.get_node(ua.NodeId(TEMPC, ns)))
            assert len(iserver.subscription_service.subscriptions) == 1
            c.uaclient.disconnect_socket()  # no CloseSession
            # the server sees the connection go on one of its next turns (its own thread)
            deadline = asyncio.get_running_loop().time() + TIMEOUT
            while iserver.subscription_service.subscriptions:
                if asyncio.get_running_loop().time() > deadline:
                    break
                await asyncio.sleep(0.01)
            assert not iserver.subscription_service.subscriptions
            assert not iserver._external_sessions
        finally:
            await iface.close()

    run(scenario)


def test_a_session_cannot_touch_another_sessions_subscription(service: ObjectService) -> None:
    """Subscription ids are small integers: B names A's in DeleteSubscriptions and
    SetPublishingMode and gets BadSubscriptionIdInvalid; A's subscription lives on."""

    async def scenario() -> None:
        iface = await started(service)
        try:
            async with client(iface) as a, client(iface) as b:
                ns = await a.get_namespace_index(NAMESPACE_URI)
                sub = await a.create_subscription(100, None)
                await sub.subscribe_data_change(a.get_node(ua.NodeId(TEMPC, ns)))
                sid = sub.subscription_id
                mode = ua.SetPublishingModeParameters(
                    PublishingEnabled=False, SubscriptionIds=[sid]
                )
                got = await b.uaclient.set_publishing_mode(mode)
                assert [r.value for r in got] == [ua.StatusCodes.BadSubscriptionIdInvalid]
                got = await b.uaclient.delete_subscriptions([sid])
                assert [r.value for r in got] == [ua.StatusCodes.BadSubscriptionIdInvalid]
                subs = iface.server.iserver.subscription_service.subscriptions
                assert sid in subs and subs[sid].data.RevisedPublishingInterval > 0
        finally:
            await iface.close()

    run(scenario)


@pytest.mark.slow
def test_a_client_that_does_not_read_its_answers_is_paused_then_closed(
    service: ObjectService,
) -> None:
    """The client stops reading and sends 60 Reads of the standard's type dictionary
    (i=7617, about 210 kB each, one value: a request within every operation limit):
    the server stops reading and answering it once its answers back up (what it holds
    stays near one answer), and closes it after `unread_close_s`. Before: every answer
    went into memory, and the connection stayed."""

    async def scenario() -> None:
        iface = await started(service, unread_close_s=0.5)
        try:
            c = client(iface)
            await c.connect()
            bserver = iface.server.bserver
            (conn,) = bserver.clients
            c.uaclient.protocol.transport.pause_reading()
            dictionary = ua.ReadValueId(ua.NodeId(ua.ObjectIds.OpcUa_BinarySchema))
            dictionary.AttributeId = ua.AttributeIds.Value
            params = ua.ReadParameters(NodesToRead=[dictionary])
            pending = [asyncio.ensure_future(c.uaclient.read(params)) for _ in range(60)]
            held = 0
            # until it is closed (0.5 s after it paused) and gone from the server's
            # clients: the transport closes first, the connection is forgotten when the
            # loop runs its connection_lost (later on a busy host)
            for _ in range(1000):
                if conn not in bserver.clients:
                    break
                if conn.transport is not None and not conn.transport.is_closing():
                    held = max(held, conn.transport.get_write_buffer_size())
                await asyncio.sleep(0.01)
            assert conn not in bserver.clients
            assert held < 2 * 1024 * 1024, held
            for p in pending:
                p.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
            c.uaclient.disconnect_socket()
        finally:
            await iface.close()

    run(scenario)
