"""`geo-client` as a newcomer uses it, over each of the three transports against one real
server (stepped machine; Zenoh, Modbus and ADS on ephemeral loopback ports).

Expected values come from the default machine's lists: X is axis 1, linear, at 0 mm
after homing; TEMPC::actual_offset of X at 0 mm is 40 + 4000e-6·(0 − 100) = 39.6 →
40 increments = 4.0 µm (000 p.15 formula); C (axis 4) is rotary.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_port, run_in

from geo_server import access
from geo_server.client.cli import main
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService
from geo_server.transports.ads.server import AdsOptions, AdsServer
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions
from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.server import ZenohInterface

VIAS = ("zenoh", "modbus", "ads")


class Servers:
    def __init__(self, loop, startup) -> None:
        self.loop = loop
        self.service = ObjectService(Machine(load_machine(startup), homed=True))
        access.step(self.service, 25)  # ramps of the start-up selections ended
        self.zenoh_ep = f"tcp/127.0.0.1:{free_port()}"
        self.ifaces = [
            ZenohInterface(self.service, ZenohOptions(machine="cli", listen=[self.zenoh_ep])),
            ModbusInterface(self.service, ModbusOptions(port=0)),
            AdsServer(self.service, AdsOptions(port=0)),
        ]
        for iface in self.ifaces:
            run_in(loop, iface.start())

    def base(self, via: str) -> list[str]:
        if via == "zenoh":
            return ["--via", "zenoh", "--machine", "cli", "--connect", self.zenoh_ep]
        if via == "modbus":
            return ["--via", "modbus", "--connect", f"127.0.0.1:{self.ifaces[1].port}"]
        return ["--via", "ads", "--connect", f"127.0.0.1:{self.ifaces[2].port}"]

    def close(self) -> None:
        for iface in reversed(self.ifaces):
            run_in(self.loop, iface.close())


@pytest.fixture
def servers(loop_thread, lists_copy) -> Iterator[Servers]:
    s = Servers(loop_thread, lists_copy)
    yield s
    s.close()


def run(servers: Servers, via: str, *args: str, capfd) -> tuple[int, str, str]:
    code = main([*servers.base(via), "--timeout", "5", *args])
    out, err = capfd.readouterr()
    return code, out, err


@pytest.mark.parametrize("via", VIAS)
def test_read_several_targets_by_axis_name_in_engineering_units(servers, via, capfd):
    code, out, err = run(
        servers,
        via,
        "read",
        "--axis",
        "X",
        "TEMPC::coefficient",
        "TEMPC::actual_offset",
        "SIM::command_position",
        "BC::actual_backlash",  # the Zenoh spelling of `BC::actual backlash`
        capfd=capfd,
    )
    assert code == 0, err
    assert out.splitlines() == [
        "axis 1 (X) TEMPC::coefficient = 4000.0 µm/m",
        "axis 1 (X) TEMPC::actual_offset = 4.0 µm",
        "axis 1 (X) SIM::command_position = 0.0 mm",
        "axis 1 (X) BC::actual backlash = 0.0 µm",
    ]
    assert "Info:" not in err  # AdsLib's "connection closed by remote" stays quiet


@pytest.mark.parametrize("via", VIAS)
def test_raw_units_and_a_rotary_axis(servers, via, capfd):
    access.write_name(servers.service, "SIM::set_position", 4, 1_234_567)  # C at 123.4567°
    access.step(servers.service, 1)
    code, out, _ = run(
        servers, via, "--raw", "read", "--axis", "1", "TEMPC::actual_offset", capfd=capfd
    )
    assert (code, out.strip()) == (0, "axis 1 (X) TEMPC::actual_offset = 40 Incr.")
    code, out, _ = run(servers, via, "read", "--axis", "C", "SIM::command_position", capfd=capfd)
    assert (code, out.strip()) == (0, "axis 4 (C) SIM::command_position = 123.4567 °")


@pytest.mark.parametrize("via", VIAS)
def test_unknown_names_get_a_suggestion(servers, via, capfd):
    code, _, err = run(servers, via, "read", "TEMPC::coeficient", capfd=capfd)
    assert code == 1
    assert "unknown object name 'TEMPC::coeficient'; did you mean 'TEMPC::coefficient'" in err
    code, _, err = run(servers, via, "read", "--axis", "Q", "TEMPC::coefficient", capfd=capfd)
    assert code == 1 and "no axis named 'Q' (axes: X=1, Y=2, Z=3, C=4)" in err


@pytest.mark.parametrize("via", VIAS)
def test_reload_and_save_on_every_transport(servers, via, lists_copy, capfd):
    code, out, err = run(
        servers, via, "write", "--axis", "X", "TEMPC::coefficient", "4321", capfd=capfd
    )
    assert code == 0, err
    access.step(servers.service, 1)
    code, out, err = run(servers, via, "save", capfd=capfd)
    assert code == 0, err
    assert "saved" in out
    text = (lists_copy.parent / "achsmd1.lis").read_text(encoding="utf-8")
    assert "lr_param.temp_comp_coefficient 4321" in text
    code, out, err = run(servers, via, "reload", capfd=capfd)
    assert code == 0, err
    assert out.startswith("reloaded")


@pytest.mark.parametrize("via", VIAS)
def test_a_rejected_reload_says_why_on_every_transport(servers, via, lists_copy, capfd):
    axis1 = lists_copy.parent / "achsmd1.lis"
    text = axis1.read_text(encoding="utf-8")
    line = 1 + text.splitlines().index(
        next(x for x in text.splitlines() if x.startswith("lr_param.temp_comp_coefficient"))
    )
    axis1.write_text(text.replace("temp_comp_coefficient 4000", "temp_comp_coefficient 99999"))
    code, out, err = run(servers, via, "reload", capfd=capfd)
    assert code == 1
    assert err.startswith("error: reload rejected, machine unchanged: ")
    assert f"achsmd1.lis:{line}: " in err and "lr_param.temp_comp_coefficient" in err
    assert "warning" not in err and "deactivated" not in err
    access.step(servers.service, 1)
    code, out, err = run(servers, via, "errors", capfd=capfd)
    assert code == 0 and "reload rejected, machine unchanged" in out
    assert access.read_name(servers.service, "TEMPC::coefficient", 1) == 4000.0


@pytest.mark.parametrize("via", VIAS)
def test_status_is_readable_text_and_json_on_request(servers, via, capfd):
    code, out, err = run(servers, via, "status", capfd=capfd)
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith(f"cycle {servers.service.current(stale_ok=True).cycle}  1000 µs")
    assert "axes 1 X, 2 Y, 3 Z, 4 C" in lines
    code, out, _ = run(servers, via, "--json", "status", capfd=capfd)
    assert json.loads(out)["cycle"] == servers.service.current(stale_ok=True).cycle


def test_nc_and_reset_say_they_need_zenoh(servers, capfd):
    code, _, err = run(servers, "modbus", "reset", capfd=capfd)
    assert code == 2 and "available over Zenoh only" in err


@pytest.mark.parametrize("via", VIAS)
def test_no_server_is_one_line_and_exit_2(via):
    """Nothing listening: one line naming the address, exit 2, on every transport — no
    pymodbus log line, no AdsLib warnings (they write to the process' stderr, so the
    client runs as its own process)."""
    import subprocess
    import sys

    port = free_port()  # free a moment ago: nothing listens there
    where = f"tcp/127.0.0.1:{port}" if via == "zenoh" else f"127.0.0.1:{port}"
    client = [sys.executable, "-m", "geo_server.client.cli", "--via", via, "--connect", where]
    r = subprocess.run(
        [*client, "read", "--axis", "X", "TEMPC::coefficient"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    assert r.stderr.splitlines() == [f"error: no geo-server at {where} (connection refused)"]
    assert r.stdout == ""


def test_an_injected_ads_error_names_the_object_asked_for(servers, capfd):
    """Issue 45 #15: `read`/`write --axis X TEMPC::…` with every ADS request answered
    0x707: the first request is the lookup of axis X's number (SIM::axis_names); the
    message is the object's, and says the lookup was refused (before, it was reported
    against SIM::axis_names alone). With the axis by number, the object's own read."""
    servers.service.faults.inject("ads:error=0x707")
    lookup = (
        "axis 'X': its number could not be looked up "
        "(the read of SIM::axis_names was answered with ADS 0x707) (ADS 0x707)"
    )
    code, _, err = run(servers, "ads", "read", "--axis", "X", "TEMPC::coefficient", capfd=capfd)
    assert code == 1
    assert err.strip() == f"error: TEMPC::coefficient: {lookup}"
    code, _, err = run(servers, "ads", "write", "--axis", "X", "TEMPC::offset_0", "5", capfd=capfd)
    assert code == 1
    assert err.strip() == f"error: TEMPC::offset_0: {lookup}"
    code, _, err = run(servers, "ads", "read", "--axis", "1", "TEMPC::coefficient", capfd=capfd)
    assert err.strip() == (
        "error: read TEMPC::coefficient of axis 1 (0x120300/0x10043) failed (ADS 0x707)"
    )


