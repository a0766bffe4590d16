"""The Zenoh key space of docs/design.md §7, as pure functions (no Zenoh session needed).

    cnc/<m>/ads/<port>/<ig>/<io>        raw ADS bytes (ig, io as lowercase 0x… hex)
    cnc/<m>/axis/<A>/<group>/<field>    GEO objects by name, JSON
    cnc/<m>/sim/axis/<A>/<field>        emulator axis objects, JSON
    cnc/<m>/sim/machine/<field>         emulator machine-wide objects, JSON
    cnc/<m>/com/<name>                  the COM task's objects (port 553), JSON
    cnc/<m>/nc                          execute NC lines (get with payload)
    cnc/<m>/cmd/reload, cmd/save        commands (get with payload)
    cnc/<m>/cmd/reset, cmd/measure      (measure: a JSON test plan, docs/twin.md)
    cnc/<m>/cmd/fault                   inject, clear, list faults (JSON, docs/faults.md)
    cnc/<m>/cmd/record                  start, stop a recording (JSON, docs/recorder.md)
    cnc/<m>/status, cnc/<m>/errors      JSON
    cnc/<m>/alive                       liveliness token

`<group>` and `<field>` come from the dictionary (`ObjectDef.key_group/key_field`), so no
key is typed twice.
"""

from __future__ import annotations

from dataclasses import dataclass

from geo_server.dictionary import (
    AMS_PORTS,
    ATTRIBUTES,
    GEO_AMS_PORT,
    GROUP_PORTS,
    GROUPS,
    TASK_GROUPS,
    Dictionary,
    ObjectDef,
)
from geo_server.errors import AdsError, AdsErrorCode

GEO_PORT = GEO_AMS_PORT


@dataclass(frozen=True)
class Route:
    """What a concrete key addresses."""

    #: "raw" | "named" | "nc" | "reload" | "save" | "reset" | "measure" | "fault" | "status"
    #: | "errors"
    kind: str
    obj: ObjectDef | None = None
    axis: int = 0
    index_group: int = 0
    index_offset: int = 0


