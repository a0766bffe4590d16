"""The commands every interface takes as JSON (`cmd/fault`, `cmd/record` on Zenoh; docs/
faults.md, docs/recorder.md §7): the request's JSON checked and handed to the command
service, the answer a dict. Transport-neutral: an interface passes the payload's bytes and
sends the dict back its own way (an `AdsError` as its error)."""

from __future__ import annotations

import json
from typing import Any, Protocol

from geo_server.commands.faults import FaultService
from geo_server.commands.record import RecordingService
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.faults import FaultError


class Recording(Protocol):
    """What `record_command` uses of the object service: its recordings, and its
    status (the machine caught up first, so the rows are the ones due now)."""

    @property
    def recordings(self) -> RecordingService: ...
    def status(self) -> dict[str, Any]: ...


def fault_command(faults: FaultService, payload: bytes) -> dict[str, Any]:
    """`cmd/fault` (docs/faults.md): `{"inject": "<fault>"}`, `{"clear": <id> | "all"}`
    or `{}` (list). Answers `{"ok": true, …, "faults": [the active ones]}`; a fault that
    cannot be injected or cleared is 0x70B with the reason."""
    try:
        body = json.loads(payload or b"{}")
    except ValueError:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, "cmd/fault: payload is not JSON") from None
    if not isinstance(body, dict) or not set(body) <= {"inject", "clear"}:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDPARM,
            'cmd/fault: expected {"inject": "<fault>"}, {"clear": <id> | "all"} or {}',
        )
    out: dict[str, Any] = {"ok": True, "command": "fault"}
    try:
        if "inject" in body:
            out["injected"] = faults.inject(str(body["inject"]))
        if "clear" in body:
            which = body["clear"]
            if which != "all" and (isinstance(which, bool) or not isinstance(which, int)):
                raise FaultError(f'cmd/fault: clear takes a fault id or "all", not {which!r}')
            out["cleared"] = faults.clear(None if which == "all" else which)
    except FaultError as exc:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, str(exc)) from None
    out["faults"] = faults.status()
    return out


def record_command(service: Recording, payload: bytes, machine: str) -> dict[str, Any]:
    """`cmd/record` (docs/recorder.md §7): `{"start": {"objects": [...], "every": N,
    "trigger": "...", "pre": N, "post": N, "out": "trace.csv", "overwrite": false}}`,
    `{"stop": true}` (puts the trace and its inputs in place in the recordings folder on
    the server's host), or `{}` (status). Runs in a worker thread (a stop writes)."""
    try:
        body = json.loads(payload or b"{}")
    except ValueError:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, "cmd/record: payload is not JSON") from None
    if not isinstance(body, dict) or not set(body) <= {"start", "stop"} or len(body) > 1:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDPARM,
            'cmd/record: expected {"start": {"objects": [...], ...}}, {"stop": true} or {}',
        )
    out: dict[str, Any] = {"ok": True, "command": "record"}
    if "start" in body:
        spec_body = body["start"]
        if not isinstance(spec_body, dict):
            raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, "cmd/record: start takes an object")
        # `out` is a file name in the recordings folder (docs/recorder.md §7): checked
        # by the service, which refuses paths elsewhere and existing files unless
        # `overwrite` is true
        file = spec_body.get("out", "geo-trace.csv")
        overwrite = spec_body.get("overwrite", False)
        if not isinstance(file, str) or not isinstance(overwrite, bool):
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDPARM,
                "cmd/record: out must be a file name, overwrite true or false",
                "record",
            )
        spec = {k: v for k, v in spec_body.items() if k not in ("out", "overwrite")}
        out["recording"] = service.recordings.start(spec, file, machine, overwrite=overwrite)
    elif "stop" in body:
        out["recording"] = service.recordings.stop()
    else:
        st = service.status().get("recording")
        out["recording"] = st
    return out
