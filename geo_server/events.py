"""Warnings and errors a running machine reports (list validation, NC program,
monitoring, the server itself), as every interface hands them out."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from geo_server.model import COMP_NAMES, Diagnostic


@dataclass(frozen=True)
class Event:
    """A warning or error, stamped with the GEO cycle in which it was reported."""

    cycle: int
    diagnostic: Diagnostic

    def as_dict(self) -> dict[str, Any]:
        d = self.diagnostic
        return {
            "cycle": self.cycle,
            "severity": d.severity,
            "error_id": d.error_id,
            "message": d.message,
            "file": d.file,
            "line": d.line,
            "entry": d.entry,
            "axis": d.axis,
            "deactivated": COMP_NAMES[d.deactivated] if d.deactivated is not None else None,
        }
