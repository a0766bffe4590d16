"""The recorder under attack (issue 30 items 3, 6, 7; docs/recorder.md §7–8,
docs/security.md): a Zenoh peer naming files outside the recordings folder, over the
machine's lists, through symbolic links; recorder settings of 10⁹; recordings of every
object that must stream in bounded memory; inputs flooding a recording that awaits its
trigger; SIGKILL while a trace replaces a golden file.

Every attack goes over a real Zenoh session on loopback (GeoTestServer, stepped) where it
comes from the network; memory is asserted by the sizes the recorder holds (bytes and
counts), never by timing.
"""

from __future__ import annotations

import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from geo_clients.testing import GeoTestServer

from geo_server import access
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.listfile import load_machine
from geo_server.recorder import Recorder, RecordSpec, compare, load_trace
from geo_server.recorder.inputs import load_inputs
from geo_server.recorder.paths import RecordPathError, default_record_dir, output_path
from geo_server.recorder.recorder import (
    CHUNK_BYTES,
    CHUNK_ROWS,
    LIMITS,
    ROOM_CHUNKS,
    RecorderLimits,
)

pytest.importorskip("pyarrow", reason="Parquet traces need pyarrow (the test extra)")

INVALID = AdsErrorCode.DEVICE_INVALIDPARM  # 0x70B: docs/recorder.md §7
CHILD = Path(__file__).parent / "robust" / "record_child.py"


def record(srv: GeoTestServer, body: dict) -> dict:
    """`cmd/record` over the server's Zenoh session (AdsError on reply_err)."""
    z = srv.client("zenoh")
    reply = z.get(f"cnc/{srv.machine_name}/cmd/record", json.dumps(body).encode())
    return json.loads(reply[0][1])


def refused(srv: GeoTestServer, body: dict) -> AdsError:
    with pytest.raises(AdsError) as info:
        record(srv, body)
    assert info.value.code == INVALID, info.value  # never 0x700
    assert srv.service.recordings.recording is None
    return info.value


def start(out: str, **more: object) -> dict:
    return {"start": {"objects": ["SIM::cycle_count"], "out": out, **more}}


# ---------------------------------------------------------------------- paths (item 3)


def test_a_zenoh_peer_cannot_write_over_the_machines_lists(lists_copy: Path, tmp_path: Path):
    folder = lists_copy.parent
    axis_list = folder / "achsmd2.lis"
    original = axis_list.read_bytes()
    outside = tmp_path / "outside.csv"
    outside.write_text("not a trace\n", encoding="utf-8")
    (tmp_path / "elsewhere").mkdir()
    rec_dir = tmp_path / "recordings"
    with GeoTestServer(lists_copy, record_dir=rec_dir) as srv:
        srv.start("zenoh")
        rec_dir.mkdir()
        (rec_dir / "link.csv").symlink_to(outside)
        (rec_dir / "linkdir").symlink_to(tmp_path / "elsewhere")
        deep = "../" * 20
        attacks = {
            str(axis_list): "recordings folder",  # the attack of issue 30
            f"{deep}{str(axis_list).lstrip('/')}": "recordings folder",
            "../lists/achsmd2.lis": "recordings folder",
            str(outside): "recordings folder",
            "sub/x.csv": "recordings folder",
            "a\\b.csv": "recordings folder",
            "..": "recordings folder",
            str(rec_dir / "linkdir" / "x.csv"): "recordings folder",  # a link out
            "achsmd2.lis": "must end in .csv or .parquet",
            ".hidden.csv": "hidden name",
            "x" * 300 + ".csv": "at most 256 characters",
        }
        for out, message in attacks.items():
            for overwrite in (False, True):
                err = refused(srv, start(out, overwrite=overwrite))
                assert message in err.message, (out, err.message)
        err = refused(srv, start("link.csv", overwrite=True))
        assert "symbolic link" in err.message
        for bad in ({"out": 5}, {"out": "x.csv", "overwrite": "yes"}):
            err = refused(srv, {"start": {"objects": ["SIM::cycle_count"], **bad}})
            assert "out must be a file name, overwrite true or false" in err.message
        # the machine still serves, and a plain name still records
        assert srv.read("TEMPC::coefficient", 1, via="zenoh") == 4000.0
        started = record(srv, start("ok.csv"))["recording"]
        assert started["file"] == str(rec_dir.resolve() / "ok.csv")
        srv.step(3)
        assert record(srv, {"stop": True})["recording"]["rows"] == 3
    assert axis_list.read_bytes() == original
    assert outside.read_text(encoding="utf-8") == "not a trace\n"
    assert list((tmp_path / "elsewhere").iterdir()) == []
    cfg = load_machine(lists_copy)  # the list still loads
    assert not [d for d in cfg.diagnostics if d.severity == "error"]
    assert sorted(p.name for p in rec_dir.iterdir()) == [
        "link.csv",
        "linkdir",
        "ok.csv",
        "ok.inputs.jsonl",
    ]


