"""The benchmark scripts still run against the current code (they are not part of the
package, so nothing else would notice an API change until someone benchmarks)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent.parent / "bench"
AXES = ("--axes", "1,8")


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


def test_bench_volcomp_prints_its_table():
    r = subprocess.run(
        [sys.executable, str(BENCH / "volcomp.py"), "--cycles", "100"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "| added per cycle (target ≤ 30 µs) |" in r.stdout, r.stdout


def test_bench_recorder_prints_its_table():
    r = subprocess.run(
        [sys.executable, str(BENCH / "recorder.py"), "--cycles", "400"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "| cycle, recording 20 values every cycle |" in r.stdout, r.stdout
