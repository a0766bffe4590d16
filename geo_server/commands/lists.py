"""The list commands of one machine (docs/design.md §4.4, §4.5, §6.9): `reload`, `save`
and `volcomp_update`, one at a time (`ports.CommandLock`), by name for the command
objects (`SIM::reload`, `SIM::save`, `VOLC::file`) and the interfaces' command calls."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from geo_server.commands.ports import CommandLock, CommandResult, Ports
from geo_server.commands.reload import reload_lists
from geo_server.commands.save import save_lists
from geo_server.commands.volumetric import update_volumetric
from geo_server.errors import AdsError, AdsErrorCode


class CommandService:
    """`reload`, `save`, `volcomp_update` of one machine; each blocks on list files, so
    an event loop calls them through `run_applied` (a worker thread)."""

    def __init__(self, ports: Ports) -> None:
        self._ports = ports
        #: one list command at a time (0x708 after `command_wait`)
        self.lock = CommandLock(ports)

    def reload(self, startup: Path | str | None = None) -> CommandResult:
        """Reload the lists (`commands.reload`): validate everything first, swap at a
        cycle boundary or reject with the machine unchanged (recorded in `errors()`)."""
        return self.lock.run("reload", lambda: reload_lists(self._ports, startup))

    def save(self) -> CommandResult:
        """Write the live TEMPC parameters back into the axis lists (`commands.save`)."""
        return self.lock.run("save", lambda: save_lists(self._ports))

    def volcomp_update(self, file_name: str) -> CommandResult:
        """cnc_interpr_vol_comp_file_w (`commands.volumetric`, 004 p.23)."""
        return self.lock.run(
            "volcomp_update", lambda: update_volumetric(self._ports, file_name), detail=True
        )

    def run(self, name: str, value: Any = None) -> CommandResult:
        """Run `reload`, `save` or `volcomp_update` (`value`: its file name) in the
        caller's thread; another name is 0x701."""
        if name == "reload":
            return self.reload()
        if name == "save":
            return self.save()
        if name == "volcomp_update":
            return self.volcomp_update(str(value))
        raise AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"unknown command {name!r}")

    async def run_applied(self, name: str, value: Any = None) -> CommandResult:
        """`run` in a worker thread (never on the event loop); returns when it is done."""
        return await asyncio.to_thread(self.run, name, value)
