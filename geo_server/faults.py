"""Fault injection (docs/faults.md): the faults a test bench puts into a running server.

A *fault* is one line of text (the CLI's `--fault`, the Zenoh command `cmd/fault`, the
pytest plugin's `GeoTestServer.fault`) parsed into a `Fault`:

    <target>:<kind>[=<value>][,<option>=<value>...]

    ads:error=0x707,count=2          the next 2 ADS requests answer 0x707 (not ready)
    modbus:error=6,ops=write         every Modbus write answers exception 6 (busy)
    zenoh:error=0x719                every Zenoh query gets a reply_err with 0x719
    all:delay=250,objects=TEMPC::*   requests on TEMPC objects wait 250 ms first
    ads:drop,p=0.1,seed=7            one ADS request in ten gets no reply at all
    modbus:disconnect,count=1        the next Modbus request closes its connection
    cycle:overrun=40,every=1000      every 1000th GEO cycle overruns by 40 ms
    sensor@X:stuck                   the twin's sensor of axis X keeps its last reading
    sensor@1:noisy=0.5               … adds Gaussian noise of σ = 0.5 °C
    sensor@x_screw:open              … reads an open circuit (`OPEN_CIRCUIT_C`)

Transport faults are decided here (`Faults.decide`, pure, thread-safe); the transports
carry them out, the scheduler the overruns and the twin the sensor faults. Every fault
is listed in `status()["faults"]` with its hits until it is cleared — explicitly
(`clear`), or by itself once its `count` is used up.

What a fault may ask for is bounded (docs/faults.md §1, *Bounds*): `MAX_FAULTS` at once,
`MAX_TEXT` characters of text, one `objects=` pattern of at most `MAX_PATTERN`
characters, compiled once when the fault is parsed — so a request pays at most
`MAX_FAULTS` matches of a short pattern against a short name, and nothing of a fault
stays behind once it is cleared.
"""

from __future__ import annotations

import asyncio
import fnmatch
import math
import random
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any, TypeVar

from geo_server.errors import AdsErrorCode, GeoError
from geo_server.interfaces import FAULT_KINDS, REGISTRY


class FaultKind(StrEnum):
    """What a fault does (docs/faults.md): to a request (delay, drop, error,
    disconnect), to the cycle (overrun) or to a sensor of the twin (stuck, noisy, open).
    A `str` too: the text form and the JSON of `status()` are its value."""

    DELAY = "delay"
    DROP = "drop"
    ERROR = "error"
    DISCONNECT = "disconnect"
    OVERRUN = "overrun"
    STUCK = "stuck"
    NOISY = "noisy"
    OPEN = "open"


def fault_targets() -> tuple[str, ...]:
    """The transports a fault can target: the interfaces registered with faults, as the
    registry says now (`all` means each of them)."""
    return tuple(sorted(name for name, line in REGISTRY.items() if line.faults))


#: What a sensor fault does to the twin's sensor (docs/twin.md).
SENSOR_KINDS = ("stuck", "noisy", "open")
#: The reading of an open-circuit RTD input: the overrange value 0x7FFF of a 0.1 °C
#: terminal (3276.7 °C), far outside any plausible machine temperature.
OPEN_CIRCUIT_C = 3276.7
#: Longest delay or overrun a fault may ask for, in ms (a minute).
MAX_MS = 60_000.0
OPS = ("any", "read", "write")
#: Faults active on one machine at once: a test bench needs a handful; each is matched
#: against every request while transport faults are active, and each is listed in the
#: status the HMI receives every second.
MAX_FAULTS = 64
#: Longest fault text (characters); longer ones are refused before they are parsed.
MAX_TEXT = 256
#: Longest `objects=` pattern (characters): more than twice the longest object name or
#: alias (28), so every pattern that can match a name fits.
MAX_PATTERN = 64


#: A request delayed by a fault looks this often (s) whether the fault was cleared.
_DELAY_SLICE = 0.05


R = TypeVar("R")