class KeySpace:
    """Build and parse the keys of one machine."""

    def __init__(self, machine: str, dictionary: Dictionary, axes: tuple[int, ...]) -> None:
        self.machine = machine
        self.prefix = f"cnc/{machine}"
        self.dictionary = dictionary
        self.axes = axes
        self._named: dict[str, Route] = {}
        for obj in dictionary.objects:
            for axis in axes if obj.scope == "axis" else (0,):
                self._named[self.named_key(obj, axis)] = Route("named", obj, axis)
        self._fixed = {
            f"{self.prefix}/nc": Route("nc"),
            f"{self.prefix}/cmd/reload": Route("reload"),
            f"{self.prefix}/cmd/save": Route("save"),
            f"{self.prefix}/cmd/reset": Route("reset"),
            f"{self.prefix}/cmd/measure": Route("measure"),
            f"{self.prefix}/cmd/fault": Route("fault"),
            f"{self.prefix}/cmd/record": Route("record"),
            f"{self.prefix}/status": Route("status"),
            f"{self.prefix}/errors": Route("errors"),
        }

    # ------------------------------------------------------------------ building

    def raw_key(self, index_group: int, index_offset: int, port: int | None = None) -> str:
        """`…/ads/<port>/<ig>/<io>`; the port of the group's task unless given."""
        if port is None:
            port = next((GROUP_PORTS[g] for g, ig in GROUPS.items() if ig == index_group), GEO_PORT)
        return f"{self.prefix}/ads/{port}/0x{index_group:x}/0x{index_offset:x}"

    def named_key(self, obj: ObjectDef, axis: int) -> str:
        if obj.group == "com":  # the COM task's objects (004 p.19) by their own names
            return f"{self.prefix}/com/{obj.key_field}"
        if obj.group == "sim":
            if obj.scope == "machine":
                return f"{self.prefix}/sim/machine/{obj.key_field}"
            return f"{self.prefix}/sim/axis/{axis}/{obj.key_field}"
        return f"{self.prefix}/axis/{axis}/{obj.key_group}/{obj.key_field}"

    @property
    def alive_key(self) -> str:
        return f"{self.prefix}/alive"

    def named_routes(self) -> dict[str, Route]:
        """Every named key (GEO and emulator objects) of this machine."""
        return self._named

    def readable_keys(self) -> dict[str, Route]:
        """Every concrete key a wildcard `get` answers: named and raw value keys of the
        readable objects, status and errors.

        Write-only objects (access "w": the commands `SIM::reload`/`SIM::save`,
        `SIM::set_position`) are left out: a wildcard asks for values, and a write-only
        object has none to give (asked for by its own key, it is answered as the object
        service decides). Attribute groups are answered only when asked for by concrete
        key.
        """
        keys = {key: route for key, route in self._named.items() if _readable(route)}
        for route in self._named.values():
            if not _readable(route):
                continue
            assert route.obj is not None
            ig = route.obj.index_group
            io = route.obj.index_offset(route.axis)
            key = self.raw_key(ig, io, route.obj.ams_port)
            keys[key] = Route("raw", route.obj, route.axis, ig, io)
        keys[f"{self.prefix}/status"] = self._fixed[f"{self.prefix}/status"]
        keys[f"{self.prefix}/errors"] = self._fixed[f"{self.prefix}/errors"]
        return keys

    # ------------------------------------------------------------------ parsing

    def parse(self, key: str) -> Route:
        """Route of a concrete key; unknown keys raise `AdsError` (codes: docs/design.md §9)."""
        if key in self._named:
            return self._named[key]
        if key in self._fixed:
            return self._fixed[key]
        parts = key.split("/")
        if parts[:2] != ["cnc", self.machine]:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDGRP, f"not a key of this machine: {key}")
        rest = parts[2:]
        if len(rest) == 4 and rest[0] == "ads":
            return self._parse_raw(key, rest[1:])
        if rest[:1] == ["axis"] and len(rest) == 4:
            return self._unknown_named(key, rest[1])
        if rest[:2] == ["sim", "axis"] and len(rest) == 4:
            return self._unknown_named(key, rest[2])
        raise AdsError(AdsErrorCode.DEVICE_INVALIDOFFSET, f"unknown key {key}")

    def no_match(self, key_expr: str) -> AdsError:
        """The error for a wildcard key expression that matches none of our keys.

        docs/design.md §7: every get is answered, so a wildcard that matches nothing gets a
        `reply_err` instead of silence (the client would only see its timeout). The code
        follows the concrete-key cases where a concrete chunk already tells what is
        wrong: an unknown ADS port -> 0x6, an unknown index group -> 0x702, an
        unconfigured axis -> 0x703; anything else is an unknown object -> 0x703.
        """
        rest = key_expr.split("/")[2:]

        def concrete(i: int) -> str | None:
            chunk = rest[i] if i < len(rest) else None
            return None if chunk is None or "*" in chunk else chunk

        axis_chunk = None  # the axis number, when the key expression names one
        if rest[:1] == ["axis"]:
            axis_chunk = concrete(1)
        elif rest[:2] == ["sim", "axis"]:
            axis_chunk = concrete(2)
        if axis_chunk is not None and not (axis_chunk.isdigit() and int(axis_chunk) in self.axes):
            return AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET, f"axis {axis_chunk} is not configured"
            )
        if rest[:1] == ["ads"]:
            port, ig = concrete(1), concrete(2)
            if port is not None and port not in {str(p) for p in AMS_PORTS}:
                return AdsError(
                    AdsErrorCode.TARGET_PORT_NOT_FOUND,
                    f"no ADS port {port} (GEO is {GEO_PORT}, COM {AMS_PORTS[1]})",
                )
            if ig is not None:
                try:
                    group = int(ig, 16)
                except ValueError:
                    group = -1
                if group not in GROUPS.values() and not is_attribute_group(group):
                    return AdsError(AdsErrorCode.DEVICE_INVALIDGRP, f"unknown index group {ig}")
                if is_attribute_group(group):
                    return AdsError(
                        AdsErrorCode.DEVICE_INVALIDOFFSET,
                        f"attribute groups are answered by concrete key only: {key_expr}",
                    )
        return AdsError(AdsErrorCode.DEVICE_INVALIDOFFSET, f"no object matches {key_expr}")

    def _parse_raw(self, key: str, parts: list[str]) -> Route:
        try:
            port, ig, io = int(parts[0]), int(parts[1], 16), int(parts[2], 16)
        except ValueError:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET,
                f"raw key needs <port>/<0xgroup>/<0xoffset>: {key}",
            ) from None
        if port not in AMS_PORTS:
            raise AdsError(
                AdsErrorCode.TARGET_PORT_NOT_FOUND,
                f"no ADS port {port} (GEO is {GEO_PORT}, COM {AMS_PORTS[1]})",
            )
        obj, axis, _attr = self.dictionary.resolve(ig, io, self.axes, port)
        return Route("raw", obj, axis, ig, io)

    def _unknown_named(self, key: str, axis_text: str) -> Route:
        try:
            axis = int(axis_text)
        except ValueError:
            axis = -1
        if axis not in self.axes:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDOFFSET, f"axis {axis_text} is not configured")
        raise AdsError(AdsErrorCode.DEVICE_INVALIDOFFSET, f"no object at {key}")


def _readable(route: Route) -> bool:
    return route.obj is not None and route.obj.readable


def is_attribute_group(index_group: int) -> bool:
    return any(index_group - ig in ATTRIBUTES for ig in TASK_GROUPS.values())
