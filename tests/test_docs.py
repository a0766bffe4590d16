"""The README's reference tables are generated, so they can never drift from the code."""

from __future__ import annotations

from pathlib import Path

from geo_server.docs import render

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_generated_sections_are_current():
    text = README.read_text(encoding="utf-8")
    assert "<!-- BEGIN objects -->" in text
    assert render(text) == text, "README out of date: run `python -m geo_server.docs`"


def test_readme_opens_with_the_two_commands():
    text = README.read_text(encoding="utf-8")
    head = text[: text.index("## ", text.index("## ") + 1)]
    assert "geo-server run" in head
    assert "bash .ci/run" in head