def carry_out(
    fault: Fault,
    *,
    drop: Callable[[], R],
    error: Callable[[int], R],
    disconnect: Callable[[], R],
    delay: Callable[[], R],
) -> R:
    """The one dispatch on what a transport fault does to the request it hit
    (docs/faults.md), shared by every transport: each passes what each kind means in its
    protocol (`error` gets the code to answer with; `delay` serves the request after
    `fault.delay()`)."""
    match fault.kind:
        case FaultKind.DROP:
            return drop()
        case FaultKind.ERROR:
            return error(int(fault.value))
        case FaultKind.DISCONNECT:
            return disconnect()
        case FaultKind.DELAY:
            return delay()
    raise FaultError(f"fault {fault.text!r}: {fault.kind} is not a transport fault")


def _match_all(name: str) -> bool:
    return True


class FaultError(GeoError, ValueError):
    """A fault text that cannot be used; the message names the part and what fits."""


@dataclass
class Fault:
    """One injected fault (see the module docstring for the text form)."""

    target: str  # ads | modbus | zenoh | all | cycle | sensor
    kind: str
    value: float = 0.0  # ms (delay, overrun), error code, σ in °C (noisy)
    ops: str = "any"
    objects: str = "*"
    count: int = 0  # requests (or overruns) left to hit; 0: until cleared
    probability: float = 1.0
    every: int = 1  # overrun: cycles from one overrun to the next
    sensor: str = ""  # sensor@<axis number, axis name or sensor name>
    seed: int | None = None
    text: str = ""
    ident: int = 0
    hits: int = 0
    _rng: random.Random = field(default_factory=random.Random, repr=False, compare=False)
    #: `objects` compiled once when parsed (`_option`): no per-request compilation and
    #: no global cache keeping it after the fault is cleared
    _matches: Callable[[str], bool] = field(default=_match_all, repr=False, compare=False)
    #: set by `Faults.remove`: a delay under way ends (`delay`)
    cleared: bool = field(default=False, repr=False, compare=False)

    def transports(self) -> tuple[str, ...]:
        if self.target == "all":
            return fault_targets()
        return (self.target,) if self.target in fault_targets() else ()

    def applies(self, transport: str, op: str, name: str) -> bool:
        """Does this fault concern a `op` request on object `name` over `transport`?"""
        if transport not in self.transports():
            return False
        if self.ops != "any" and op != self.ops:
            return False
        if self.objects != "*" and not (name and self._matches(name)):
            return False
        return self.kind in REGISTRY[transport].faults  # (`all`: where it can act)

    async def delay(self) -> None:
        """Wait out this delay fault's `value` ms — less when it is cleared meanwhile:
        clearing a fault ends its effect at once (within `_DELAY_SLICE`)."""
        loop = asyncio.get_running_loop()
        end = loop.time() + self.value / 1000
        while not self.cleared:
            left = end - loop.time()
            if left <= 0:
                return
            await asyncio.sleep(min(left, _DELAY_SLICE))

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.ident,
            "fault": self.text,
            "target": self.target,
            "kind": self.kind,
            "hits": self.hits,
        }
        if self.kind == "error":
            out["code"] = int(self.value)
        elif self.kind in ("delay", "overrun"):
            out["ms"] = self.value
        elif self.kind == "noisy":
            out["sigma_C"] = self.value
        if self.count:
            out["left"] = self.count
        return out


# ---------------------------------------------------------------------- parsing


def parse_fault(text: str) -> Fault:
    """The `Fault` a line of text describes (module docstring); `FaultError` says what
    is wrong with it — whatever the text, nothing else is raised."""
    if not isinstance(text, str):
        raise FaultError(f"a fault is a line of text, not {type(text).__name__}")
    text = text.strip()
    if len(text) > MAX_TEXT:
        raise FaultError(
            f"fault {text[:40]!r}…: {len(text)} characters, at most {MAX_TEXT} (docs/faults.md)"
        )
    try:
        return _parse(text)
    except FaultError:
        raise
    except (ValueError, OverflowError, TypeError) as exc:  # a number no fault can have
        raise FaultError(f"fault {text!r}: {exc}") from None


