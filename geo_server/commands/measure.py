"""`cmd/measure` (docs/twin.md): an ISO 230-2 positioning test on the twin, one at a
time; on a running machine it moves the axis through object writes, in stepped mode it
steps the machine itself."""

from __future__ import annotations

import threading
import time
from typing import Any

from geo_server.commands.ports import Ports
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.seam import Measured
from geo_server.twin.measure import LiveBench, MeasureError, StepBench, plan_from_json, run_test


class MeasureService:
    """Measurements of one machine; `host` is the object service the bench reads and
    writes through (the same reads and writes as any client)."""

    def __init__(self, ports: Ports, host: Measured) -> None:
        self._ports = ports
        self.host = host
        self._lock = threading.Lock()
        self._cancel = threading.Event()

    def run(self, spec: Any) -> dict[str, Any]:
        """`spec` is the JSON plan of `twin.measure.plan_from_json`; returns the
        evaluation as a dict. Blocks until done: call it from a worker thread. At most
        `limits.measure_deadline` in all (`cancel` ends it). A bad plan is 0x706; one
        measurement at a time, and a test that cannot go on (axis not homed, moved by
        someone else, an NC error) is 0x708."""
        limits = self._ports.limits
        try:
            plan = plan_from_json(spec, self._ports.machine.cfg)
        except MeasureError as exc:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDDATA, str(exc), "measure") from None
        if not self._lock.acquire(blocking=False):
            raise AdsError(AdsErrorCode.DEVICE_BUSY, "a measurement is running", "measure")
        self._cancel.clear()
        try:
            bench = (
                LiveBench(
                    self.host,
                    timeout_s=limits.command_wait + 60.0,
                    deadline_s=limits.measure_deadline,
                    cancel=self._cancel,
                    settle=self._ports.settle_sync,
                )
                if self._ports.running
                else StepBench(self.host)
            )
            started = time.monotonic()
            ev = run_test(bench, plan)
        except MeasureError as exc:
            raise AdsError(AdsErrorCode.DEVICE_BUSY, str(exc), "measure") from None
        finally:
            self._lock.release()
        return {
            "ok": True,
            "command": "measure",
            "axis": plan.axis,
            "runs": plan.runs,
            "off": list(plan.compensation_off),
            "host_s": round(time.monotonic() - started, 3),
            **ev.as_dict(),
        }

    def cancel(self) -> None:
        """End a running measurement at its next wait (the server is shutting down)."""
        self._cancel.set()
