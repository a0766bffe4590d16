"""`save` (docs/design.md §4.5): write the live TEMPC parameters back into the axis
lists (an atomic rewrite of each changed entry); the shipped default machine is never
written."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from geo_server.commands.ports import CommandResult, Ports
from geo_server.dictionary import Dictionary, ObjectDef
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.listfile import ListFileError, rewrite_values
from geo_server.machine.port import Saved
from geo_server.model import AxisParams, MachineConfig, seal, with_axis_params
from geo_server.paths import is_product_data
from geo_server.snapshot import Snapshot


def save_lists(ports: Ports) -> CommandResult:
    """Rewrite each axis list whose saved parameters differ from the live values."""
    machine = ports.machine
    startup = machine.cfg.startup_path
    if is_product_data(startup):  # refused whatever changed: it is never saved
        return CommandResult(
            False, "save", errors=[_read_only_default(startup)], code=AdsErrorCode.DEVICE_ERROR
        )
    snap = ports.snapshot()
    files: list[str] = []
    errors: list[str] = []
    saved: dict[int, AxisParams] = {}
    for axis in machine.axes:
        params = machine.cfg.axes[axis].params
        changes = _changed_parameters(machine.dictionary, params, snap, axis)
        if not changes:
            continue
        if not params.path:
            errors.append(f"axis {axis}: no axis parameter list to save into")
            continue
        if is_product_data(params.path):
            errors.append(_read_only_default(params.path))
            continue
        try:
            rewrite_values(params.path, changes)
        except (OSError, ListFileError) as exc:
            errors.append(f"{params.path}: {exc}")
            continue
        saved[axis] = _as_saved(machine.dictionary, params, changes)
        files.append(params.path)
    if saved:
        try:  # the configuration as saved, swapped in whole at a cycle boundary
            ports.apply(Saved(_as_saved_config(machine.cfg, saved)))
        except AdsError as exc:
            errors.append(f"saved, but not yet taken as the stored values: {exc.message}")
    return CommandResult(
        not errors, "save", errors=errors, files=files, code=AdsErrorCode.DEVICE_ERROR
    )


def format_value(obj: ObjectDef, value: Any) -> str:
    """A value as a list-file token: integers plain, REAL64 shortest round-trip form."""
    if obj.type.name == "BOOLEAN":
        return "1" if value else "0"
    if obj.type.name == "REAL64":
        f = float(value)
        return str(int(f)) if f.is_integer() and abs(f) < 1e15 else repr(f)
    return str(round(value))


def _changed_parameters(
    dictionary: Dictionary, params: Any, snap: Snapshot, axis: int
) -> dict[str, str]:
    changes: dict[str, str] = {}
    for obj in dictionary.saved_parameters():  # objects with a `list_key`
        if obj.type.name == "BOOLEAN" and params.temp_comp_manual_activation:
            continue  # a manual-activation selection is not a list setting (000 §3.2)
        live = snap.value(obj, axis)
        stored = getattr(params, obj.param_attr or "")
        if format_value(obj, live) != format_value(obj, stored):
            changes[obj.list_key or ""] = format_value(obj, live)
    return changes


def _read_only_default(path: str | Path) -> str:
    """Why `save` does not write into `path`, a file of the shipped default machine
    (docs/design.md §4.5)."""
    return (
        f"{path} belongs to the default machine shipped with geo-server, which is read-only "
        "wherever it is installed; copy it with `geo-server init DIR` and run "
        "`geo-server run DIR/hochlauf.lis` to save"
    )


def _as_saved(dictionary: Dictionary, params: AxisParams, changes: dict[str, str]) -> AxisParams:
    """After a save, the lists hold the live values: `params` with them as the stored
    ones (a new, unsealed copy)."""
    attrs = {o.list_key: o.param_attr or "" for o in dictionary.saved_parameters()}
    stored: dict[str, Any] = {}
    for entry, text in changes.items():
        attr = attrs[entry]
        current = getattr(params, attr)
        stored[attr] = type(current)(float(text)) if not isinstance(current, bool) else text == "1"
    return replace(params, **stored)


def _as_saved_config(cfg: MachineConfig, saved: dict[int, AxisParams]) -> MachineConfig:
    """`cfg` with the saved axes' parameters, sealed (the other parts are shared)."""
    new = with_axis_params(cfg, saved)
    seal(new)
    return new
