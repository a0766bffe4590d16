"""The GEO cycle in its own process (`--cycle-in process`): framing, the remote machine
behind the object service, a real client, and the child's lifetime."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyads
import pytest
from conftest import run_in

from geo_server import access
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.ipc import ChannelError, FrameDecoder, OutBuffer, encode_frame
from geo_server.machine.machine import Machine
from geo_server.machine.process import ProcessScheduler, RemoteMachine
from geo_server.service import ObjectService
from geo_server.transports.ads.server import AdsOptions, AdsServer

# ---------------------------------------------------------------------- framing (no I/O)


def test_frames_survive_any_split_and_coalescing():
    messages = [("call", 1, "reset", ()), ("cycle", 7, b"\x00" * 300, [1, 2]), {"k": 1.5}]
    stream = b"".join(encode_frame(m) for m in messages)
    for chunk in (1, 3, 7, len(stream)):
        dec = FrameDecoder()
        got = []
        for i in range(0, len(stream), chunk):
            got += dec.feed(stream[i : i + chunk])
        assert got == messages, chunk


def test_frame_header_is_length_then_pickle():
    frame = encode_frame(("stop",))
    assert int.from_bytes(frame[:4], "little") == len(frame) - 4
    assert pickle.loads(frame[4:]) == ("stop",)
    with pytest.raises(ChannelError):
        FrameDecoder().feed((200 * 1024 * 1024).to_bytes(4, "little"))


def test_out_buffer_never_blocks_and_drops_only_droppable_frames():
    out = OutBuffer(limit=100)
    out.add(("cycle", 1, b"x" * 200), droppable=True)  # buffer empty: kept
    out.add(("cycle", 2, b"x" * 200), droppable=True)  # over the limit: superseded, dropped
    out.add(("ack", 9), droppable=False)  # acknowledgements are always kept
    assert out.dropped == 1
    written = bytearray()

    def writer_taking(n):
        def write(b):
            if n[0] == 0:
                raise BlockingIOError
            k = min(n[0], len(b))
            written.extend(b[:k])
            n[0] -= k
            return k

        return write

    out.flush(writer_taking([50]))  # a reader that takes 50 bytes, then would block
    assert len(written) == 50 and len(out) > 0
    out.flush(writer_taking([10**6]))
    assert len(out) == 0
    assert [m[:2] for m in FrameDecoder().feed(bytes(written))] == [("cycle", 1), ("ack", 9)]


# ---------------------------------------------------------------------- the remote machine


@pytest.fixture
def remote(default_cfg) -> Iterator[tuple[RemoteMachine, ProcessScheduler, ObjectService]]:
    machine = RemoteMachine(default_cfg, cycle_s=0.001, homed=True)
    sched = ProcessScheduler(machine, mode="realtime")
    svc = ObjectService(machine, sched)
    sched.start()
    try:
        wait_cycle(machine, 30)
        yield machine, sched, svc
    finally:
        sched.stop()


def wait_cycle(machine, n: int, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while machine.cycle < n:
        assert time.monotonic() < end, f"cycle {machine.cycle} < {n}"
        time.sleep(0.01)


@pytest.mark.slow
def test_acknowledged_write_is_in_the_snapshot_and_ramps(remote):
    machine, _, svc = remote
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 40  # X at 0: 40 + 4000e-6·(0 − 100)
    fut = access.write_name(svc, "TEMPC::offset_0", 1, 140.0)
    assert fut.result(timeout=5) is None
    cycle = machine.cycle
    # acknowledged only once the snapshot of the cycle that applied it is here
    assert access.read_name(svc, "TEMPC::offset_0", 1) == 140.0
    wait_cycle(machine, cycle + 25)  # temp_comp_n_cycles 20
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 140  # 140 − 0.4
    st = svc.status()
    assert st["cycle_in"] == "process" and st["mode"] == "realtime"
    assert st["cycle"] >= cycle + 25 and st["cycle_pid"] not in (None, os.getpid())


@pytest.mark.slow
def test_every_cycle_arrives_from_the_moment_the_demand_returns(remote, monkeypatch):
    """A demand of every cycle (ADS notifications, a recording, `subscribe_changes`) is in
    force when `demand_every_cycle` returns, however late its message reaches the cycle
    process: from the snapshot the server holds then on, every cycle arrives. Here the
    message is held 50 ms on its way (the sender thread on a busy host) while reads wake
    the cycle process, and a second demand is made meanwhile; before, a demand returned
    at once and the cycles in between arrived only where a read looked (an ADS stream
    every 3 cycles got 44, 50, 55)."""
    machine, sched, _svc = remote
    send = machine.control

    def late(message: tuple) -> None:
        if message[0] == "every":
            threading.Timer(0.05, send, (message,)).start()
        else:
            send(message)

    monkeypatch.setattr(machine, "control", late)
    seen: list[int] = []
    machine.subscribe(lambda snap: seen.append(snap.cycle))
    done = threading.Event()

    def reads() -> None:
        while not done.is_set():
            sched.sync()
            time.sleep(0.002)

    demands: dict[str, tuple[Any, int]] = {}

    def demand(who: str) -> None:
        release = sched.demand_every_cycle()
        demands[who] = (release, machine.snapshot.cycle)

    reader = threading.Thread(target=reads)
    reader.start()
    try:
        time.sleep(0.01)
        first_one = threading.Thread(target=demand, args=("first",))
        first_one.start()
        time.sleep(0.01)
        demand("second")  # while the first one's message is on its way
        first_one.join()
        first = min(cycle for _release, cycle in demands.values())
        wait_cycle(machine, first + 100)
    finally:
        done.set()
        reader.join()
    for release, _cycle in demands.values():
        release()
    after = [c for c in seen if c >= first]
    assert after == list(range(first, after[-1] + 1))


@pytest.mark.slow
def test_errors_and_events_cross_the_process_boundary(remote):
    _, _, svc = remote
    seen = []
    svc.subscribe_events(seen.append)
    svc.nc.run("G91 G01 X50 F600").result(timeout=5)  # runs for seconds
    with pytest.raises(AdsError) as e:
        svc.nc.run("G91 G01 X-50 F600").result(timeout=5)
    assert e.value.code == 0x708  # refused by the machine in the child, code kept
    svc.nc.reset().result(timeout=5)
    svc.nc.run("Y[COMP ON FRICT]").result(timeout=5)  # Y has frict_comp 0: 70495
    end = time.monotonic() + 5
    while not any(ev.diagnostic.error_id == 70495 for ev in seen):
        assert time.monotonic() < end, seen
        time.sleep(0.01)
    assert any(err["error_id"] == 70495 for err in svc.errors())


@pytest.mark.realtime
@pytest.mark.slow
def test_reload_swaps_in_the_child_and_here(lists_copy: Path):
    machine = RemoteMachine(load_machine(lists_copy), cycle_s=0.001, homed=True)
    sched = ProcessScheduler(machine, mode="realtime")
    svc = ObjectService(machine, sched)
    sched.start()
    try:
        wait_cycle(machine, 30)
        axis_list = lists_copy.parent / "achsmd1.lis"
        text = axis_list.read_text(encoding="utf-8")
        axis_list.write_text(
            text.replace("lr_param.temp_comp_offset_0 40", "lr_param.temp_comp_offset_0 90"),
            encoding="utf-8",
        )
        before = machine.cfg
        result = svc.commands.reload()
        assert result.ok, result.errors
        assert machine.cfg is not before
        assert machine.cfg.axes[1].params.temp_comp_offset_0 == 90
        cycle = machine.cycle
        wait_cycle(machine, cycle + 25)
        assert access.read_name(svc, "TEMPC::actual_offset", 1) == 90  # 90 − 0.4
        # save takes the live values from the snapshot received here
        access.write_name(svc, "TEMPC::coefficient", 1, 4100.0).result(timeout=5)
        saved = svc.commands.save()
        assert saved.ok and saved.files == [str(axis_list)]
        assert "lr_param.temp_comp_coefficient 4100" in axis_list.read_text(encoding="utf-8")
    finally:
        sched.stop()


@pytest.mark.realtime
@pytest.mark.slow
def test_same_values_as_the_stepped_machine(default_cfg):
    """Cycles count, not clocks: N free-running cycles in the child end in exactly the
    snapshot N stepped cycles give here (program started before the first cycle)."""
    program = "G90 G01 X20 Y-5 F3000\nX[COMP OFF TEMP]\nG01 X0 F6000\nM30\n"
    n = 900
    stepped = Machine(default_cfg, cycle_s=0.001, homed=True)
    stepped.start_program(program)
    want = stepped.step(n)
    machine = RemoteMachine(default_cfg, cycle_s=0.001, homed=True)
    sched = ProcessScheduler(machine, mode="free", max_cycles=n)
    machine.start_program(program)
    sched.start()
    end = time.monotonic() + 30
    while sched.running:
        assert time.monotonic() < end
        time.sleep(0.02)
    sched.stop()
    assert machine.snapshot.cycle == n
    np.testing.assert_array_equal(machine.snapshot.values, want.values)
    col = machine.layout.col("SIM::command_position")
    assert machine.snapshot.values[1, col] == -50_000  # Y went to −5 mm: the program ran


@pytest.mark.slow
def test_pyads_reads_and_writes_through_the_cycle_process(loop_thread, remote):
    _, _, svc = remote
    srv = AdsServer(svc, AdsOptions(port=0))
    run_in(loop_thread, srv.start())
    conn = pyads.Connection("127.0.77.1.1.1", 551, srv.address)
    conn.open()
    try:
        conn.set_timeout(5000)
        assert conn.read(0x120300, 0x10043, pyads.PLCTYPE_LREAL) == 4000.0
        conn.write(0x120300, 0x10043, 4200.0, pyads.PLCTYPE_LREAL)
        assert conn.read(0x120300, 0x10043, pyads.PLCTYPE_LREAL) == 4200.0
        with pytest.raises(pyads.ADSError) as e:
            conn.write(0x120300, 0x10042, 1, pyads.PLCTYPE_DINT)  # actual_offset: read-only
        assert e.value.err_code == 0x704
    finally:
        conn.close()
        run_in(loop_thread, srv.close())


@pytest.mark.slow
def test_the_cycle_process_ends_with_its_server(tmp_path):
    """SIGKILL the server process: the cycle process sees end of file and exits."""
    script = tmp_path / "server.py"
    script.write_text(
        textwrap.dedent(
            """
            import sys, time
            from geo_server.listfile import load_machine
            from geo_server.paths import default_startup_list
            from geo_server.machine.process import ProcessScheduler, RemoteMachine

            if __name__ == "__main__":
                m = RemoteMachine(load_machine(default_startup_list()))
                s = ProcessScheduler(m)
                s.start()
                while m.cycle < 10:
                    time.sleep(0.01)
                print(s.pid, flush=True)
                time.sleep(60)
            """
        ),
        encoding="utf-8",
    )
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        child = int(proc.stdout.readline())
        assert pid_alive(child)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        end = time.monotonic() + 10
        while pid_alive(child):
            assert time.monotonic() < end, "the cycle process outlived its server"
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait()


def pid_alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"  # a zombie has ended (its parent is gone or has not reaped it)
