"""asyncua's internals, confined (geo_server/transports/opcua/internals.py; docs/design.md
§9.1): every asyncua function the OPC UA interface and its guard hook, subclass, copy or
re-implement is the one its hash was taken from, and only internals.py and guard.py reach
asyncua's internal server."""

from __future__ import annotations

import ast
from pathlib import Path

import asyncua
import pytest

from geo_server.transports.opcua import internals

OPCUA = Path(internals.__file__).parent
#: asyncua's internal server and what hangs off it: reached only in these two modules
INTERNAL_NAMES = frozenset(
    {"iserver", "aspace", "isession", "subscription_service", "monitored_item_srv",
     "_monitored_items", "_monitored_datachange", "_nodes", "node_mgt_service",
     "attribute_service", "method_service", "datachange_callbacks", "isub"}
)  # fmt: skip
CONFINED = {"internals.py", "guard.py"}


def test_the_asyncua_installed_is_the_one_read() -> None:
    assert asyncua.__version__ == internals.ASYNCUA


@pytest.mark.parametrize("where", sorted(internals.RELIED_ON))
def test_every_asyncua_function_relied_on_is_unchanged(where: str) -> None:
    """An asyncua whose function changed (or moved) fails here: look at its use again
    (the modules named beside it in `RELIED_ON`), then take the new hash."""
    assert internals.source_hash(where) == internals.RELIED_ON[where], where


def test_a_changed_function_is_seen(monkeypatch: pytest.MonkeyPatch) -> None:
    where = "asyncua.server.server:Server.start"
    monkeypatch.setitem(internals.RELIED_ON, where, "0" * 64)
    monkeypatch.setitem(internals.RELIED_ON, "asyncua.server.server:Server.gone", "1" * 64)
    assert internals.changed() == [where, "asyncua.server.server:Server.gone"]


def internal_uses(source: str) -> list[str]:
    """Attribute accesses (`x.iserver`) of asyncua's internal names in `source`."""
    return [
        f"line {node.lineno}: .{node.attr}"
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Attribute) and node.attr in INTERNAL_NAMES
    ]


def test_only_internals_and_the_guard_reach_asyncuas_internal_server() -> None:
    bad = [
        f"{path.name}: {use}"
        for path in sorted(OPCUA.glob("*.py"))
        if path.name not in CONFINED
        for use in internal_uses(path.read_text(encoding="utf-8"))
    ]
    assert bad == []


def test_the_confinement_check_sees_a_reach() -> None:
    source = "a = self.server.iserver.aspace\nn = sub.monitored_item_srv._monitored_items\n"
    assert len(internal_uses(source)) == 4


def test_the_interface_module_imports_no_asyncua() -> None:
    """The OPC UA plug reads the options class from server.py when planning a start;
    asyncua (most of a second) is imported later, off the loop (`OpcUa.prepare`)."""
    import subprocess
    import sys

    code = (
        "import sys\nimport geo_server.transports.opcua.server\nprint('asyncua' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "False", out.stderr
