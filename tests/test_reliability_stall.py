"""A stalled GEO cycle: nothing reported as failed takes effect later, nothing stale is
served as current.

The cycle runs in its own process (the default of `geo-server run`); the test stops
that process with SIGSTOP, as a debugger, an overloaded host or a paused VM would, and
resumes it with SIGCONT. Bounded: every wait has a deadline, every request a timeout.
"""

from __future__ import annotations

import os
import signal
import socket
import struct
import time
from collections.abc import Iterator

import pytest
from conftest import run_in

from geo_server import access
from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.listfile import load_machine
from geo_server.machine.process import ProcessScheduler, RemoteMachine
from geo_server.service import ObjectService, ServiceLimits
from geo_server.transports.modbus.regmap import encode, register_address
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="needs SIGSTOP")

D = load_dictionary()
COEF = D.by_name("TEMPC::coefficient")
TIMEOUT = 10.0


def wait_for(predicate, timeout: float = TIMEOUT) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < end, "condition not met in time"
        time.sleep(0.01)


class Stoppable:
    """A machine whose cycle runs in a child process that the test can stop."""

    def __init__(self, startup, limits: ServiceLimits) -> None:
        self.machine = RemoteMachine(load_machine(startup), cycle_s=0.001, homed=True)
        self.sched = ProcessScheduler(self.machine, mode="realtime")
        self.service = ObjectService(self.machine, self.sched, limits)
        self.sched.start()
        wait_for(lambda: self.machine.cycle > 20)
        self.stopped = False

    def stop_cycle(self) -> None:
        assert self.sched.pid is not None
        os.kill(self.sched.pid, signal.SIGSTOP)
        self.stopped = True
        # a cycle already in flight may still arrive: wait until no frame comes any more
        last = -1
        while last != self.machine.cycle:
            last = self.machine.cycle
            time.sleep(0.05)

    def resume_cycle(self) -> None:
        if self.stopped and self.sched.pid is not None:
            os.kill(self.sched.pid, signal.SIGCONT)
            self.stopped = False

    def close(self) -> None:
        self.resume_cycle()
        self.sched.stop()


@pytest.fixture
def slow_to_notice(lists_copy) -> Iterator[Stoppable]:
    """Stall detection far away: a write queued while the cycle is stopped times out."""
    m = Stoppable(lists_copy, ServiceLimits(write_timeout=0.5, swap_timeout=0.5, stall_after=60))
    yield m
    m.close()


@pytest.fixture
def quick_to_notice(lists_copy) -> Iterator[Stoppable]:
    m = Stoppable(lists_copy, ServiceLimits(write_timeout=0.5, stall_after=0.3))
    yield m
    m.close()


@pytest.mark.slow
def test_a_write_that_timed_out_is_withdrawn_and_never_applied(slow_to_notice, loop_thread):
    m = slow_to_notice
    svc = m.service
    before = access.read_name(svc, "TEMPC::coefficient", 1)
    m.stop_cycle()
    with pytest.raises(AdsError) as err:
        run_in(loop_thread, access.write_name_applied(svc, "TEMPC::coefficient", 1, before + 111.0))
    assert err.value.code == AdsErrorCode.DEVICE_TIMEOUT
    m.resume_cycle()
    resumed = m.machine.cycle
    wait_for(lambda: m.machine.cycle > resumed + 200)
    assert access.read_name(svc, "TEMPC::coefficient", 1) == before  # withdrawn: never applied
    # and the machine takes writes again
    run_in(loop_thread, access.write_name_applied(svc, "TEMPC::coefficient", 1, before + 1.0))
    assert access.read_name(svc, "TEMPC::coefficient", 1) == before + 1.0


