"""Modbus TCP interface (docs/design.md §8) against the default machine, with pymodbus' own client.

The server runs on an asyncio loop thread (`loop_thread`), the machine in stepped mode
unless a test starts the real-time scheduler; clients talk over loopback to an
ephemeral port. Every request is bounded by the client timeout.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout

import pytest
from conftest import run_in
from pymodbus.client import ModbusTcpClient

from geo_server import access
from geo_server.client.modbus_client import ModbusClient
from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.port import WriteObjects
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService, ServiceLimits
from geo_server.transports.modbus.regmap import (
    ModbusMap,
    bit_address,
    encode,
    register_address,
    register_count,
)
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

D = load_dictionary()
MM = ModbusMap.build(D)
TIMEOUT = 3.0


def obj(name: str):
    return D.by_name(name)


def start(loop, service, **kw) -> ModbusInterface:
    iface = ModbusInterface(service, ModbusOptions(port=0, **kw))
    run_in(loop, iface.start())
    return iface


@pytest.fixture
def server(loop_thread, service) -> Iterator[ModbusInterface]:
    access.step(service, 5)
    iface = start(loop_thread, service)
    yield iface
    run_in(loop_thread, iface.close())


@pytest.fixture
def client(server) -> Iterator[ModbusTcpClient]:
    c = ModbusTcpClient("127.0.0.1", port=server.port, timeout=TIMEOUT, retries=0)
    assert c.connect()
    yield c
    c.close()


@pytest.fixture
def geo(server) -> Iterator[ModbusClient]:
    with ModbusClient(port=server.port, timeout=TIMEOUT) as c:
        yield c


def regs_of(service: ObjectService, o, axis: int) -> list[int]:
    return encode(o, service.current(stale_ok=True).value(o, axis))


def exc(rr) -> int:
    assert rr.isError(), rr
    return rr.exception_code


def move(service: ObjectService) -> None:
    """Give the machine non-trivial values: moves on every axis, some cycles."""
    for axis in service.info.axes:
        access.write_name(service, "SIM::target_position", axis, 123_456 * axis)
    access.step(service, 40)


# ---------------------------------------------------------------------- reads


def test_port_zero_is_ephemeral(server):
    assert server.port not in (0, 5020)
    assert server.endpoint == f"127.0.0.1:{server.port}"


def test_every_object_of_every_axis(server, client, service):
    move(service)
    for axis in (0, *service.info.axes):
        um = MM.machine if axis == 0 else MM.axis
        for o in um.objects:
            a, n = register_address(o), register_count(o)
            hr = client.read_holding_registers(a, count=n, device_id=axis)
            ir = client.read_input_registers(a, count=n, device_id=axis)
            want = regs_of(service, o, axis)
            assert hr.registers == want, (axis, o.name)
            assert ir.registers == want, (axis, o.name)
            if o.type.name == "BOOLEAN":
                di = client.read_discrete_inputs(bit_address(o), count=1, device_id=axis)
                assert di.bits[0] == service.current(stale_ok=True).value(o, axis), (axis, o.name)
                if o.writable:
                    co = client.read_coils(bit_address(o), count=1, device_id=axis)
                    assert co.bits[0] == service.current(stale_ok=True).value(o, axis)


def test_client_read_matches_service(server, geo, service):
    move(service)
    for axis in service.info.axes:
        for o in MM.axis.objects:
            assert geo.read(o.name, axis) == access.read_name(service, o.name, axis), o.name
    assert geo.read("SIM::cycle_count") == access.read_name(service, "SIM::cycle_count") > 0
    ig, io = 0x120300, (1 << 16) | 0x43
    assert geo.read_raw(ig, io, 8) == service.read(ig, io, 8)
    assert geo.read_raw(0x120400, io, 256).rstrip(b"\0") == b"TEMPC::coefficient"
    with pytest.raises(AdsError) as info:
        geo.read("TEMPC::coefficient", 77)
    assert info.value.code == AdsErrorCode.DEVICE_INVALIDOFFSET


def test_block_read_across_objects(server, client, service):
    move(service)
    snap = service.current(stale_ok=True)
    start_ = register_address(obj("TEMPC::activated"))  # 0x41 … 0x45: 20 registers
    rr = client.read_holding_registers(start_, count=20, device_id=2)
    want = MM.axis.read_registers(start_, 20, lambda o: snap.value(o, 2))
    assert rr.registers == want
    # the emulator group: command position … FRICT::additive_current, 36 registers
    rr = client.read_input_registers(0x4004, count=36, device_id=1)
    assert rr.registers == MM.axis.read_registers(0x4004, 36, lambda o: snap.value(o, 1))
    rr = client.read_discrete_inputs(0x1D6, count=3, device_id=1)
    assert rr.bits[:3] == [
        snap.value(obj(n), 1) for n in ("CROSSC::activated", "CC2::activated", "TEMPC::f_is_active")
    ]


@pytest.mark.realtime
def test_block_read_never_mixes_cycles(loop_thread, machine):
    """While the GEO cycle runs, output = command + total offset in every block read."""
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    iface = start(loop_thread, service)
    sched.start()
    try:
        access.write_name(service, "SIM::target_position", 1, 50_000_000)
        with ModbusTcpClient("127.0.0.1", port=iface.port, timeout=TIMEOUT, retries=0) as c:
            seen = set()
            for _ in range(200):
                regs = c.read_holding_registers(0x4004, count=28, device_id=1).registers
                cmd = int.from_bytes(bytes(_b(regs[0:2])), "big", signed=True)
                out = int.from_bytes(bytes(_b(regs[20:22])), "big", signed=True)
                tot = int.from_bytes(bytes(_b(regs[24:26])), "big", signed=True)
                assert abs(out - (cmd + tot)) <= 1, (cmd, out, tot)
                seen.add(cmd)
            assert len(seen) > 5  # the axis really moved during the reads
    finally:
        sched.stop()
        run_in(loop_thread, iface.close())


def _b(regs: list[int]) -> list[int]:
    return [x for r in regs for x in (r >> 8, r & 0xFF)]


def test_concurrent_clients(server, service):
    move(service)
    errors: list[BaseException] = []
    a = register_address(obj("TEMPC::coefficient"))
    want = {axis: regs_of(service, obj("TEMPC::coefficient"), axis) for axis in service.info.axes}

    def worker() -> None:
        try:
            with ModbusTcpClient("127.0.0.1", port=server.port, timeout=TIMEOUT, retries=0) as c:
                for i in range(50):
                    axis = service.info.axes[i % len(service.info.axes)]
                    assert (
                        c.read_holding_registers(a, count=4, device_id=axis).registers
                        == (want[axis])
                    )
        except BaseException as e:  # collected for the main thread
            errors.append(e)

    threads = [threading.Thread(target=worker) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors, errors[0]
    assert server.requests >= 400


def test_device_identification(server, client, geo):
    import geo_server

    info = client.read_device_information(device_id=1).information
    assert info[0] == b"geo-server"
    assert info[1] == b"geo-server"
    assert info[2] == geo_server.__version__.encode()
    assert geo.device_information()[2] == geo_server.__version__.encode()


# ---------------------------------------------------------------------- writes


def test_write_every_writable_tempc_object(server, client, service):
    axis = 2
    before = access.read_name(service, "TEMPC::actual_offset", axis)
    coef = obj("TEMPC::coefficient")
    a = register_address(coef)
    rr = client.write_registers(a, encode(coef, 4000.0), device_id=axis)  # FC 16, 4 words
    assert not rr.isError()
    rr = client.write_registers(
        register_address(obj("TEMPC::offset_0")),
        encode(obj("TEMPC::offset_0"), -2500),
        device_id=axis,
    )
    assert not rr.isError()
    rr = client.write_registers(
        register_address(obj("TEMPC::position_0")),
        encode(obj("TEMPC::position_0"), 1000),
        device_id=axis,
    )
    assert not rr.isError()
    assert not client.write_coil(0x41, True, device_id=axis).isError()  # FC 5
    # stepped: nothing applied before the next cycle boundary
    assert access.read_name(service, "TEMPC::offset_0", axis) != -2500
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::coefficient", axis) == 4000.0
    assert access.read_name(service, "TEMPC::offset_0", axis) == -2500
    assert access.read_name(service, "TEMPC::position_0", axis) == 1000
    assert access.read_name(service, "TEMPC::activated", axis) is True
    assert client.read_holding_registers(a, count=4, device_id=axis).registers == [
        0x40AF,
        0x4000,
        0,
        0,
    ]
    access.step(service, 60)  # past the sin² ramp of temp_comp_n_cycles
    after = client.read_holding_registers(4 * 0x42, count=2, device_id=axis).registers
    assert after == regs_of(service, obj("TEMPC::actual_offset"), axis)
    assert access.read_name(service, "TEMPC::actual_offset", axis) != before
    # FC 6 on a one-register BOOLEAN, FC 15 on a coil: deactivate again
    assert not client.write_register(4 * 0x41, 0, device_id=axis).isError()
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::activated", axis) is False
    assert not client.write_coils(0x41, [True], device_id=axis).isError()
    access.step(service, 1)
    assert client.read_coils(0x41, count=1, device_id=axis).bits[0] is True
    # other axes untouched
    assert access.read_name(service, "TEMPC::offset_0", 1) != -2500


def test_client_write_and_raw(server, geo, service):
    assert geo.write("TEMPC::coefficient", 1, 12.5) == 12.5
    geo.write_raw(0x120300, (1 << 16) | 0x44, (-7).to_bytes(4, "little", signed=True))
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::coefficient", 1) == 12.5
    assert access.read_name(service, "TEMPC::offset_0", 1) == -7
    with pytest.raises(AdsError) as info:
        geo.write("TEMPC::actual_offset", 1, 5)
    assert info.value.code == AdsErrorCode.DEVICE_INVALIDACCESS
    with pytest.raises(AdsError) as info:
        geo.write("TEMPC::coefficient", 1, 1e6)  # refused by the client's own check
    assert info.value.code == AdsErrorCode.DEVICE_INVALIDDATA


@pytest.mark.realtime
def test_writes_wait_for_the_cycle_when_running(loop_thread, machine):
    sched = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, sched)
    iface = start(loop_thread, service)
    sched.start()
    try:
        with ModbusClient(port=iface.port, timeout=TIMEOUT) as c:
            for v in (1.25, -3.5, 77.0):
                c.write("TEMPC::coefficient", 3, v)
                assert c.read("TEMPC::coefficient", 3) == v  # applied before the ack
    finally:
        sched.stop()
        run_in(loop_thread, iface.close())


class HandCranked(Scheduler):
    """Reports running cycles (so the transports wait for writes to be applied, as with
    the real-time thread), but a cycle runs only when the test calls `crank()`."""

    def __init__(self, machine: Machine) -> None:
        super().__init__(machine, mode="stepped")

    @property
    def running(self) -> bool:
        return True

    def crank(self) -> None:
        self.machine.run_cycle()


def test_write_reply_comes_with_the_cycle_that_applied_it(loop_thread, machine):
    """The reply waits for exactly ONE cycle: the cycle applies the queued write (docs/design.md §5
    step 1), publishes the snapshot that contains it (step 4) and only then resolves the
    write's future (`Machine.run_cycle`). So the reply goes out after that cycle, and a
    read sent after the reply sees the value with no further cycle. (Waiting for a
    further snapshot as well held every reply back by a second cycle: here it would
    never come, the exception 6 after `write_timeout`.)"""
    sched = HandCranked(machine)
    service = ObjectService(machine, sched)
    iface = start(loop_thread, service, write_timeout=TIMEOUT)
    coef, off0 = obj("TEMPC::coefficient"), obj("TEMPC::offset_0")
    assert register_address(off0) == register_address(coef) + 4  # one FC 16 covers both
    writes = [
        lambda c: c.write_registers(
            register_address(coef), encode(coef, 42.5) + encode(off0, -17), device_id=3
        ),
        lambda c: c.write_coil(bit_address(obj("TEMPC::activated")), True, device_id=3),
    ]
    pool = ThreadPoolExecutor(1)
    try:
        with ModbusTcpClient("127.0.0.1", port=iface.port, timeout=TIMEOUT, retries=0) as c:
            for n, write in enumerate(writes, 1):
                cycle = machine.cycle
                reply = pool.submit(write, c)
                # queued once the loop has counted the request (same loop step)
                assert wait_until(loop_thread, lambda n=n: iface.requests == n)
                with pytest.raises(FutureTimeout):
                    reply.result(timeout=0.1)  # not before the cycle has applied it
                sched.crank()
                assert not reply.result(timeout=TIMEOUT).isError()
                assert machine.cycle == cycle + 1
            rr = c.read_holding_registers(register_address(coef), count=8, device_id=3)
            assert rr.registers == encode(coef, 42.5) + encode(off0, -17) + [0, 0]
            assert c.read_coils(bit_address(obj("TEMPC::activated")), device_id=3).bits[0]
            assert machine.cycle == cycle + 1  # the reads needed no further cycle
    finally:
        pool.shutdown(wait=False)
        run_in(loop_thread, iface.close())


def wait_until(loop, predicate, timeout: float = TIMEOUT) -> bool:
    """Evaluate `predicate()` on the loop thread until it is true or `timeout` passes."""

    async def check() -> bool:
        return bool(predicate())

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if run_in(loop, check()):
            return True
        time.sleep(0.005)
    return False


def test_sim_objects_move_the_axis(server, geo, service):
    geo.write("SIM::feed", 1, 100_000)
    geo.write("SIM::target_position", 1, 20_000)
    access.step(service, 2000)
    assert geo.read("SIM::command_position", 1) == 20_000
    assert geo.read("SIM::command_position", 1) == access.read_name(
        service, "SIM::command_position", 1
    )


# ---------------------------------------------------------------------- exceptions


def test_exception_codes(server, client):
    c = client
    # 2: a read touching a register outside every slot
    assert exc(c.read_holding_registers(0, count=1, device_id=1)) == 2
    assert exc(c.read_holding_registers(4 * 0x45, count=8, device_id=1)) == 2
    assert exc(c.read_input_registers(0x3FFF, count=2, device_id=1)) == 2
    assert exc(c.read_coils(0x40, count=1, device_id=1)) == 2
    assert exc(c.read_discrete_inputs(0x42, count=1, device_id=1)) == 2
    # 2: a write to a read-only object
    assert exc(c.write_registers(4 * 0x42, [0, 1], device_id=1)) == 2
    assert exc(c.write_coil(0x1D8, True, device_id=1)) == 2
    # 3: a write that does not cover whole objects, a value out of range
    assert exc(c.write_register(4 * 0x43, 0x40AF, device_id=1)) == 3
    assert exc(c.write_registers(4 * 0x43, [0x40AF, 0x4000], device_id=1)) == 3
    assert (
        exc(c.write_registers(4 * 0x43, encode(obj("TEMPC::coefficient"), 1e5), device_id=1)) == 3
    )
    assert exc(c.write_register(4 * 0x41, 2, device_id=1)) == 3
    # 11: an unknown unit id
    assert exc(c.read_holding_registers(4 * 0x43, count=4, device_id=42)) == 11
    assert exc(c.write_coil(0x41, True, device_id=200)) == 11
    # 1: function codes geo-server does not serve, with the right function code echoed
    rr = c.mask_write_register(address=4 * 0x41, and_mask=0, or_mask=1, device_id=1)
    assert exc(rr) == 1 and rr.function_code == 0x80 | 22
    rr = c.readwrite_registers(
        read_address=4 * 0x41, read_count=1, write_address=4 * 0x41, values=[1], device_id=1
    )
    assert exc(rr) == 1
    assert exc(c.report_device_id(device_id=1)) == 1
    # the machine unit has no per-axis objects
    assert exc(c.read_holding_registers(4 * 0x43, count=4, device_id=0)) == 2
    assert not c.read_holding_registers(0x4004, count=4, device_id=1).isError()


def test_read_only_option(loop_thread, service):
    iface = start(loop_thread, service, read_only=True)
    try:
        with ModbusTcpClient("127.0.0.1", port=iface.port, timeout=TIMEOUT, retries=0) as c:
            assert exc(c.write_coil(0x41, False, device_id=1)) == 2
            coef = encode(obj("TEMPC::coefficient"), 1.0)
            assert exc(c.write_registers(4 * 0x43, coef, device_id=1)) == 2
            assert not c.read_holding_registers(4 * 0x43, count=4, device_id=1).isError()
    finally:
        run_in(loop_thread, iface.close())


def test_units_are_machine_zero_and_every_axis(service):
    iface = ModbusInterface(service, ModbusOptions(port=0))
    assert set(iface.unit_maps) == {0, 255, *service.info.axes}


def test_unit_255_is_the_machine_unit(server, client, service):
    """The MODBUS/TCP guide's unit of a directly addressed device (0xFF) reaches the
    machine-wide objects, as unit 0 does; the reply carries the unit asked for."""
    cycles = obj("SIM::cycle_count")  # UNS32, two registers, high word first
    address = register_address(cycles)
    for unit in (0, 255):
        rr = client.read_holding_registers(address, count=2, device_id=unit)
        assert not rr.isError(), rr
        assert rr.dev_id == unit
        assert rr.registers == [0, 5]  # the fixture stepped 5 cycles
    # the machine unit has no per-axis objects, on 255 either
    assert exc(client.read_holding_registers(4 * 0x43, count=4, device_id=255)) == 2
    # a write on 255 is a write of the machine's object: SIM::reload reloads the lists
    reload = register_address(obj("SIM::reload"))
    rr = client.write_register(reload, 1, device_id=255)
    assert not rr.isError() and rr.dev_id == 255


def test_reload_over_modbus(loop_thread, lists_copy):
    from geo_server.listfile import load_machine

    service = ObjectService(Machine(load_machine(lists_copy), cycle_s=0.001, homed=True))
    iface = start(loop_thread, service)
    try:
        with ModbusClient(port=iface.port, timeout=TIMEOUT) as c:
            c.reload()
            c.save()
    finally:
        run_in(loop_thread, iface.close())


def test_geo_client_via_modbus(server, capsys):
    from geo_server.client.cli import main as client_main

    base = ["--via", "modbus", "--connect", f"127.0.0.1:{server.port}", "--timeout", "3"]
    assert client_main([*base, "read", "--axis", "1", "TEMPC::coefficient"]) == 0
    assert capsys.readouterr().out.strip() == "axis 1 (X) TEMPC::coefficient = 4000.0 µm/m"
    assert client_main([*base, "--json", "read", "0x120300", "0x10044"]) == 0
    assert '"raw": 40' in capsys.readouterr().out  # offset_0 40 increments = 4.0 µm
    assert client_main([*base, "write", "--axis", "2", "TEMPC::offset_0", "-250"]) == 0
    capsys.readouterr()
    access.step(server.service, 1)
    assert access.read_name(server.service, "TEMPC::offset_0", 2) == -250
    assert client_main([*base, "write", "--axis", "1", "BC::actual backlash", "1"]) == 1
    assert "ADS 0x704" in capsys.readouterr().err
    assert client_main([*base, "status"]) == 0  # from the emulator objects
    assert "axes 1 X, 2 Y, 3 Z, 4 C" in capsys.readouterr().out


def test_a_read_at_rest_catches_up_only_for_what_can_vary_at_rest(loop_thread) -> None:
    """docs/design.md §13, *Reads at rest*: the exact engine under a virtual clock, a
    machine at rest. Registers of TEMPC::offset_0 (SGN32 -250: 0xFFFF 0xFF06, the rest of
    its slot 0) and of SIM::cycle_time_us (1000 µs) are answered without catching up 5000
    cycles; a read whose range covers SIM::cycle_count catches up to the cycle due and
    shows it."""
    from test_virtual_time import P, driven

    vc, m, sched = driven(load_machine(default_startup_list()))
    service = ObjectService(m, sched, ServiceLimits(stall_after=60.0))  # (a slow host)
    m.submit(WriteObjects((("TEMPC::offset_0", 1, -250),)))
    vc.t += 100 * P
    cycle = service.current().cycle
    iface = start(loop_thread, service)
    c = ModbusTcpClient("127.0.0.1", port=iface.port, timeout=TIMEOUT, retries=0)
    try:
        assert c.connect()
        vc.t += 5000 * P
        offset = register_address(obj("TEMPC::offset_0"))
        assert c.read_holding_registers(offset, count=4, device_id=1).registers == [
            0xFFFF,
            0xFF06,
            0,
            0,
        ]
        period = register_address(obj("SIM::cycle_time_us"))
        assert c.read_input_registers(period, count=2, device_id=0).registers == [0, 1000]
        assert m.cycle == cycle  # nothing caught up
        count = register_address(obj("SIM::cycle_count"))
        regs = c.read_input_registers(count, count=6, device_id=0).registers
        due = cycle + 5000
        assert regs == [due >> 16, due & 0xFFFF, 0, 0, 0, 1000]
        assert m.cycle == due
    finally:
        c.close()
        run_in(loop_thread, iface.close())
