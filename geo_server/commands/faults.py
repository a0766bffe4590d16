"""Injected faults (docs/faults.md): the registry the transports ask per request
(`geo_server.faults.Faults`), with injecting and clearing what acts on the machine —
cycle overruns through the engine in this process, sensor faults through the twin."""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from typing import Any

from geo_server.commands.ports import Ports
from geo_server.faults import Fault, FaultError, Faults, parse_fault
from geo_server.machine.port import SensorFault
from geo_server.twin.engine import TwinEngine

#: `Scheduler.set_overrun` of the engine in this process
SetOverrun = Callable[..., None]

_THREAD_ONLY = "need the GEO cycle in a thread (geo-server run --cycle-in thread)"


class FaultService(Faults):
    """The faults of one machine. `set_overrun` and `twin` are None when the cycle runs
    in its own process (those faults are refused there)."""

    def __init__(
        self, ports: Ports, set_overrun: SetOverrun | None, twin: Callable[[], TwinEngine] | None
    ) -> None:
        super().__init__()
        self._ports = ports
        self._set_overrun = set_overrun
        self._twin = twin
        #: held from looking at what is active to acting on the machine: two injects at
        #: once (Zenoh's cmd/fault and OPC UA's InjectFault run on workers) never both
        #: find the place free, and a clear never undoes an overrun injected meanwhile
        self._acting = threading.Lock()

    def inject(self, fault: str | Fault) -> dict[str, Any]:
        """Inject a fault (text as in docs/faults.md, or parsed) and return it as listed
        in `status()`. Transport faults act on the next request; a cycle overrun from
        the next cycle on; a sensor fault at the next cycle boundary. Raises
        `FaultError` (a clear message) for a fault this machine cannot have."""
        f = parse_fault(fault) if isinstance(fault, str) else fault
        with self._acting:
            if f.target == "cycle":
                return self._overrun(f)
            if f.target == "sensor":
                return self._sensor(f)
            return self.add(f).as_dict()

    def clear(self, ident: int | None = None) -> list[dict[str, Any]]:
        """Clear fault `ident` (None: every fault) and undo what it did: overruns stop,
        a sensor reads its node again from its next sample. Returns the faults cleared;
        an `ident` that is not active raises `FaultError`."""
        with self._acting:
            gone = self.remove(ident)
            if ident is not None and not gone:
                active = ", ".join(str(f["id"]) for f in self.status()) or "none"
                raise FaultError(f"no active fault {ident} (active: {active})")
            for f in gone:
                if f.target == "cycle" and self._set_overrun is not None:
                    self._set_overrun(0, 0)
                elif f.target == "sensor" and self._twin is not None:
                    self._ports.apply(SensorFault(self._twin().sensor_index(f.sensor), ""))
            return [f.as_dict() for f in gone]

    def _overrun(self, f: Fault) -> dict[str, Any]:
        if self._set_overrun is None:
            raise FaultError(f"fault {f.text!r}: cycle overruns {_THREAD_ONLY}")
        active = self.of("cycle")
        if active:
            raise FaultError(
                f"fault {f.text!r}: overrun fault {active[0].ident} is active; clear it first"
            )
        cycles = max(1, round(f.value / (self._ports.machine.cycle_s * 1000)))
        added = self.add(f)
        self._set_overrun(cycles, f.every, lambda: self.hit(added))
        return added.as_dict()

    def _sensor(self, f: Fault) -> dict[str, Any]:
        if self._twin is None:
            raise FaultError(f"fault {f.text!r}: sensor faults {_THREAD_ONLY}")
        twin = self._twin()
        try:
            k = twin.sensor_index(f.sensor)
        except LookupError as exc:
            raise FaultError(f"fault {f.text!r}: {exc}") from None
        if any(twin.sensor_index(g.sensor) == k for g in self.of("sensor")):
            raise FaultError(f"fault {f.text!r}: that sensor has a fault already; clear it first")
        added = self.add(f)
        self._ports.apply(SensorFault(k, f.kind, f.value))
        return added.as_dict()


def inject_faults(specs: list[str] | None, faults: FaultService, label: str = "") -> bool:
    """`run --fault`: inject each fault before the first cycle (docs/faults.md);
    False (after saying why) when one cannot be."""
    for spec in specs or ():
        try:
            fault = faults.inject(spec)
        except FaultError as exc:
            print(f"error: {label}{exc}", file=sys.stderr)
            return False
        print(f"{label}fault {fault['id']} injected: {fault['fault']}", file=sys.stderr)
    return True
