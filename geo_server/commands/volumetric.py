"""`volcomp_update` (004 p.23, docs/design.md §6.9): read a VOLC list and its correction
files off the cycle; the cycle swaps the compensation in."""

from __future__ import annotations

from geo_server.commands.ports import ADSERR_DEVICE_SYNTAX, CommandResult, Ports
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.listfile.values import Reporter
from geo_server.machine.port import VolcUpdate
from geo_server.model import Diagnostic
from geo_server.volcomp.config import reload_compensation
from geo_server.volcomp.kernel import VOLC_ERROR


def update_volumetric(ports: Ports, file_name: str) -> CommandResult:
    """cnc_interpr_vol_comp_file_w: read the VOLC list `file_name` for the compensation
    whose ID was written to cnc_interpr_vol_comp_index_w (VOLC::index). A list or file
    with errors leaves the compensation as it was: 0x70D with the diagnostics."""
    machine = ports.machine
    ident = int(ports.snapshot().value(machine.dictionary.by_name("VOLC::index"), 0))
    diags: list[Diagnostic] = []
    new = reload_compensation(machine.cfg, ident, file_name, Reporter(diags))
    if new is None:
        return CommandResult(
            False,
            "volcomp_update",
            [f"vol_comp[{ident}] is not configured in the start-up list (004 p.12)"],
            code=AdsErrorCode.DEVICE_INVALIDDATA,
            error_id=VOLC_ERROR,
        )
    warnings = [d.describe() for d in diags if d.severity != "error"]
    if not new.available:
        return CommandResult(
            False,
            "volcomp_update",
            [d.describe() for d in diags if d.severity == "error"],
            warnings,
            code=ADSERR_DEVICE_SYNTAX,
            error_id=VOLC_ERROR,
        )
    try:
        ports.refuse_when_stalled()
        ports.settle_sync(ports.scheduler.submit(VolcUpdate(ident, new)), ports.limits.swap_timeout)
    except AdsError as exc:
        return CommandResult(False, "volcomp_update", errors=[exc.message], code=exc.code)
    return CommandResult(
        True, "volcomp_update", warnings=warnings, files=[new.path, *new.param_files]
    )