def _parse(text: str) -> Fault:
    head, _, rest = text.partition(",")
    target, sep, action = head.partition(":")
    if not sep or not action:
        raise FaultError(f"fault {text!r}: expected <target>:<kind>[=value], e.g. ads:error=0x707")
    kind, _, value = action.partition("=")
    fault = Fault(target="", kind=kind.strip().lower(), text=text)
    _target(fault, target.strip())
    _value(fault, value.strip())
    for item in filter(None, (s.strip() for s in rest.split(","))):
        _option(fault, item)
    if fault.seed is not None:
        fault._rng = random.Random(fault.seed)
    return fault


def _target(fault: Fault, text: str) -> None:
    target = text.lower()
    if target.startswith("sensor@") and len(target) > 7:
        fault.target, fault.sensor = "sensor", text[7:]  # as written: a sensor's name
        kinds: tuple[str, ...] = SENSOR_KINDS
    elif target in fault_targets():
        fault.target = target
        kinds = REGISTRY[target].faults
    elif target == "all":
        fault.target = target
        kinds = FAULT_KINDS  # (what a transport fault does to a request it hits)
    elif target == "cycle":
        fault.target = target
        kinds = ("overrun",)
    else:
        raise FaultError(
            f"fault {fault.text!r}: unknown target {target!r} ({', '.join(fault_targets())}, "
            "all, cycle, sensor@<axis or sensor>)"
        )
    if fault.kind not in kinds:
        raise FaultError(
            f"fault {fault.text!r}: {target} has no fault {fault.kind!r} ({', '.join(kinds)})"
        )
    fault.kind = FaultKind(fault.kind)


def _number(fault: Fault, what: str, text: str) -> float:
    try:
        v = float(int(text, 0)) if text.lower().startswith("0x") else float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise FaultError(f"fault {fault.text!r}: {what} {text!r} is not a number")
    return v


def _value(fault: Fault, value: str) -> None:
    kind = fault.kind
    needs = {"delay": "ms", "error": "code", "overrun": "ms", "noisy": "σ in °C"}
    if kind not in needs:
        if value:
            raise FaultError(f"fault {fault.text!r}: {kind} takes no value")
        return
    if not value:
        raise FaultError(f"fault {fault.text!r}: {kind} needs a value ({needs[kind]})")
    v = _number(fault, needs[kind], value.removesuffix("ms"))
    if kind in ("delay", "overrun") and not 0 < v <= MAX_MS:
        raise FaultError(f"fault {fault.text!r}: {kind} of {v:g} ms outside 0 … {MAX_MS:g}")
    if kind == "noisy" and not 0 < v <= 100:
        raise FaultError(f"fault {fault.text!r}: noise σ {v:g} °C outside 0 … 100")
    if kind == "error":
        if v != int(v):
            raise FaultError(f"fault {fault.text!r}: code {value!r} is not a whole number")
        _check_code(fault, int(v))
    fault.value = v


def _check_code(fault: Fault, code: int) -> None:
    """ADS return codes for every transport (and `all`, where Modbus answers the
    exception the server gives that code); an interface's own codes (Modbus exceptions,
    `Registered.codes`) for it alone."""
    line = REGISTRY.get(fault.target)
    if line is not None and line.codes is not None and code < 0x100:
        what, codes = line.codes
        if code not in codes:
            raise FaultError(
                f"fault {fault.text!r}: {what} {code} is not one a server answers "
                f"({', '.join(str(c) for c in codes)})"
            )
        return
    try:
        AdsErrorCode(code)
    except ValueError:
        raise FaultError(
            f"fault {fault.text!r}: 0x{code:X} is not an ADS return code "
            "(e.g. 0x707 not ready, 0x708 busy, 0x719 timeout)"
        ) from None


