"""Generated documentation never drifts from the code: the reference pages under docs/
and docs/limits.md are what `python -m geo_server.docs` writes."""

from __future__ import annotations

from pathlib import Path

import pytest

from geo_server.docs import PAGES, render

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def test_readme_generated_sections_are_current():
    text = README.read_text(encoding="utf-8")
    assert render(text) == text, "README out of date: run `python -m geo_server.docs`"


@pytest.mark.parametrize("name", sorted(PAGES))
def test_reference_pages_are_current(name):
    page = ROOT / "docs" / name
    assert page.read_text(encoding="utf-8") == PAGES[name](), (
        f"docs/{name} out of date: run `python -m geo_server.docs`"
    )


def test_readme_opens_with_the_two_commands():
    text = README.read_text(encoding="utf-8")
    head = text[: text.index("## ")]
    assert "geo-server run" in head
    assert "bash .ci/run" in head


def test_the_limits_table_shows_the_defaults():
    """A changed default shows up in docs/limits.md (here: the ADS connection cap)."""
    from geo_server.transports.ads.server import AdsOptions

    row = next(
        ln
        for ln in (ROOT / "docs" / "limits.md").read_text(encoding="utf-8").splitlines()
        if "AdsOptions.max_connections" in ln
    )
    assert f"| {AdsOptions().max_connections} |" in row


def test_the_symbol_page_lists_only_served_symbols():
    """docs/ads-symbols.md lists no symbol that no symbol service serves: every row's name
    is one the GEO task's symbol table of the default machine answers (axis X for
    `<axis>`), and the COM task's objects (port 553) are not among them."""
    import re

    from geo_server.dictionary import load_dictionary
    from geo_server.transports.ads.symbols import SymbolTable

    table = SymbolTable(load_dictionary(), {1: "X"})
    names = re.findall(r"^\| `([^`]+)` \|", (ROOT / "docs" / "ads-symbols.md").read_text(), re.M)
    assert names and not [n for n in names if n.startswith("GEO.COM.")]
    for name in names:
        table.lookup(name.replace("<axis>", "X"))  # raises for an unknown name


def test_the_docs_site_builds_with_every_link_resolved(tmp_path: Path) -> None:
    """Issue 48: docs/ is a site (mkdocs.yml, the Material theme); `mkdocs build
    --strict` fails on a link to a page or an anchor that does not exist, and on a page
    the site leaves out."""
    import os
    import subprocess
    import sys

    env = os.environ | {"NO_MKDOCS_2_WARNING": "1"}  # (the theme's notice, not ours)
    r = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "limits" / "index.html").is_file()
