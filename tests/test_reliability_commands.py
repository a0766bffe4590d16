"""Commands (reload, save) never wedge the server: a list that is a FIFO is refused at
once, a second command waits a bounded time and is told "busy", and the reason of a
rejection is readable in the error list."""

from __future__ import annotations

import os
import socket
import struct
import threading
import time

import pytest
from conftest import run_in

from geo_server import access
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService, ServiceLimits
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

TIMEOUT = 10.0
RELOAD_ADDR = 0x4000 + 4 * 0x0004  # SIM::reload, unit 0 (emulator group base + 4·ID)


def fc6(tid: int, unit: int, address: int, value: int) -> bytes:
    pdu = struct.pack(">BHH", 6, address, value)
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


@pytest.mark.timeout(60)
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_reload_of_a_fifo_list_is_refused_at_once_over_modbus(loop_thread, lists_copy):
    svc = ObjectService(Machine(load_machine(lists_copy), homed=True))
    iface = ModbusInterface(svc, ModbusOptions(port=0))
    run_in(loop_thread, iface.start())
    axis1 = lists_copy.parent / "achsmd1.lis"
    axis1.unlink()
    os.mkfifo(axis1)  # opening it for reading would block until a writer comes
    try:
        with socket.create_connection(("127.0.0.1", iface.port), timeout=TIMEOUT) as s:
            s.settimeout(TIMEOUT)
            t0 = time.monotonic()
            s.sendall(fc6(1, 0, RELOAD_ADDR, 1))
            reply = s.recv(64)
            assert time.monotonic() - t0 < TIMEOUT
            # exception 4 (server device failure): a rejected command; the reason is
            # in the error list
            assert reply == struct.pack(">HHHB", 1, 0, 3, 0) + b"\x86\x04"
            s.sendall(struct.pack(">HHHBBHH", 2, 0, 6, 1, 3, 4 * 0x43, 4))
            assert s.recv(64)[7:9] == b"\x03\x08"  # and the server goes on answering
        (err,) = [e for e in svc.errors() if "reload rejected" in e["message"]]
        assert "reload rejected, machine unchanged:" in err["message"]
        assert "achsmd1.lis" in err["message"] and "FIFO" in err["message"]
        assert access.read_name(svc, "TEMPC::coefficient", 1) == 4000.0
    finally:
        run_in(loop_thread, iface.close())


def test_a_second_command_is_told_busy_within_the_bound(loop_thread, lists_copy):
    svc = ObjectService(
        Machine(load_machine(lists_copy), homed=True), limits=ServiceLimits(command_wait=0.2)
    )
    running = threading.Event()
    release = threading.Event()

    def long_command() -> None:  # holds the one command slot, as a slow save would
        with svc.commands.lock._lock:
            running.set()
            release.wait(TIMEOUT)

    worker = threading.Thread(target=long_command)
    worker.start()
    try:
        assert running.wait(TIMEOUT)
        result = svc.commands.save()
        assert not result.ok and result.code == AdsErrorCode.DEVICE_BUSY
        assert result.errors == ["another reload or save is still running; try again"]
        with pytest.raises(AdsError) as err:
            run_in(loop_thread, access.write_name_applied(svc, "SIM::reload", 0, 1))
        assert err.value.code == AdsErrorCode.DEVICE_BUSY
    finally:
        release.set()
        worker.join(TIMEOUT)
    assert svc.commands.reload().ok  # free again