def test_an_existing_recording_is_replaced_only_when_asked(tmp_path: Path):
    with GeoTestServer(record_dir=tmp_path) as srv:
        srv.start("zenoh")
        record(srv, start("run.csv"))
        srv.step(2)
        record(srv, {"stop": True})
        first = (tmp_path / "run.csv").read_bytes()
        err = refused(srv, start("run.csv"))
        assert "run.csv exists; ask for overwrite (true)" in err.message
        (tmp_path / "other.inputs.jsonl").write_text("", encoding="utf-8")
        err = refused(srv, start("other.csv"))  # its inputs file would be replaced
        assert "other.inputs.jsonl exists" in err.message
        record(srv, start(str(tmp_path / "run.csv"), overwrite=True))  # absolute, inside
        srv.step(4)
        assert record(srv, {"stop": True})["recording"]["rows"] == 4
        assert (tmp_path / "run.csv").read_bytes() != first
        assert load_trace(tmp_path / "run.csv").cycles.tolist() == [3, 4, 5, 6]


def test_the_machines_files_are_never_replaced_even_with_overwrite(lists_copy: Path):
    folder = lists_copy.parent
    grid = folder / "grid.csv"  # a correction file of the machine, say (CSV like a trace)
    grid.write_text("1,2\n", encoding="utf-8")
    for name in ("grid.csv", str(grid)):
        with pytest.raises(RecordPathError, match=r"grid\.csv is a file of the machine"):
            output_path(name, folder, overwrite=True, protected=[grid])
    # a recordings folder that is the lists folder itself: lists are never trace names
    with GeoTestServer(lists_copy, record_dir=folder) as srv:
        srv.start("zenoh")
        for name in ("hochlauf.lis", "achsmd1.lis", "twin.toml"):
            err = refused(srv, start(name, overwrite=True))
            assert "must end in .csv or .parquet" in err.message
    assert grid.read_text(encoding="utf-8") == "1,2\n"


def test_the_default_recordings_folder(lists_copy: Path, tmp_path: Path, monkeypatch):
    assert default_record_dir(lists_copy) == lists_copy.parent.resolve() / "recordings"
    monkeypatch.chdir(tmp_path)  # the shipped machine's folder is the product's own
    from geo_server.paths import default_startup_list

    assert default_record_dir(default_startup_list()) == tmp_path / "recordings"


def test_the_command_line_sets_the_folder_and_a_fleet_gets_one_per_machine(tmp_path, lists_copy):
    import argparse

    from geo_server.recorder import cli as recorder_cli

    with GeoTestServer(lists_copy) as srv:
        args = argparse.Namespace(record_dir=str(tmp_path / "rec"), record=None)
        assert recorder_cli.start_from_args(args, srv.service)
        assert srv.service.recordings.record_dir == tmp_path / "rec"
        srv.start("zenoh")
        record(srv, start("a.csv"))
        record(srv, {"stop": True})
    assert (tmp_path / "rec" / "a.csv").is_file()
    args = argparse.Namespace(record_dir=None)
    assert recorder_cli.record_dir(args) is None  # the service's default
    assert recorder_cli.record_dir(args, "m7", lists_copy) == default_record_dir(lists_copy) / "m7"
    args = argparse.Namespace(record_dir=str(tmp_path))
    assert recorder_cli.record_dir(args, "m7", lists_copy) == tmp_path / "m7"


