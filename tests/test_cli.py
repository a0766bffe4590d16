"""The console scripts as a user runs them: from another directory, as subprocesses."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port

BIN = Path(sys.executable).parent
QUICK_STATUS = ("--status-period", "0.1")


def script(name: str) -> list[str]:
    """The installed console script (falls back to `python -m` in odd environments)."""
    exe = BIN / name
    if exe.exists():
        return [str(exe)]
    module = {"geo-server": "geo_server.cli", "geo-client": "geo_server.client.cli"}[name]
    return [sys.executable, "-m", module]


def run(args: list[str], cwd: Path, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


@pytest.mark.slow
def test_objects_from_any_directory(tmp_path):
    r = run([*script("geo-server"), "objects"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "| TEMPC::coefficient | 0x120300 | 0x0043 | axis | REAL64 | 8 | read/write |" in r.stdout
    r = run([*script("geo-server"), "objects", "--format", "json"], tmp_path)
    rows = json.loads(r.stdout)
    assert {"name": "SIM::cycle_count", "id": "0x0001", "scope": "machine"}.items() <= {
        k: v for k, v in next(x for x in rows if x["name"] == "SIM::cycle_count").items()
    }.items()
    r = run([*script("geo-server"), "objects", "--format", "csv"], tmp_path)
    assert r.stdout.splitlines()[0].startswith("name,index_group,id,")


@pytest.mark.slow
def test_check_exit_codes(tmp_path, lists_copy):
    r = run([*script("geo-server"), "check"], tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "4 axes (1=X, 2=Y, 3=Z, 4=C)" in r.stdout
    # a broken table deactivates one compensation -> 1, with file and line
    comp = lists_copy.parent / "achskw2.lis"
    text = comp.read_text(encoding="utf-8")
    comp.write_text(
        text.replace("kw.ssfk.table[1].setpoint -199306", "kw.ssfk.table[1].setpoint -300000"),
        encoding="utf-8",
    )
    r = run([*script("geo-server"), "check", str(lists_copy)], tmp_path)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "achskw2.lis:" in r.stdout and "110476" in r.stdout
    # an axis list that has to be skipped (an error, as for reload) -> 1, with the line
    comp.write_text(text, encoding="utf-8")
    startup = lists_copy.read_text(encoding="utf-8")
    lists_copy.write_text(
        startup.replace("achs_mds_log_ax_nr[2] 3", "achs_mds_log_ax_nr[2] 1"), encoding="utf-8"
    )
    r = run([*script("geo-server"), "check", str(lists_copy)], tmp_path)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "axis 1 defined twice" in r.stdout and "1 errors" in r.stdout
    # unreadable lists -> 2
    r = run([*script("geo-server"), "check", str(tmp_path / "nope.lis")], tmp_path)
    assert r.returncode == 2
    assert "nope.lis" in r.stderr


def test_objects_into_a_closed_pipe_ends_quietly(tmp_path):
    """`geo-server objects | head -1`: no BrokenPipeError traceback, exit 0."""
    r = subprocess.run(
        f"{' '.join(script('geo-server'))} objects --format json | head -c 10",
        shell=True,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and len(r.stdout) == 10
    assert "Traceback" not in r.stderr and "BrokenPipe" not in r.stderr, r.stderr


@pytest.mark.realtime
@pytest.mark.slow
@pytest.mark.parametrize(
    "cycle_in, engine", [("thread", "exact"), ("process", "exact"), ("process", "punctual")]
)
def test_run_serves_and_stops(tmp_path, cycle_in, engine):
    zport, mport, aport, oport = free_port(), free_port(), free_port(), free_port()
    r = run(
        [
            *script("geo-server"),
            "run",
            "--opcua-endpoint",
            f"opc.tcp://127.0.0.1:{oport}",
            "--opcua-cert-dir",
            str(tmp_path / "opcua"),
            "--cycle-in",
            cycle_in,
            "--engine",
            engine,
            "--homed",
            "--cycles",
            "300",
            "--status-period",
            "0.1",
            "--zenoh-listen",
            f"tcp/127.0.0.1:{zport}",
            "--modbus-port",
            str(mport),
            "--ads-port",
            str(aport),
        ],
        tmp_path,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert f"tcp/127.0.0.1:{zport}" in r.stdout
    assert f"127.0.0.1:{mport}" in r.stdout
    assert f"127.0.0.1:{aport}" in r.stdout
    assert f"opcua: opc.tcp://127.0.0.1:{oport}" in r.stdout  # (ready later: background)
    # the punctual engine reports its lateness, the exact one what it computed
    assert ("lateness p50" if engine == "punctual" else "catch-up p50") in r.stdout
    assert f"{engine} engine, cycle in its own {cycle_in}" in r.stdout
    assert "stopped after 300 cycles" in r.stdout  # --cycles is exact, no overshoot


@pytest.mark.realtime
def test_ctrl_c_stops_run_cleanly(tmp_path):
    """Ctrl-C reaches the whole process group (server and GEO-cycle process): `run`
    stops cleanly, exit 0, no traceback from either process."""
    proc = subprocess.Popen(
        [
            *script("geo-server"),
            "run",
            "--no-zenoh",
            "--no-modbus",
            "--no-ads",
            "--no-opcua",
            *QUICK_STATUS,
        ],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    try:
        assert "Ctrl-C stops" in proc.stdout.readline()
        assert proc.stdout.readline().startswith("cycle ")  # the cycle runs
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "stopped after" in out
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err


@pytest.mark.realtime
@pytest.mark.slow
def test_run_program_option(tmp_path):
    """`--program`: a missing or broken program is exit 2 with the reason (and the line),
    no traceback; a good one runs (here on a 2 ms cycle, for exactly 120 cycles)."""
    base = [*script("geo-server"), "run", "--no-zenoh", "--no-modbus", "--no-ads", "--no-opcua"]
    r = run([*base, "--program", str(tmp_path / "missing.nc")], tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "error: NC program" in r.stderr and "missing.nc" in r.stderr
    bad = tmp_path / "bad.nc"
    bad.write_text("G90 G01 X10 F1000\nG01 Q?? F1000\n", encoding="utf-8")
    r = run([*base, "--program", str(bad)], tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "error: NC program" in r.stderr and "line 2" in r.stderr
    good = tmp_path / "good.nc"
    good.write_text("G90 G01 X10 F1000\nM30\n", encoding="utf-8")
    r = run(
        [*base, "--homed", "--program", str(good), "--cycle-ms", "2", "--cycles", "120"],
        tmp_path,
    )
    assert r.returncode == 0, r.stderr
    assert "cycle 2 ms" in r.stdout and "stopped after 120 cycles" in r.stdout
    # progress reports: 10 mm at 1000 mm/min take 0.6 s = 300 cycles, so the program
    # is still at line 1 when run stops after 120
    assert f"program {good}: started" in r.stdout
    assert "program line 1" in r.stdout


@pytest.mark.realtime
@pytest.mark.parametrize(
    ("busy", "option"),
    [
        ("zenoh", "--zenoh-listen"),
        ("modbus", "--modbus-port"),
        ("ads", "--ads-port"),
        ("opcua", "--opcua-endpoint"),
    ],
)
def test_run_with_a_busy_port_fails_cleanly(tmp_path, busy, option):
    """A port in use ends `run` with exit 2 and one clear line that names the address
    and the option to change (no Rust source paths, no traceback), instead of a hang
    with the interfaces that did start still open."""
    zport, mport, aport, oport = free_port(), free_port(), free_port(), free_port()
    blocker = socket.socket()
    ports = {"zenoh": zport, "modbus": mport, "ads": aport, "opcua": oport}
    blocker.bind(("127.0.0.1", ports[busy]))
    blocker.listen()
    try:
        r = run(
            [
                *script("geo-server"),
                "run",
                "--cycles",
                "50",
                "--zenoh-listen",
                f"tcp/127.0.0.1:{zport}",
                "--modbus-port",
                str(mport),
                "--ads-port",
                str(aport),
                "--opcua-endpoint",
                f"opc.tcp://127.0.0.1:{oport}",
                "--opcua-cert-dir",
                str(tmp_path / "opcua"),
            ],
            tmp_path,
            timeout=60,
        )
    finally:
        blocker.close()
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"error: {busy} interface did not start" in r.stderr
    assert "is in use" in r.stderr and option in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and ".rs:" not in r.stderr


@pytest.mark.slow
def test_init_copies_the_default_machine(tmp_path):
    """`init DIR` gives the user lists of their own (save must not edit an installed
    package); the copy loads like the original and a second init refuses to overwrite."""
    dest = tmp_path / "mymachine"
    r = run([*script("geo-server"), "init", str(dest)], tmp_path)
    assert r.returncode == 0, r.stderr
    names = sorted(p.name for p in dest.iterdir())
    assert names == [
        *[f"achskw{i}.lis" for i in range(1, 5)],
        *[f"achsmd{i}.lis" for i in range(1, 5)],
        "demo_temperature.nc",
        "hochlauf.lis",
        "twin.toml",
    ]
    r = run([*script("geo-server"), "check", str(dest / "hochlauf.lis")], tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "4 axes (1=X, 2=Y, 3=Z, 4=C)" in r.stdout
    # the copies are the user's: no "generated, edit the script" advice in them
    for p in dest.glob("*.lis"):
        text = p.read_text(encoding="utf-8")
        assert "edit the script, not this file" not in text, p.name
    header = (dest / "achsmd1.lis").read_text(encoding="utf-8").splitlines()[3]
    assert (
        header == "# Copied from geo-server's default machine by `geo-server init`: yours to edit."
    )
    r = run([*script("geo-server"), "init", str(dest)], tmp_path)
    assert r.returncode == 2 and "already has" in r.stderr
    assert run([*script("geo-server"), "init", "--force", str(dest)], tmp_path).returncode == 0


def test_modbus_map_command(tmp_path):
    r = run([*script("geo-server"), "modbus-map", "--format", "csv"], tmp_path)
    assert r.returncode == 0
    assert any("TEMPC::coefficient" in line and "268" in line for line in r.stdout.splitlines())


@pytest.mark.realtime
@pytest.mark.slow
def test_run_program_reports_its_end(tmp_path):
    """1 mm at 6000 mm/min takes 10 ms: the program ends long before the 300 cycles."""
    prog = tmp_path / "short.nc"
    prog.write_text("N10 G90 G01 X1 F6000\nN20 M30\n", encoding="utf-8")
    quiet = ("--no-zenoh", "--no-modbus", "--no-ads", "--no-opcua", "--status-period", "0.05")
    r = run(
        [
            *script("geo-server"),
            "run",
            *quiet,
            "--homed",
            "--program",
            str(prog),
            "--cycles",
            "300",
        ],
        tmp_path,
    )
    assert r.returncode == 0, r.stderr
    assert f"program {prog}: started" in r.stdout
    assert f"program {prog}: ended at cycle" in r.stdout and "(line 2)" in r.stdout
    # Y has no lr_param.frict_comp: COMP ON FRICT is P-ERR-70495 (000 p.73), the program stops
    prog.write_text("N10 Y[COMP ON FRICT]\nN20 M30\n", encoding="utf-8")
    r = run(
        [
            *script("geo-server"),
            "run",
            *quiet,
            "--homed",
            "--program",
            str(prog),
            "--cycles",
            "300",
        ],
        tmp_path,
    )
    assert r.returncode == 0, r.stderr
    assert f"program {prog}: stopped at line 1: <nc>:1: [70495]" in r.stdout, r.stdout


@pytest.mark.realtime
def test_run_removes_what_an_interrupted_save_left(tmp_path, lists_copy):
    """A save killed between writing its temporary file and renaming it leaves
    `.<list>.<8 chars>.tmp` beside the list; the next start removes exactly those."""
    folder = lists_copy.parent
    orphan = folder / ".achsmd1.lis.k3j_x9a2.tmp"
    orphan.write_text("half a list")
    keep = folder / ".notes.tmp"
    keep.write_text("not ours")
    quiet = (
        "--no-zenoh",
        "--no-modbus",
        "--no-ads",
        "--no-opcua",
        "--cycle-in",
        "thread",
        "--cycles",
        "5",
    )
    r = run([*script("geo-server"), "run", str(lists_copy), *quiet], tmp_path)
    assert r.returncode == 0, r.stderr
    assert not orphan.exists() and keep.exists()
    assert f"removed {orphan}: left over from an interrupted save" in r.stderr


def test_where_the_cycle_runs_by_default_and_priority_without_os_nice(monkeypatch):
    """The punctual engine on Linux and macOS: its own process; Windows (no fd pipes, no
    os.nice) and the exact engine: a thread; and
    asking for priority where os.nice does not exist is not an error."""
    from geo_server.cli import default_cycle_in
    from geo_server.machine import process

    assert default_cycle_in("posix", "punctual") == "process"
    assert default_cycle_in("nt", "punctual") == "thread"
    # the exact engine computes where it is observed: a process adds only a round trip
    assert default_cycle_in("posix", "exact") == "thread"
    assert default_cycle_in("posix") == "thread"
    monkeypatch.delattr(process.os, "nice", raising=False)
    process._raise_priority()  # logs "keeps normal priority", raises nothing


def test_check_exits_1_when_a_value_was_replaced_by_its_default(tmp_path, lists_copy):
    """`40O0` (a letter O) for the coefficient: the CNC warns and uses the default
    (002/003 §1.3), so the machine loads; `check` says so and exits 1, since the
    machine would run with 0 where the list meant 4000."""
    axis_list = lists_copy.parent / "achsmd1.lis"
    text = axis_list.read_text(encoding="utf-8")
    broken = text.replace(
        "lr_param.temp_comp_coefficient 4000", "lr_param.temp_comp_coefficient 40O0"
    )
    assert broken != text
    axis_list.write_text(broken, encoding="utf-8")
    r = run([*script("geo-server"), "check", str(lists_copy)], tmp_path)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "achsmd1.lis:" in r.stdout and "'40O0'" in r.stdout
    assert "1 values replaced by their default" in r.stdout


def test_check_names_the_first_cause_first(tmp_path, lists_copy):
    """Issue 45 #12: a typo `achs_mdz[0]` in the start-up list loses axis X; the twin
    file then names an axis the machine lacks, which stops the load (exit 2). The typo's
    diagnostic, with its suggestion, comes before the twin file's error (before, only
    the twin file's error was printed)."""
    assert (lists_copy.parent / "twin.toml").exists()
    text = lists_copy.read_text(encoding="utf-8")
    lists_copy.write_text(text.replace("achs_mds[0] ", "achs_mdz[0] ", 1), encoding="utf-8")
    r = run([*script("geo-server"), "check", str(lists_copy)], tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.splitlines()
    assert "achs_mdz[0]: unknown entry" in lines[0] and "did you mean achs_mds[0]?" in lines[0]
    assert lines[-1].startswith("error: ") and "twin.toml:" in lines[-1]
    assert "no axis 'X'" in lines[-1]
