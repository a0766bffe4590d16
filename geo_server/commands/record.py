"""Recordings asked for over an interface or the command line (docs/recorder.md §7):
one at a time, into the recordings folder (never a file of the machine), within
`RecorderLimits`."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from geo_server.commands.ports import Ports
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.machine.machine import Machine
from geo_server.machine.port import Operation
from geo_server.recorder import Recorder, RecordSpec, SelectionError, TraceFileError
from geo_server.recorder.paths import check_target, default_record_dir, machine_files, output_path
from geo_server.recorder.recorder import Recorded, RecorderLimits


class RecordingService:
    """The recording of one machine; `host` is the object service it records from."""

    def __init__(self, ports: Ports, host: Recorded) -> None:
        self._ports = ports
        self.host = host
        #: the recording under way and where it goes
        self.recording: Recorder | None = None
        self._lock = threading.Lock()
        #: where recordings asked for over an interface go (`run --record-dir`); None:
        #: `recordings/` beside the start-up list (recorder.paths.default_record_dir)
        self.record_dir: Path | None = None
        #: bounds of a recording (docs/limits.md, docs/recorder.md §8)
        self.limits = RecorderLimits()

    def start(
        self,
        spec: RecordSpec | dict[str, Any],
        out: str | Path = "geo-trace.csv",
        name: str = "",
        *,
        overwrite: bool = False,
        local: bool = False,
    ) -> dict[str, Any]:
        """Start recording `spec` into `out` (CSV or .parquet, the inputs beside it as
        `<stem>.inputs.jsonl`), streamed while it records and put in place by `stop`.
        An `out` from an interface (not `local`, the command line's own) is a file name
        in the recordings folder, an existing file replaced only with `overwrite`, never
        a file of the machine (recorder.paths); anything else is refused with 0x70B, as
        are settings outside `limits`. Another recording is refused with 0x708."""
        with self._lock:
            if self.recording is not None:
                raise AdsError(
                    AdsErrorCode.DEVICE_BUSY, "a recording runs already: stop it first", "record"
                )
            cfg = self._ports.machine.cfg
            try:
                if isinstance(spec, dict):
                    spec = RecordSpec.from_json(spec, self.limits)
                protected = machine_files(cfg)
                if local:
                    target = Path(out)
                    check_target(target, overwrite=True, protected=protected)
                else:
                    folder = self.record_dir or default_record_dir(cfg.startup_path)
                    folder.mkdir(parents=True, exist_ok=True)
                    target = output_path(
                        str(out),
                        folder,
                        overwrite=overwrite,
                        protected=protected,
                        max_text=self.limits.max_text,
                    )
                rec = Recorder(self.host, spec, name, out=target, limits=self.limits)
                self.recording = rec.start()
            except (SelectionError, ValueError) as exc:
                raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, str(exc), "record") from None
            except OSError as exc:  # the folder cannot be made or written
                raise AdsError(
                    AdsErrorCode.DEVICE_ERROR, f"record: cannot write {out}: {exc}", "record"
                ) from None
            return {**rec.status(), "file": str(target)}

    def stop(self) -> dict[str, Any]:
        """Stop the recording, write the rows it still holds and put its trace and
        inputs in place (in the calling thread: call it off the event loop)."""
        with self._lock:
            rec, self.recording = self.recording, None
        if rec is None:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDSTATE, "no recording runs", "record")
        try:
            return rec.finish()
        except (OSError, TraceFileError) as exc:
            raise AdsError(AdsErrorCode.DEVICE_ERROR, str(exc), "record") from None

    def tap_inputs(self, callback: Callable[[int, Operation], None]) -> Callable[[], None]:
        """Call `callback(cycle, operation)` for each input the cycle applies (a
        recording's inputs, docs/recorder.md §4) until the returned function is called;
        the cycle in its own process has no taps (a no-op)."""
        machine = self._ports.machine
        if not isinstance(machine, Machine):
            return lambda: None
        machine.input_taps.append(callback)
        return lambda: machine.input_taps.remove(callback)

    def status(self) -> dict[str, Any] | None:
        """What `status()["recording"]` shows; None while none runs."""
        rec = self.recording
        if rec is None:
            return None
        return {**rec.status(), "file": str(rec.out)}
