"""What docs/design.md says is or is not emulated, checked against the dictionary and the
list schema where a machine can check it (issue 32): a section must not call a task, an
object group or a list entry "not emulated" or "ignored" while the server serves it."""

from __future__ import annotations

import re
from pathlib import Path

from geo_server.dictionary import COM_AMS_PORT, load_dictionary
from geo_server.listfile.schema import ListKind, lookup

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _sections(text: str) -> dict[str, str]:
    """`### x.y Title` -> its text."""
    parts = re.split(r"^(#{2,3} .+)$", text, flags=re.M)
    return {parts[i].strip("# "): parts[i + 1] for i in range(1, len(parts) - 1, 2)}


def test_the_com_task_is_not_called_missing_while_its_objects_are_served():
    served = [o for o in load_dictionary().objects if o.ams_port == COM_AMS_PORT]
    assert served, "the dictionary serves the COM task's objects"
    design = (DOCS / "design.md").read_text(encoding="utf-8")
    stale = [
        title
        for title, body in _sections(design).items()
        if re.search(r"no COM task|COM task[^.]*not emulated", body, flags=re.I)
    ]
    assert stale == []


def test_volumetric_entries_are_not_called_ignored_while_the_schema_reads_them():
    assert lookup(ListKind.STUP, "vol_comp[].file_name") is not None
    design = (DOCS / "design.md").read_text(encoding="utf-8")
    stale = [
        title
        for title, body in _sections(design).items()
        if re.search(r"vol_comp\[i\]\.\*`? ignored", body)
        or re.search(r"Volumetric compensation\s+Not emulated", title + body)
    ]
    assert stale == []
    section = _sections(design)["6.9 Volumetric compensation"]
    assert "Not emulated" not in section
