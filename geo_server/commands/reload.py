"""`reload` (docs/design.md §4.4): validate every list first, swap at a cycle boundary
or reject with the machine unchanged."""

from __future__ import annotations

from pathlib import Path

from geo_server.commands.ports import ADSERR_DEVICE_SYNTAX, CommandResult, Ports
from geo_server.errors import AdsError
from geo_server.listfile import ListFileError, compare_max_points, load_machine
from geo_server.machine.port import Reload
from geo_server.model import Diagnostic, MachineConfig


def reload_lists(ports: Ports, startup: Path | str | None) -> CommandResult:
    """Load the lists from `startup` (None: the machine's own) and swap them in."""
    machine = ports.machine
    path = Path(startup) if startup else machine.cfg.startup_path
    try:  # the folders the user allowed at start stay allowed
        new = load_machine(path, machine.cfg.allow_dirs)
    except ListFileError as exc:
        earlier = [str(d) for d in exc.earlier]  # (the first cause first)
        return CommandResult(
            False, "reload", errors=[str(exc)], warnings=earlier, code=ADSERR_DEVICE_SYNTAX
        )
    problems = _rejecting(new) + compare_max_points(machine.cfg, new)
    if set(new.axes) != set(machine.cfg.axes):
        problems.append(
            Diagnostic(
                "error",
                f"the axes changed ({sorted(machine.cfg.axes)} -> "
                f"{sorted(new.axes)}); restart the server to change the machine layout",
            )
        )
    warnings = [str(d) for d in new.diagnostics if d not in problems]
    if problems:
        return CommandResult(
            False,
            "reload",
            [p.describe() for p in problems],
            warnings,
            code=ADSERR_DEVICE_SYNTAX,
            error_id=next((p.error_id for p in problems if p.error_id), 0),
        )
    try:
        ports.refuse_when_stalled()
        ports.settle_sync(ports.scheduler.submit(Reload(new)), ports.limits.swap_timeout)
    except AdsError as exc:
        return CommandResult(False, "reload", errors=[exc.message], code=exc.code)
    return CommandResult(True, "reload", warnings=warnings, files=new.list_files)


def _rejecting(cfg: MachineConfig) -> list[Diagnostic]:
    """Diagnostics that make a reload fail: errors and deactivated compensations."""
    return [d for d in cfg.diagnostics if d.severity == "error" or d.deactivated is not None]