def test_status_shows_what_the_engine_did():
    """`geo-client status` shows the server console's figures: under the exact engine (the
    default) what it computed and the catch-up, not a lateness that is always 0."""
    from geo_server.client.cli import status_lines

    st = {
        "cycle": 5000,
        "cycle_time_us": 1000,
        "engine": "exact",
        "mode": "realtime",
        "computed_cycles": 120,
        "engine_wakes": 20,
        "sync_p50_us": 408.4,
        "sync_p99_us": 746.0,
        "overruns": 0,
        "cycle_p50_us": 294.0,
        "kernel_p50_us": 115.2,
        "lateness_p50_us": 0.0,
    }
    assert status_lines(st)[1] == (
        "computed 120 (20 wake-ups)  catch-up p50 408 µs p99 746 µs  "
        "overruns 0  cycle p50 294 µs (kernel 115 µs)"
    )
    punctual = {**st, "engine": "punctual", "lateness_p50_us": 12.0, "lateness_p99_us": 80.6}
    assert status_lines(punctual)[1].startswith("lateness p50 12 µs p99 81 µs max 0 µs  ")


#: a trampoline: SIGINT to its default, then exec the program in the same process
_SIGINT_DEFAULT_THEN_EXEC = (
    "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
    "os.execv(sys.argv[1], sys.argv[1:])"
)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc/<pid>/maps")
@pytest.mark.parametrize("library", ["_json", "zenoh", "connected"])
def test_ctrl_c_while_starting_is_one_line_and_130(library: str) -> None:
    """Issue 45 #18: Ctrl-C while `geo-client` starts — while Python loads its modules
    (the `_json` extension, early among them: the dictionary's), or Zenoh, or once it
    waits for a server that accepted its connection and says nothing — ends it with the
    one line `interrupted` and status 130 (before: a traceback of 31 lines when it came
    during the imports). The moment is observed, not slept for: the library's shared
    object in the process' memory map, or the connection accepted. (geo-client's Zenoh
    read no longer loads numpy, the first variant's library until the interfaces'
    packages stopped importing their servers.) It ends at once, also while Zenoh still
    opens its session."""
    import contextlib
    import signal
    import socket
    import subprocess
    import sys
    import time

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        where = f"tcp/127.0.0.1:{listener.getsockname()[1]}"
        script = Path(sys.executable).with_name("geo-client")
        # Ctrl-C as at a terminal: SIGINT at its default in the client, whatever this
        # process has. An ignored signal stays ignored across exec, and Python then
        # installs no KeyboardInterrupt: the stress check (started as a shell's background
        # job, SIGINT ignored) failed here with the client's own "no reply" after 11 s
        args = [str(script), "--connect", where, "--timeout", "30", "read", "TEMPC::coefficient"]
        proc = subprocess.Popen(
            [sys.executable, "-c", _SIGINT_DEFAULT_THEN_EXEC, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        maps = Path(f"/proc/{proc.pid}/maps")
        t0 = time.monotonic()
        deadline = t0 + 60
        held = []
        seen, polls = None, 0
        while time.monotonic() < deadline and proc.poll() is None:
            polls += 1
            if library == "connected":
                listener.settimeout(0.01)
                with contextlib.suppress(TimeoutError):
                    held.append(listener.accept()[0])  # (the probe's, then Zenoh's)
                if len(held) >= 2:
                    seen = time.monotonic() - t0
                    break
            elif library in maps.read_text():
                seen = time.monotonic() - t0
                break
            time.sleep(0.001)
        signalled = time.monotonic() - t0
        proc.send_signal(signal.SIGINT)
        # at once, not when Zenoh's session open gives up: that waits 10 s for a server
        # that accepted and says nothing, and the client's main thread used to wait in it
        # (Ctrl-C took effect 10 s late)
        out, err = proc.communicate(timeout=5)
        for conn in held:
            conn.close()
    # (a failure says when the moment was seen, after how many looks, and when the
    # signal went: in the stress check all three variants once failed with exit 1 and
    # the client's own "no reply" error, cause not yet found)
    why = f"seen at {seen} s after {polls} looks, signalled at {signalled:.2f} s; {err!r}"
    assert (proc.returncode, err, out) == (130, "interrupted\n", ""), why


@pytest.mark.slow
@pytest.mark.parametrize("via", ["zenoh", "modbus", "ads"])
def test_wait_lets_a_client_started_first_answer_once_the_server_is_up(
    tmp_path: Path, via: str
) -> None:
    """Issue 48 #2: the README's tour reads right after `geo-server run … &`, before the
    server listens (0.4-2 s). `geo-client --wait S` tries until the server answers, up to
    S seconds: started before the server, it reads its cycle count once the server is
    up, over each transport. Without --wait the same read fails at once (exit 2)."""
    import signal
    import subprocess
    import sys

    from conftest import geo_server_cmd, stop_process

    zport, mport, aport, oport = free_port(), free_port(), free_port(), free_port()
    where = {
        "zenoh": f"tcp/127.0.0.1:{zport}",
        "modbus": f"127.0.0.1:{mport}",
        "ads": f"127.0.0.1:{aport}",
    }[via]
    client = [str(Path(sys.executable).with_name("geo-client")), "--via", via]
    client += ["--connect", where]
    early = subprocess.run([*client, "read", "SIM::cycle_count"], capture_output=True, text=True)
    assert early.returncode == 2 and "error:" in early.stderr
    waiting = subprocess.Popen(
        [*client, "--wait", "120", "read", "SIM::axis_names"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    ports = ["--zenoh-listen", f"tcp/127.0.0.1:{zport}", "--modbus-port", str(mport)]
    ports += ["--ads-port", str(aport), "--ads-udp-port", "0"]
    ports += ["--opcua-endpoint", f"opc.tcp://127.0.0.1:{oport}", "--opcua-no-companions"]
    server = subprocess.Popen(
        [*geo_server_cmd(), "run", "--homed", "--quiet", *ports],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        out, err = waiting.communicate(timeout=150)
        assert waiting.returncode == 0, err
        assert "X" in out and "C" in out
    finally:
        stop_process(server, signal.SIGINT, 30)
        stop_process(waiting, signal.SIGKILL, 5)
    printed = server.stdout.read() if server.stdout else ""
    status = [ln for ln in printed.splitlines() if ln.startswith("cycle ") and "STALLED" not in ln]
    assert status == []  # --quiet: no status lines
