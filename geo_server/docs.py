"""Generated README sections: tables come from the dictionary and the check table, never typed.

`python -m geo_server.docs` rewrites every `<!-- BEGIN name -->` … `<!-- END name -->`
block of README.md and the whole of `docs/list_checks.md`; `tests/test_docs.py` and
`tests/test_listfile_validation.py` fail when either is out of date.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path

from geo_server.dictionary import dictionary_markdown


def _checks() -> str:
    from geo_server.listfile.checks import checks_markdown

    return checks_markdown()


def _modbus() -> str:
    try:
        from geo_server.transports.modbus.regmap import modbus_map
    except ImportError:  # the Modbus interface is optional in this build
        return "(the Modbus interface is not part of this build)\n"
    return modbus_map("md")


SECTIONS: dict[str, Callable[[], str]] = {
    "objects": dictionary_markdown,
    "checks": _checks,
    "modbus-map": _modbus,
}

_BLOCK = re.compile(
    r"(<!-- BEGIN (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- END (?P=name) -->)", re.S
)


def render(text: str) -> str:
    """README text with every generated block replaced by its current content."""

    def repl(m: re.Match[str]) -> str:
        name = m.group("name")
        if name not in SECTIONS:
            return m.group(0)
        return m.group(1) + SECTIONS[name]() + m.group(4)

    return _BLOCK.sub(repl, text)


def main(argv: list[str] | None = None) -> int:
    root = Path(__file__).resolve().parent.parent
    path = Path(argv[0]) if argv else root / "README.md"
    _update(path, render(path.read_text(encoding="utf-8")))
    checks = root / "docs" / "list_checks.md"
    if not argv and checks.parent.is_dir():  # a source checkout, not an installed wheel
        _update(checks, _checks())
    return 0


def _update(path: Path, new: str) -> None:
    if not path.exists() or path.read_text(encoding="utf-8") != new:
        path.write_text(new, encoding="utf-8")
        print(f"updated {path}")


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