@pytest.mark.slow
def test_a_modbus_write_answered_busy_never_takes_effect(slow_to_notice, loop_thread):
    m = slow_to_notice
    iface = ModbusInterface(m.service, ModbusOptions(port=0, write_timeout=0.5))
    run_in(loop_thread, iface.start())
    before = access.read_name(m.service, "TEMPC::coefficient", 2)
    addr = register_address(COEF)
    pdu = struct.pack(">BHHB", 16, addr, 4, 8) + struct.pack(">4H", *encode(COEF, before - 7.5))
    try:
        m.stop_cycle()
        with socket.create_connection(("127.0.0.1", iface.port), timeout=TIMEOUT) as s:
            s.sendall(struct.pack(">HHHB", 1, 0, len(pdu) + 1, 2) + pdu)
            assert s.recv(64) == struct.pack(">HHHB", 1, 0, 3, 2) + b"\x90\x06"
        m.resume_cycle()
        resumed = m.machine.cycle
        wait_for(lambda: m.machine.cycle > resumed + 200)
        assert access.read_name(m.service, "TEMPC::coefficient", 2) == before
    finally:
        run_in(loop_thread, iface.close())


@pytest.mark.slow
def test_a_reload_that_timed_out_leaves_the_machine_unchanged(slow_to_notice, lists_copy):
    m = slow_to_notice
    svc = m.service
    axis1 = lists_copy.parent / "achsmd1.lis"
    text = axis1.read_text()
    assert "lr_param.temp_comp_coefficient 4000" in text
    axis1.write_text(text.replace("temp_comp_coefficient 4000", "temp_comp_coefficient 1234"))
    cfg_before = m.machine.cfg
    m.stop_cycle()
    result = svc.commands.reload()
    assert not result.ok and result.code == AdsErrorCode.DEVICE_TIMEOUT
    assert "reload rejected, machine unchanged" in result.message
    m.resume_cycle()
    resumed = m.machine.cycle
    wait_for(lambda: m.machine.cycle > resumed + 200)
    # the cycle process owns the error list: the rejection is in it once it resumed
    assert any("reload rejected" in e["message"] for e in svc.errors())
    assert "reload rejected" in access.read_name(svc, "SIM::last_error", 0)
    assert m.machine.cfg is cfg_before
    assert access.read_name(svc, "TEMPC::coefficient", 1) == 4000.0


@pytest.mark.slow
def test_while_stalled_reads_and_writes_say_so_and_status_tells(quick_to_notice, loop_thread):
    m = quick_to_notice
    svc = m.service
    iface = ModbusInterface(svc, ModbusOptions(port=0))
    run_in(loop_thread, iface.start())
    addr = register_address(COEF)
    read = struct.pack(">HHHBBHH", 4, 0, 6, 1, 3, addr, 4)
    try:
        assert svc.status()["stalled"] is False
        m.stop_cycle()
        wait_for(lambda: svc.status()["stalled"])
        st = svc.status()
        assert st["stalled_for_s"] >= 0.3  # (rounded to ms: 0.3004 shows as 0.3)
        with pytest.raises(AdsError) as err:
            svc.read(0x120300, 0x10043)
        assert err.value.code == AdsErrorCode.DEVICE_NOTREADY
        with pytest.raises(AdsError) as err:  # refused at once, nothing queued
            access.write_name(svc, "TEMPC::coefficient", 1, 1.0)
        assert err.value.code == AdsErrorCode.DEVICE_NOTREADY
        with socket.create_connection(("127.0.0.1", iface.port), timeout=TIMEOUT) as s:
            s.sendall(read)
            assert s.recv(64) == struct.pack(">HHHB", 4, 0, 3, 1) + b"\x83\x06"
        m.resume_cycle()
        wait_for(lambda: not svc.status()["stalled"])
        assert access.read_name(svc, "TEMPC::coefficient", 1) == 4000.0
        with socket.create_connection(("127.0.0.1", iface.port), timeout=TIMEOUT) as s:
            s.sendall(read)
            assert s.recv(64)[7:9] == b"\x03\x08"
    finally:
        run_in(loop_thread, iface.close())