def _option(fault: Fault, item: str) -> None:
    key, sep, value = item.partition("=")
    key, value = key.strip().lower(), value.strip()
    if not sep or not value:
        raise FaultError(f"fault {fault.text!r}: option {item!r} needs a value (key=value)")
    transport = fault.target in (*fault_targets(), "all")
    if key == "ops" and transport:
        if value not in OPS:
            raise FaultError(f"fault {fault.text!r}: ops={value} (any, read, write)")
        fault.ops = value
    elif key == "objects" and transport:
        if fault.objects != "*":
            raise FaultError(f"fault {fault.text!r}: one objects= pattern per fault")
        if len(value) > MAX_PATTERN:
            raise FaultError(
                f"fault {fault.text!r}: objects= pattern of {len(value)} characters, at most "
                f"{MAX_PATTERN} (the longest object name has 28)"
            )
        fault.objects = value
        fault._matches = _compiled(value)
    elif key == "count" and fault.target != "sensor":
        fault.count = _positive(fault, key, value)
    elif key == "every" and fault.target == "cycle":
        fault.every = _positive(fault, key, value)
    elif key == "p" and transport:
        p = _number(fault, "probability", value)
        if not 0 < p <= 1:
            raise FaultError(f"fault {fault.text!r}: p={value} outside (0, 1]")
        fault.probability = p
    elif key == "seed" and transport:
        fault.seed = _positive(fault, key, value, zero=True)
    else:
        raise FaultError(f"fault {fault.text!r}: {fault.target} has no option {key!r}")


def _compiled(pattern: str) -> Callable[[str], bool]:
    """`pattern` (fnmatch, case-sensitive) as a matcher of its own: `fnmatch.fnmatchcase`
    would keep every pattern ever used in its module-wide cache."""
    match = re.compile(fnmatch.translate(pattern)).match
    return lambda name: match(name) is not None


def _positive(fault: Fault, key: str, value: str, zero: bool = False) -> int:
    try:
        n = int(value, 0)
    except ValueError:
        n = -1
    if n < (0 if zero else 1):
        least = 0 if zero else 1
        raise FaultError(f"fault {fault.text!r}: {key}={value} must be a whole number ≥ {least}")
    return n


# ---------------------------------------------------------------------- the registry


class Faults:
    """The faults active on one machine's server. `decide` is called by the transports
    for every request while any transport fault is active (`active` is a plain bool
    read: no lock, no cost when there are none)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._faults: list[Fault] = []
        self._next = 1
        self.active = False  # any transport fault
        self.cleared = 0

    def add(self, fault: Fault) -> Fault:
        """Register a parsed fault; returns it with its id. `FaultError` once
        `MAX_FAULTS` are active."""
        with self._lock:
            if len(self._faults) >= MAX_FAULTS:
                raise FaultError(
                    f"fault {fault.text!r}: {MAX_FAULTS} faults are active, the most a machine "
                    "takes; clear some first"
                )
            fault = replace(fault, ident=self._next)
            if fault.seed is not None:
                fault._rng = random.Random(fault.seed)
            self._next += 1
            self._faults.append(fault)
            self._update()
        return fault

    def remove(self, ident: int | None = None) -> list[Fault]:
        """Take away fault `ident` (None: all); returns those removed (empty: no such)."""
        with self._lock:
            gone = [f for f in self._faults if ident is None or f.ident == ident]
            for f in gone:
                f.cleared = True
            self._faults = [f for f in self._faults if f not in gone]
            self.cleared += len(gone)
            self._update()
        return gone

    def of(self, target: str) -> list[Fault]:
        with self._lock:
            return [f for f in self._faults if f.target == target]

    def _update(self) -> None:
        self.active = any(f.transports() for f in self._faults)

    def decide(self, transport: str, op: str, name: str = "") -> Fault | None:
        """The fault (if any) that hits this request: the first one registered that
        applies, passes its probability draw and has hits left. Counts the hit; a fault
        whose count is used up is removed."""
        with self._lock:
            for f in self._faults:
                if not f.applies(transport, op, name):
                    continue
                if f.probability < 1 and f._rng.random() >= f.probability:
                    continue
                f.hits += 1
                if f.count:
                    f.count -= 1
                    if not f.count:
                        self._faults.remove(f)
                        self._update()
                return f
        return None

    def hit(self, fault: Fault) -> bool:
        """Count one hit of a non-transport fault (an overrun); False once its count is
        used up (it is then removed)."""
        with self._lock:
            if fault not in self._faults:
                return False
            fault.hits += 1
            if fault.count:
                fault.count -= 1
                if not fault.count:
                    self._faults.remove(fault)
            return True

    def status(self) -> list[dict[str, Any]]:
        with self._lock:
            return [f.as_dict() for f in self._faults]

    def __len__(self) -> int:
        return len(self._faults)
