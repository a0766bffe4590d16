"""OPC UA in a process of its own (geo_server/transports/opcua/apart.py, docs/design.md
§9.1): `OpcUaProcess` runs the interface in a child over the server's own services, so
everything an OPC UA client does reaches the machine through the server's event loop,
and the child's end is the server's business alone. Stepped: each value below follows
from the cycles the test steps, computed by hand."""

from __future__ import annotations

import asyncio
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import free_port, geo_server_cmd
from support.probes import modbus_read
from support.procfs import children, spawned
from test_opcua import Collect, node_of, options
from test_opcua_items import item

from geo_server import access
from geo_server.dictionary import load_dictionary
from geo_server.service import ObjectService
from geo_server.transports.opcua.apart import OpcUaProcess
from geo_server.transports.opcua.space import NAMESPACE_URI

TIMEOUT = 30.0
COUNT = "local/SIM/cycle_count"
COEF = "local/Axes/X/TEMPC/coefficient"


@pytest.mark.slow
def test_reads_writes_items_and_status_through_the_child(service: ObjectService) -> None:
    """A Read answers the machine's value; a Write is applied by the next step (stepped:
    queued, as in one process); an item on the cycle count gets the five cycles stepped,
    each its own value; the machine's status shows the child's item and what it
    sampled; the server is another process, gone after `close`."""

    async def scenario() -> None:
        ua_server = OpcUaProcess({"local": service}, options(background=False))
        await ua_server.start()
        pid = ua_server.pid
        assert pid is not None and pid != os.getpid()
        try:
            async with Client(ua_server.endpoint, timeout=10) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = node_of(c, ns, COEF)
                assert await coef.read_value() == 4000.0
                await coef.write_value(ua.Variant(1234.5, ua.VariantType.Double))
                access.step(service, 1)
                assert access.read_name(service, "TEMPC::coefficient", 1) == 1234.5
                assert await coef.read_value() == 1234.5
                seen = Collect()
                await item(c, seen, node_of(c, ns, COUNT), 1.0)  # (a queue of 16 values)
                await seen.until(1, COUNT)
                start = service.current().cycle
                access.step(service, 5)
                got = await seen.until(6, COUNT)
                assert [v for v, _ in got][1:] == list(range(start + 1, start + 6))
                while (service.status().get("opcua_items") or {}).get("items") != 1:
                    await asyncio.sleep(0.05)  # (sent twice a second)
        finally:
            await ua_server.close()
        assert ua_server._proc is not None and not ua_server._proc.is_alive()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


@pytest.mark.slow
def test_refusals_cross_the_pipe_as_their_status_codes(service: ObjectService) -> None:
    """What the server's service refuses reaches the OPC UA client as in one process: a
    value out of range BadOutOfRange (0x706 on the server), a fault that cannot be
    parsed BadInvalidArgument (a FaultError), and the session goes on."""

    async def scenario() -> None:
        ua_server = OpcUaProcess({"local": service}, options(background=False))
        await ua_server.start()
        try:
            async with Client(ua_server.endpoint, timeout=10) as c:
                ns = await c.get_namespace_index(NAMESPACE_URI)
                coef = node_of(c, ns, COEF)
                with pytest.raises(ua.UaStatusCodeError) as err:
                    await coef.write_value(ua.Variant(1e12, ua.VariantType.Double))
                assert err.value.code == ua.StatusCodes.BadOutOfRange
                machine = c.get_node(ua.NodeId("local", ns))
                with pytest.raises(ua.UaStatusCodeError) as err:
                    await machine.call_method(ua.QualifiedName("InjectFault", ns), "no such fault")
                assert err.value.code == ua.StatusCodes.BadInvalidArgument
                assert await coef.read_value() == 4000.0
        finally:
            await ua_server.close()

    asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))


def test_the_server_unpickles_only_plain_values_from_the_child() -> None:
    """The child faces the network; what it sends is read with `_Restricted`: plain
    values and the errors it passes on, never a class that would run code here."""
    from geo_server.errors import AdsError, AdsErrorCode
    from geo_server.transports.opcua.apart import _portable, _Restricted, _shown

    plain = ("call", 7, "local", "apply", ([("TEMPC::coefficient", 1, 12.5)],))
    assert _Restricted.loads(pickle.dumps(plain)) == plain
    err = _Restricted.loads(pickle.dumps(AdsError(AdsErrorCode.DEVICE_INVALIDSIZE, "x")))
    assert err.code == AdsErrorCode.DEVICE_INVALIDSIZE
    for hostile in (os.system, subprocess.Popen, Path("/etc/passwd")):
        with pytest.raises(pickle.UnpicklingError):
            _Restricted.loads(pickle.dumps(hostile))
    # what the child sends of an error the server can read (a certificate folder that
    # cannot be written: a PermissionError keeps its errno)
    denied = _Restricted.loads(pickle.dumps(_portable(PermissionError(13, "Permission denied"))))
    assert type(denied) is PermissionError and denied.errno == 13
    # of a machine's status only OPC UA's own keys, numbers only
    forged = {"stalled": True, "opcua_items": {"items": 3, "x": "y"}, "opcua_share": [1]}
    assert _shown(forged) == {"opcua_items": {"items": 3}}


@pytest.mark.slow
def test_a_start_that_fails_in_the_child_is_said_once(service: ObjectService) -> None:
    """A user without a certificate folder cannot be served (the password would travel
    in clear): the child says so, `on_started` hears it once, and the child ends."""

    async def scenario() -> list[BaseException | None]:
        heard: list[BaseException | None] = []
        opts = options(user="u", password="p", background=True)
        ua_server = OpcUaProcess({"local": service}, opts)
        ua_server.on_started = heard.append
        await ua_server.start()
        try:
            while not heard:
                await asyncio.sleep(0.02)
            while not ua_server.ended:  # (it ends by itself; the server sees its pipe end)
                await asyncio.sleep(0.02)
        finally:
            await ua_server.close()
        return heard

    heard = asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))
    assert len(heard) == 1 and isinstance(heard[0], ValueError), heard
    assert "certificate" in str(heard[0])


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_child_that_dies_is_said_and_the_others_keep_serving(tmp_path: Path) -> None:
    """`geo-server run`: OPC UA's endpoint is served by a child of the server. Killed
    (SIGKILL, as the kernel's OOM killer would), the server says so on stderr once and
    Modbus keeps answering; SIGTERM then ends the server as ever."""
    port, mport = free_port(), free_port()
    args = [*geo_server_cmd(), "run", "--homed", "--no-zenoh", "--no-ads"]
    args += ["--modbus-port", str(mport), "--opcua-endpoint", f"opc.tcp://127.0.0.1:{port}"]
    args += ["--opcua-no-companions", "--status-period", "60"]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    err = tmp_path / "err.txt"
    with err.open("w") as stderr:
        proc = subprocess.Popen(
            args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=stderr, text=True
        )
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                if line.startswith("opcua: ready"):
                    break
            (child,) = (c for c in children(proc.pid) if spawned(c))
            assert _listening(port)
            os.kill(child, signal.SIGKILL)
            deadline = time.monotonic() + TIMEOUT
            while "OPC UA's process ended" not in err.read_text():
                assert time.monotonic() < deadline, err.read_text()
                time.sleep(0.05)
            assert not _listening(port)
            assert modbus_read(mport, load_dictionary().by_name("TEMPC::coefficient"), 5.0) == 0
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(TIMEOUT) == 0
            assert err.read_text().count("OPC UA's process ended") == 1
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