@pytest.mark.slow
def test_over_ads_a_timed_out_write_is_0x719_and_never_applied(slow_to_notice, loop_thread):
    import pyads

    from geo_server.transports.ads.server import AdsOptions, AdsServer

    m = slow_to_notice
    ads = AdsServer(m.service, AdsOptions(port=0, netid="127.0.0.1.1.1", write_timeout=0.5))
    run_in(loop_thread, ads.start())
    conn = pyads.Connection("127.91.0.1.1.1", 551, ads.address)
    conn.open()
    try:
        before = conn.read(0x120300, 0x30043, pyads.PLCTYPE_LREAL)
        m.stop_cycle()
        with pytest.raises(pyads.ADSError) as err:
            conn.write(0x120300, 0x30043, before + 5.0, pyads.PLCTYPE_LREAL)
        assert err.value.err_code == AdsErrorCode.DEVICE_TIMEOUT
        m.resume_cycle()
        resumed = m.machine.cycle
        wait_for(lambda: m.machine.cycle > resumed + 200)
        assert conn.read(0x120300, 0x30043, pyads.PLCTYPE_LREAL) == before
    finally:
        conn.close()
        run_in(loop_thread, ads.close())


@pytest.mark.slow
def test_over_ads_reads_answer_not_ready_while_stalled(quick_to_notice, loop_thread):
    import pyads

    from geo_server.transports.ads.server import AdsOptions, AdsServer

    m = quick_to_notice
    ads = AdsServer(m.service, AdsOptions(port=0, netid="127.0.0.1.1.1"))
    run_in(loop_thread, ads.start())
    conn = pyads.Connection("127.91.0.2.1.1", 551, ads.address)
    conn.open()
    try:
        assert conn.read(0x120300, 0x10043, pyads.PLCTYPE_LREAL) == 4000.0
        m.stop_cycle()
        wait_for(lambda: m.service.status()["stalled"])
        with pytest.raises(pyads.ADSError) as err:
            conn.read(0x120300, 0x10043, pyads.PLCTYPE_LREAL)
        assert err.value.err_code == AdsErrorCode.DEVICE_NOTREADY
        # attributes are constants of the dictionary: still answered
        assert conn.read(0x120600, 0x10043, pyads.PLCTYPE_UDINT) == 8  # length
        m.resume_cycle()
        wait_for(lambda: not m.service.status()["stalled"])
        assert conn.read(0x120300, 0x10043, pyads.PLCTYPE_LREAL) == 4000.0
    finally:
        conn.close()
        run_in(loop_thread, ads.close())


@pytest.mark.slow
def test_over_zenoh_stalled_reads_and_a_withdrawn_write(lists_copy, loop_thread):
    """While stalled, Zenoh reads answer reply_err 0x707, status says so, and a write is
    refused at once (0x707, nothing queued); after resuming, values are served again."""
    from conftest import free_port

    from geo_server.client.zenoh_client import ZenohClient
    from geo_server.transports.zenoh.options import ZenohOptions
    from geo_server.transports.zenoh.server import ZenohInterface

    m = Stoppable(lists_copy, ServiceLimits(write_timeout=0.5, stall_after=0.3))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    iface = ZenohInterface(m.service, ZenohOptions(machine="stall", listen=[endpoint]))
    run_in(loop_thread, iface.start())
    client = ZenohClient(machine="stall", connect=[endpoint], timeout=TIMEOUT)
    try:
        assert client.read("TEMPC::coefficient", 1) == 4000.0
        m.stop_cycle()
        wait_for(lambda: m.service.status()["stalled"])
        with pytest.raises(AdsError) as err:
            client.read("TEMPC::coefficient", 1)
        assert err.value.code == AdsErrorCode.DEVICE_NOTREADY
        assert client.status()["stalled"] is True  # status is always answered
        with pytest.raises(AdsError) as err:  # refused at once: nothing queued
            client.write("TEMPC::coefficient", 1, 17.0)
        assert err.value.code == AdsErrorCode.DEVICE_NOTREADY
        m.resume_cycle()
        wait_for(lambda: not m.service.status()["stalled"])
        assert client.read("TEMPC::coefficient", 1) == 4000.0
    finally:
        client.close()
        run_in(loop_thread, iface.close())
        m.close()