# ---------------------------------------------------------------------- settings (item 7)


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ({"samples": 10**9}, "samples must be a whole number 1 … 10000000, not 1000000000"),
        (
            {"pre": 10**9, "trigger": "SIM::cycle_count > 5"},
            "pre must be a whole number 0 … 100000",
        ),
        ({"post": 10**9}, "post must be a whole number 0 … 10000000"),
        ({"every": 10**9}, "every must be a whole number 1 … 1000000, not 1000000000"),
        ({"every": 0}, "every must be a whole number 1 … 1000000, not 0"),
        ({"samples": -1}, "samples must be a whole number 1 … 10000000, not -1"),
        ({"pre": "5"}, "pre must be a whole number 0 … 100000, not '5'"),
        ({"every": True}, "every must be a whole number 1 … 1000000, not True"),
        ({"samples": 10**400}, "not an integer of 1329 bits"),
        ({"objects": ["SIM::cycle_count"] * 1000}, "objects must name 1 … 256 selectors, not 1000"),
        ({"objects": ["X" * 5000]}, "is longer than 256 characters"),
        ({"objects": [{"a": 1}]}, "'objects' must be a list of texts"),
        ({"trigger": 5}, "trigger must be a text"),
        ({"trigger": "SIM::cycle_count " + "> 1" * 100}, "is longer than 256 characters"),
    ],
)
def test_out_of_range_settings_are_refused_with_0x70b(tmp_path, setting, message):
    with GeoTestServer(record_dir=tmp_path) as srv:
        srv.start("zenoh")
        body = {"start": {"objects": ["SIM::cycle_count"], "out": "x.csv", **setting}}
        err = refused(srv, body)
        assert message in err.message, err.message
        assert list(tmp_path.iterdir()) == []  # nothing made


