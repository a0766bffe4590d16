"""ASCII list files of the CNC (002/003 §1.3–1.4): tokenizer, loader, validation, writer.

Public API:

* `load_machine(startup) -> MachineConfig` — start-up list + every list it names, validated
  (docs/design.md §4); raises `ListFileError` only if the lists cannot be read at all;
* `parse_list(path) -> ParsedList` — tokenized entries with value spans;
* `default_startup_list() -> Path` — `lists/hochlauf.lis` of the default machine;
* `compare_max_points(old, new) -> list[Diagnostic]` — reload check (110638–110641);
* `rewrite_values(path, changes)` / `apply_changes(text, changes)` — token writer for `save`;
* `remove_orphan_temps(paths) -> list[Path]` — delete the temporary files a killed `save`
  left next to these lists;
* `NotAListFileError` (an OSError) — a file that is no regular text list file;
  `MAX_LIST_BYTES` — the largest list file read;
* `checks_markdown() -> str` — the check → error-ID table (`docs/list_checks.md`).
"""

from __future__ import annotations

from geo_server.listfile.checks import CHECKS, EMU_TEMP_ERROR, Check, checks_markdown
from geo_server.listfile.loader import ListFileError, compare_max_points, load_machine
from geo_server.listfile.syntax import (
    MAX_LIST_BYTES,
    Entry,
    NotAListFileError,
    ParsedList,
    parse_list,
    parse_text,
)
from geo_server.listfile.writer import apply_changes, remove_orphan_temps, rewrite_values
from geo_server.paths import default_startup_list

__all__ = [
    "CHECKS",
    "EMU_TEMP_ERROR",
    "MAX_LIST_BYTES",
    "Check",
    "Entry",
    "ListFileError",
    "NotAListFileError",
    "ParsedList",
    "apply_changes",
    "checks_markdown",
    "compare_max_points",
    "default_startup_list",
    "load_machine",
    "parse_list",
    "parse_text",
    "remove_orphan_temps",
    "rewrite_values",
]
