"""What went into the machine, cycle by cycle, to replay it (docs/recorder.md §4).

Recorded where the machine applies queued operations at a cycle boundary
(`Machine.input_taps`), so every transport's writes, NC text, resets, reloads and sensor
faults are caught with the cycle after which they took effect. One JSON object per line:

    {"cycle": 120, "op": "write", "items": [["TEMPC::coefficient", 1, 4300.0]]}
    {"cycle": 300, "op": "nc", "text": "G01 X10 F6000", "mdi": true}
    {"cycle": 900, "op": "reset"}
    {"cycle": 950, "op": "reload", "startup": "/path/hochlauf.lis"}
    {"cycle": 990, "op": "sensor_fault", "sensor": 0, "kind": "stuck", "sigma": 0.0}

Temperatures are writes (`TWIN::ambient_temperature`). Not recorded: the server's own
error-list entries and volumetric `UPDATE`s (their files are read outside the cycle).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from geo_server.dictionary import ObjectDef
from geo_server.machine.nc import parse_program
from geo_server.machine.port import (
    Operation,
    Reload,
    Reset,
    SensorFault,
    StartProgram,
    WriteObjects,
)
from geo_server.recorder.trace import TraceFileError


def op_to_json(cycle: int, op: Operation) -> dict[str, Any] | None:
    """The line for `op`, applied after cycle `cycle`; None for what is not replayed."""
    match op:
        case WriteObjects(items):
            return {"cycle": cycle, "op": "write", "items": [[_name(o), a, v] for o, a, v in items]}
        case StartProgram(_program, mdi, text):
            return {"cycle": cycle, "op": "nc", "text": text, "mdi": mdi}
        case Reset():
            return {"cycle": cycle, "op": "reset"}
        case Reload(cfg):
            return {"cycle": cycle, "op": "reload", "startup": str(cfg.startup_path)}
        case SensorFault(sensor, kind, sigma):
            return {
                "cycle": cycle,
                "op": "sensor_fault",
                "sensor": sensor,
                "kind": kind,
                "sigma": sigma,
            }
    return None


def _name(obj: ObjectDef | str) -> str:
    return obj if isinstance(obj, str) else obj.name


def json_to_op(line: dict[str, Any], names: dict[str, int], where: str) -> Operation:
    """The operation of one line (`names`: the machine's axis letters for NC text)."""
    kind = line.get("op")
    try:
        if kind == "write":
            return WriteObjects(tuple((str(n), int(a), v) for n, a, v in line["items"]))
        if kind == "nc":
            text = str(line["text"])
            mdi = bool(line.get("mdi", False))
            return StartProgram(parse_program(text, names, mdi=mdi), mdi, text)
        if kind == "reset":
            return Reset()
        if kind == "reload":
            from geo_server.listfile import load_machine

            return Reload(load_machine(Path(line["startup"])))
        if kind == "sensor_fault":
            return SensorFault(int(line["sensor"]), str(line["kind"]), float(line["sigma"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise TraceFileError(f"{where}: {kind} line is incomplete: {exc}") from None
    raise TraceFileError(
        f"{where}: unknown input {kind!r} (write, nc, reset, reload, sensor_fault)"
    )


def inputs_path(trace_path: str | Path) -> Path:
    """Where the inputs of a trace go: `run.csv` → `run.inputs.jsonl`."""
    p = Path(trace_path)
    return p.with_name(p.stem + ".inputs.jsonl")


def save_inputs(lines: list[dict[str, Any]], path: str | Path) -> Path:
    p = Path(path)
    p.write_text("".join(json.dumps(x) + "\n" for x in lines), encoding="utf-8")
    return p


def load_inputs(path: str | Path) -> list[dict[str, Any]]:
    """The lines of an inputs file, in order; bad lines name file and line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TraceFileError(f"{p}: cannot read: {exc}") from None
    out: list[dict[str, Any]] = []
    last = -1
    for n, raw in enumerate(text.splitlines(), start=1):
        if not raw.strip():
            continue
        try:
            line = json.loads(raw)
        except ValueError:
            raise TraceFileError(f"{p}:{n}: not JSON") from None
        cycle = line.get("cycle") if isinstance(line, dict) else None
        if not isinstance(cycle, int) or cycle < last:
            raise TraceFileError(f"{p}:{n}: needs a 'cycle' at or after the line before")
        last = cycle
        line["_where"] = f"{p}:{n}"
        out.append(line)
    return out