def test_pre_is_bounded_by_the_ring_of_a_wide_recording(tmp_path):
    with GeoTestServer(record_dir=tmp_path) as srv:
        srv.start("zenoh")
        body = {"objects": ["*"], "trigger": "SIM::cycle_count > 5", "pre": 100_000}
        err = refused(srv, {"start": {**body, "out": "x.csv"}})
        m = re.search(r"pre must be 0 … (\d+) for (\d+) values", err.message)
        assert m is not None, err.message
        most, columns = int(m[1]), int(m[2])
        row_bytes = (2 + columns) * 8
        chunk = max(CHUNK_ROWS[0], min(CHUNK_ROWS[1], CHUNK_BYTES // row_bytes))
        ring = (most + 1 + ROOM_CHUNKS * chunk) * row_bytes  # the most that fits
        assert ring <= LIMITS.buffer_bytes < ring + row_bytes
        started = record(srv, {"start": {**body, "pre": most, "out": "x.csv"}})["recording"]
        assert started["buffer_bytes"] <= LIMITS.buffer_bytes
        record(srv, {"stop": True})


# ---------------------------------------------------------------------- streaming (item 6)


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_a_recording_of_every_object_streams_in_bounded_memory(tmp_path, suffix):
    """The ring is the same size for 3000 rows as for 10 million; the rows reach the
    file while recording; the streamed file holds exactly what an in-memory recording of
    the same cycles holds."""
    with GeoTestServer(record_dir=tmp_path) as srv:
        svc = srv.service
        svc.recordings.start({"objects": ["*"], "samples": 10_000_000}, f"long{suffix}")
        long_ring = svc.recordings.recording.buffer_bytes
        svc.recordings.stop()
        svc.nc.run("G91 G01 X1 Y-1 F6000")  # moving: values change every cycle
        svc.recordings.start({"objects": ["*"]}, f"star{suffix}", srv.machine_name)
        rec = svc.recordings.recording
        mem = srv.record("*")
        assert rec.buffer_bytes == long_ring <= LIMITS.buffer_bytes
        assert rec.capacity == 1 + ROOM_CHUNKS * rec.chunk < 3000
        srv.step(3000)
        # a stepped machine waits for the writer when the ring is full: nothing dropped,
        # and everything but the last ring's worth is in the (temporary) file already
        assert rec._written >= 3000 - rec.capacity and rec.dropped == 0
        assert not (tmp_path / f"star{suffix}").exists()
        temps = [p for p in tmp_path.iterdir() if p.name.startswith(f".star{suffix}.")]
        assert len(temps) == 1 and temps[0].stat().st_size > 0
        done = svc.recordings.stop()
        golden = mem.stop()
    assert done["rows"] == 3000 and done["dropped"] == 0
    streamed = load_trace(tmp_path / f"star{suffix}")
    assert streamed.labels == golden.labels and streamed.types == golden.types
    assert streamed.meta == golden.meta
    result = compare(golden, streamed)
    assert result.ok and result.compared_rows == 3000, result.report()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [f"long{suffix}", "long.inputs.jsonl", f"star{suffix}", "star.inputs.jsonl"]
    )


def test_a_triggered_recording_streams_what_an_in_memory_one_holds(tmp_path):
    with GeoTestServer(record_dir=tmp_path) as srv:
        svc = srv.service
        spec = {"objects": ["TEMPC::*@1", "SIM::cycle_count"], "trigger": "SIM::cycle_count > 500"}
        svc.recordings.start({**spec, "pre": 300, "post": 5000}, "t.csv", srv.machine_name)
        rec = svc.recordings.recording
        mem = srv.record(*spec["objects"], trigger=spec["trigger"], pre=300, post=5000)
        srv.step(450)
        assert rec.status()["waiting"] and rec.status()["rows"] == 300
        assert rec._written == 0  # awaiting the trigger, only the ring holds them
        access.write_name(srv.service, "TEMPC::offset_0", 1, 140)
        srv.step(2000)
        done = svc.recordings.stop()
        golden = mem.stop()
    streamed = load_trace(tmp_path / "t.csv")
    assert done["rows"] == len(golden) == 300 + 1 + 1949
    assert streamed.meta["triggered_at"] == "501" == golden.meta["triggered_at"]
    assert compare(golden, streamed).ok
    assert load_inputs(tmp_path / "t.inputs.jsonl")[0]["cycle"] == 450


@pytest.mark.realtime
def test_a_real_time_recording_to_a_file_has_no_gaps(tmp_path):
    from geo_server.machine.machine import Machine
    from geo_server.machine.scheduler import Scheduler
    from geo_server.paths import default_startup_list
    from geo_server.service import ObjectService

    m = Machine(load_machine(default_startup_list()), homed=True)
    sched = Scheduler(m, mode="realtime", engine="exact")
    service = ObjectService(m, sched)
    service.recordings.record_dir = tmp_path
    service.recordings.start({"objects": ["SIM::cycle_count", "TEMPC::*@1"]}, "rt.csv")
    sched.start()
    try:
        service.nc.run("G91 G01 X2 F6000")
        deadline = time.monotonic() + 30
        while service.recordings.recording.status()["rows"] < 300 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        done = service.recordings.stop()
        sched.stop()
    trace = load_trace(tmp_path / "rt.csv")
    assert done["dropped"] == 0 and done["rows"] == len(trace) >= 300
    assert (trace.cycles[1:] - trace.cycles[:-1] == 1).all()  # every cycle, none twice
    assert (trace.column("SIM::cycle_count") == trace.cycles).all()


def test_inputs_while_the_trigger_is_awaited_are_bounded(tmp_path):
    """A flood of writes into a machine whose recording awaits its trigger: the inputs
    held never exceed `input_buffer_bytes` (the oldest go, counted)."""
    limit = 64 * 1024
    with GeoTestServer(record_dir=tmp_path) as srv:
        svc = srv.service
        svc.recordings.limits = RecorderLimits(input_buffer_bytes=limit)
        never = {"objects": ["SIM::cycle_count"], "trigger": "SIM::cycle_count < 0"}
        svc.recordings.start(never, "never.csv")
        rec = svc.recordings.recording
        spec = RecordSpec(never["objects"], trigger=never["trigger"])
        mem = Recorder(svc, spec, limits=svc.recordings.limits).start()  # in memory: the same
        for _ in range(40):
            for k in range(100):
                svc.submit_writes([svc.prepare_name("TEMPC::offset_0", 1, 40 + k)])
            srv.step(1)
            assert rec._inputs_bytes <= limit and mem._inputs_bytes <= limit
        st = rec.status()
        assert st["inputs_dropped"] > 0 and st["inputs"] + st["inputs_dropped"] == 4000
        assert st["inputs"] == len(rec._inputs) < 4000
        kept = mem.inputs
        assert kept[-1]["items"] == [["TEMPC::offset_0", 1, 139]]  # the newest are kept
        mem.stop()
        svc.recordings.stop()
    lines = load_inputs(tmp_path / "never.inputs.jsonl")
    assert len(lines) == st["inputs"]


# ---------------------------------------------------------------------- atomicity (item 6)


@pytest.mark.slow
def test_sigkill_while_a_trace_replaces_a_golden_file_leaves_old_or_whole_new(tmp_path):
    """A child records every object over an existing golden file (overwrite) in a loop,
    400 rows per trace, and is killed with SIGKILL at random moments — while it streams
    the rows or while it writes the last of them and replaces the file. After each kill
    the golden file is the one before, or a whole new trace. Every other round the kill
    comes only after the child said it replaced the file once, so new traces are seen
    however slow the host (before: kills 0.1-1.5 s after the start, which a busy host
    could all place before the first replacement)."""
    golden = tmp_path / "golden.csv"
    with GeoTestServer(record_dir=tmp_path) as srv:
        rec = srv.record("SIM::cycle_count")
        srv.step(7)
        rec.stop().save(golden)
    previous = golden.read_bytes()
    rng = random.Random(0x7EC0)
    child = subprocess.Popen(
        [sys.executable, str(CHILD), str(tmp_path), "400"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    outcomes = {"old": 0, "new": 0}
    try:
        assert child.stdin is not None and child.stdout is not None
        assert child.stdout.readline().strip() == "zygote"
        for r in range(10):
            child.stdin.write("go\n")
            child.stdin.flush()
            line = child.stdout.readline().split()
            assert line[0] == "ready", line
            if r % 2:  # after one replacement: a new whole trace at least
                assert child.stdout.readline().split() == ["replaced"]
            time.sleep(rng.uniform(0.0, 1.5))  # (a moment picked at random, any will do)
            os.kill(int(line[1]), signal.SIGKILL)
            said = child.stdout.readline().split()
            while said == ["replaced"]:
                said = child.stdout.readline().split()
            assert said == ["dead", "9"]
            now = golden.read_bytes()
            if now == previous:
                outcomes["old"] += 1
                continue
            trace = load_trace(golden)  # whole: it loads, every row of it
            assert len(trace) == 400, f"round {r}: {len(trace)} rows"
            assert trace.meta["selectors"] == "*" and len(trace.labels) > 100
            assert (trace.cycles[1:] - trace.cycles[:-1] == 1).all()
            assert now.endswith(b"\n")
            outcomes["new"] += 1
            previous = now
        child.stdin.close()
        assert child.wait(10) == 0
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(5)
        if child.stdout is not None:
            child.stdout.close()
    print(f"outcomes {outcomes}")
    assert outcomes["new"] >= 1, outcomes
    stray = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))
    assert all(
        re.fullmatch(r"\.golden\.(csv|inputs\.jsonl)\.[a-z0-9_]{8}\.tmp", n) for n in stray
    ), stray
    load_inputs(tmp_path / "golden.inputs.jsonl")  # the inputs file is whole too
