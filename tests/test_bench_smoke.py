"""The benchmark scripts still run against the current code (they are not part of the
package, so nothing else would notice an API change until someone benchmarks)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"
AXES = ("--axes", "1,8")


@pytest.mark.slow
def test_bench_server_runs_and_dumps_its_cycles(tmp_path):
    dump = tmp_path / "cycles.npz"
    r = subprocess.run(
        [
            sys.executable,
            str(BENCH / "server.py"),
            "--stats-size",
            "100",
            "--dump",
            str(dump),
            "--",
            "--no-zenoh",
            "--no-modbus",
            "--no-ads",
            "--no-opcua",
            "--homed",
            "--engine",
            "punctual",  # every cycle computed on its deadline: 60 lateness records
            "--cycles",
            "60",
            "--status-period",
            "0.1",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert "stopped after 60 cycles" in r.stdout
    data = np.load(dump)
    assert len(data["lateness_us"]) == 60 and len(data["cycle_us"]) == 60
    assert int(data["cycle_errors"]) == 0


def test_bench_kernel_prints_its_table():
    r = subprocess.run(
        [sys.executable, str(BENCH / "kernel.py"), "--cycles", "20", "--ref-cycles", "3", *AXES],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    rows = [line for line in r.stdout.splitlines() if line.startswith("| 1 |")]
    rows += [line for line in r.stdout.splitlines() if line.startswith("| 8 |")]
    assert len(rows) == 2, r.stdout


@pytest.mark.slow
def test_bench_batch_prints_its_table():
    r = subprocess.run(
        [sys.executable, str(BENCH / "batch.py"), "--passes", "6"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    rows = [line for line in r.stdout.splitlines() if line.startswith("| pass of ")]
    assert len(rows) == 6, r.stdout


@pytest.mark.slow
def test_bench_volcomp_prints_its_table():
    r = subprocess.run(
        [sys.executable, str(BENCH / "volcomp.py"), "--cycles", "100"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "| added per cycle |" in r.stdout, r.stdout


@pytest.mark.slow
def test_bench_recorder_prints_its_table():
    r = subprocess.run(
        [sys.executable, str(BENCH / "recorder.py"), "--cycles", "400"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "| cycle, recording 20 values every cycle |" in r.stdout, r.stdout


@pytest.mark.slow
def test_bench_fleet_isolation_prints_its_table():
    """A fleet of 3, every phase briefly (quiet, notifications, client gone, flood)."""
    r = subprocess.run(
        [sys.executable, str(BENCH / "fleet_isolation.py"), "--quick"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "| flood on m1 | ADS m3 |" in r.stdout, r.stdout
    assert '"granted": 3' in r.stdout, r.stdout


def test_bench_addresses_come_from_the_dictionary(monkeypatch):
    """The benchmarks take every address from objects/ (bench/common.py `address`):
    TEMPC::offset_0 is ID 0x44, so axis 1 is ADS 0x120300 / (1 << 16 | 0x44) and the
    holding registers 4·0x44 = 272 (two: a DINT) — docs/design.md §2 addressing."""
    monkeypatch.syspath_prepend(str(BENCH))
    from common import address

    a = address("TEMPC::offset_0", 1, machine="mill")
    assert (a.index_group, a.index_offset) == (0x120300, 0x10044)
    assert (a.register, a.registers, a.size) == (272, 2, 4)
    assert a.raw_key == "cnc/mill/ads/551/0x120300/0x10044"
    assert a.named_key == "cnc/mill/axis/1/tempc/offset_0"
    c = address("TEMPC::coefficient", 3)
    assert (c.index_offset, c.register, c.registers, c.size) == (0x30043, 268, 4, 8)
