"""The registry of interfaces (geo_server/interfaces.py) and the contract each keeps
(geo_server/transports/interface.py), docs/design.md §1.3: the composition root, the
command line, the fleet and the faults iterate the registry and name no interface; an
interface is one module plus one registry line (`example_interface`, the worked
example, is registered here with one line and served for real on 127.0.0.1)."""

from __future__ import annotations

import argparse
import ast
import asyncio
import importlib
import re
from pathlib import Path

import pytest

import geo_server
from geo_server.interfaces import FAULT_KINDS, REGISTRY, Registered
from geo_server.transports.interface import Interface, load

GEO = Path(geo_server.__file__).parent
#: The modules that must know interfaces only through the registry.
ROOTS = ("compose.py", "cli.py", "fleet.py", "faults.py")
#: Strings that look like an interface's yet are the fleet file's own (`Member`'s fields)
FLEET_FIELDS = ("modbus_port",)
#: Libraries a plug may import only when it serves (the parser is built for every command).
SERVING_LIBRARIES = ("zenoh", "aiohttp", "asyncua", "pymodbus", "cryptography")


def packages() -> dict[str, str]:
    """Each registered interface's package (its plug's), by name."""
    return {name: line.plug.rpartition(".")[0] for name, line in REGISTRY.items()}


def named_interfaces(source: str) -> list[str]:
    """Where `source` names an interface: an import from an interface's package, a
    string that is an interface's name, one of its options or one of its status entries
    (`opcua_share`: a plug reads those, `Interface.fleet_counts`)."""
    tree = ast.parse(source)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom | ast.Import):
            names = [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            names += [a.name for a in node.names]
            found += [
                f"line {node.lineno}: imports {n}"
                for n in names
                for package in packages().values()
                if n == package or n.startswith(package + ".")
            ]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if node.value in FLEET_FIELDS:
                continue
            for name in REGISTRY:
                if node.value == name or re.match(rf"--(no-)?{name}\b|{name}_\w", node.value):
                    found.append(f"line {node.lineno}: {node.value!r}")
    return found


def test_the_composition_root_names_no_interface() -> None:
    bad = [f"{m}: {use}" for m in ROOTS for use in named_interfaces((GEO / m).read_text())]
    assert bad == []


def test_the_check_sees_an_interface_named() -> None:
    source = (
        "from geo_server.transports.zenoh.server import ZenohInterface\n"
        "import geo_server.web.server\n"
        "caps['modbus'] = 4\n"
        "p.add_argument('--opcua-user')\n"
        "from geo_server.transports.share import LoopShare\n"  # (shared, not an interface)
        "items = st.get('opcua_items')\n"
    )
    assert len(named_interfaces(source)) == 5


@pytest.mark.parametrize("name", list(REGISTRY))
def test_every_registered_interface_keeps_the_contract(name: str) -> None:
    plug = load(name)
    assert isinstance(plug, Interface) and plug.name == name and plug.title
    assert set(REGISTRY[name].faults) <= set(FAULT_KINDS)
    # its options are its own: --NAME…, --no-NAME
    parser = argparse.ArgumentParser()
    plug.add_arguments(parser)
    options = [o for a in parser._actions for o in a.option_strings if o not in ("-h", "--help")]
    assert options and all(re.match(rf"--(no-)?{name}\b", o) for o in options), options
    # nothing heavy at import: its server's libraries only inside what serves
    module = importlib.import_module(REGISTRY[name].plug)
    tree = ast.parse(Path(module.__file__ or "").read_text(encoding="utf-8"))
    top = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    imported = [a.name for n in top if isinstance(n, ast.Import) for a in n.names]
    imported += [n.module or "" for n in top if isinstance(n, ast.ImportFrom)]
    assert not [m for m in imported if m.split(".")[0] in SERVING_LIBRARIES]
    assert not [m for m in imported if m.endswith((".server", ".options"))], imported


@pytest.fixture
def line_registered(monkeypatch: pytest.MonkeyPatch) -> None:
    """The worked example's one registry line."""
    monkeypatch.setitem(REGISTRY, "line", Registered("example_interface"))


def test_one_module_and_one_line_make_an_interface(line_registered, capsys) -> None:
    """Registered, `line` has its options, its connections planned, and `geo-server
    run`'s composition root starts it for a machine and closes it (values by hand:
    --cycle-ms 2 is 2000 µs; 7 cycles stepped)."""
    from geo_server.cli import build_parser
    from geo_server.compose import EngineOptions, Interfaces, build_machine, connection_caps
    from geo_server.listfile import load_machine
    from geo_server.paths import default_startup_list

    off = ["--no-zenoh", "--no-modbus", "--no-ads", "--no-opcua"]
    args = build_parser().parse_args(["run", *off, "--line-port", "0", "--cycle-ms", "2"])
    assert connection_caps(args) == {"line": 8}
    built = build_machine(load_machine(default_startup_list()), EngineOptions(cycle_ms=2.0))
    built.service.stepper().step(7)

    async def main() -> list[str]:
        interfaces = Interfaces.plan(args)
        try:
            await interfaces.start_machine(args, built.service)
            said = capsys.readouterr().out
            port = int(re.search(r"line: tcp://127\.0\.0\.1:(\d+)", said).group(1))
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"SIM::cycle_count\nSIM::cycle_time_us\nNOPE::nothing\n")
            answers = [(await reader.readline()).decode().strip() for _ in range(3)]
            writer.close()
            return answers
        finally:
            await interfaces.close()

    count, cycle, nope = asyncio.run(main())
    assert (count, cycle) == ("7", "2000")
    assert nope.startswith("error: ") and "NOPE::nothing" in nope


def test_the_example_is_on_the_command_line_once_registered(line_registered) -> None:
    from geo_server.cli import build_parser

    args = build_parser().parse_args(["run", "--no-line"])
    assert args.no_line and args.line_port == 5099


def test_a_command_that_serves_nothing_loads_no_server_library() -> None:
    """`geo-server objects` builds the parser with every plug's options, and loads none
    of the libraries the interfaces serve with (nor the compiler)."""
    import subprocess
    import sys

    heavy = (*SERVING_LIBRARIES, "numba")
    code = (
        "import contextlib, io, sys\n"
        "from geo_server.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    assert main(['objects', '--format', 'csv']) == 0\n"
        f"print(sorted(m for m in {heavy!r} if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
