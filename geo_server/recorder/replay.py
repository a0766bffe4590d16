"""Replaying recorded inputs into a stepped run (docs/recorder.md §5).

A fresh machine from the start-up list, stepped cycle by cycle; each recorded input is
queued when the machine is at the cycle after which it took effect in the recording, so
it is applied in the same cycle boundary. What the recording started from must be what
the replay starts from — a server's first cycle (`geo-server run --record`), or a stepped
test from its start: then the replay reproduces the recorded values exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from geo_server import access, jit
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.recorder.inputs import json_to_op
from geo_server.recorder.recorder import Recorder, RecordSpec
from geo_server.recorder.trace import Trace, TraceFileError
from geo_server.service import ObjectService


def replay(
    startup: str | Path,
    inputs: list[dict[str, Any]],
    spec: RecordSpec,
    cycles: int,
    *,
    homed: bool = True,
    cycle_ms: float = 1.0,
    time_scale: float | None = None,
    name: str = "replay",
) -> Trace:
    """Run `cycles` cycles of a fresh machine with `inputs` applied; record `spec`."""
    jit.load()  # compiled from the first cycle (the numbers are the same either way)
    machine = Machine(
        load_machine(Path(startup)), cycle_s=cycle_ms / 1000, homed=homed, time_scale=time_scale
    )
    service = ObjectService(machine)  # stepped
    spec = RecordSpec(spec.objects, spec.every, spec.trigger, spec.pre, spec.post, spec.samples)
    spec.inputs = False
    recorder = Recorder(service, spec, name).start()
    todo = sorted(inputs, key=lambda line: int(line["cycle"]))
    i = 0
    while machine.cycle < cycles and not recorder.done:
        while i < len(todo) and int(todo[i]["cycle"]) <= machine.cycle:
            line = todo[i]
            where = str(line.get("_where", f"input {i + 1}"))
            if int(line["cycle"]) < machine.cycle:
                raise TraceFileError(
                    f"{where}: cycle {line['cycle']} is before the replay's first cycle"
                )
            machine.submit(json_to_op(line, machine.names, where))
            i += 1
        access.step(service, 1)
    trace = recorder.stop()
    trace.meta["replayed"] = str(startup)
    return trace
