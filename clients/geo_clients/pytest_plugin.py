"""pytest plugin: fixtures that start a stepped geo-server on free ports (docs/design.md §10).

Enable it with `-p geo_clients.pytest_plugin`, with `pytest_plugins = ["geo_clients.pytest_plugin"]`
in a `conftest.py` / test module, or through the `pytest11` entry point of the installed
package. Fixtures:

- `geo_server` — a `geo_clients.testing.GeoTestServer`: the machine in stepped mode (every
  axis homed unless the marker says otherwise) with Zenoh / Modbus / ADS started on
  demand on 127.0.0.1 ephemeral ports, closed after the test. Control: `step(n)`,
  `move(axis, pos)`, `home(axis)`, `nc(text)`, `run_until(pred)`.
- `geo_via` — the transport the `geo` fixture uses: `service` (in-process, the default),
  `zenoh`, `modbus` or `ads`. Choose per run with `--geo-via zenoh`, per test with
  `@pytest.mark.parametrize("geo_via", ["zenoh", "modbus", "ads"])`.
- `geo_server_factory` — `geo_server_factory(startup=None, homed=False, ...)` makes more
  servers (other machines, options chosen inside the test); all closed after the test.
- `geo_golden` — `geo_golden(trace, "golden/x.csv", ["TEMPC::*=0.5"])`: hold a recorded
  trace (`geo_server.record(...)`, docs/recorder.md) to a golden one beside the test file;
  `--geo-update-golden` rewrites the golden files.
- `geo` — `geo_server.via(geo_via)`: `read(name, axis)`, `write(name, axis, value)`,
  `read_address(group, offset)`, `assert_value(name, axis, expected)`,
  `assert_raw(group, offset, expected)`, `expect_error(code, fn)`, and the machine
  control of the server.

Choose the machine with the marker
`@pytest.mark.geo_machine("path/to/hochlauf.lis", homed=False, cycle_ms=2, machine_name="m")`
(all arguments optional; no path = the default machine; a relative path is relative to
the folder of the test file, so a suite finds its machine wherever pytest runs from) or
for a whole run with `--geo-startup PATH` (relative to the directory pytest was started
in). A path that does not exist fails the test with a message that says how to make one
(`geo-server init DIR`). The marker is registered when the plugin loads at start-up (`-p`,
entry point); a module that enables the plugin itself with `pytest_plugins` should use
`geo_server_factory` instead (its marks are evaluated before the plugin is loaded).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from geo_clients.testing import VIAS, GeoTestServer, GeoView, check_golden
from geo_server.recorder import Comparison, Trace


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("geo-server")
    group.addoption(
        "--geo-via",
        choices=VIAS,
        default="service",
        help="transport of the `geo` fixture (default: service, in-process)",
    )
    group.addoption(
        "--geo-update-golden",
        action="store_true",
        help="geo_golden writes the traces as the new golden ones instead of comparing",
    )
    group.addoption(
        "--geo-startup",
        default=None,
        metavar="PATH",
        help="start-up list of the machine under test (default: the default machine)",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "geo_machine(startup=None, *, homed=True, cycle_ms=1.0, machine_name='test'): "
        "the machine the geo_server fixture starts",
    )


@pytest.fixture
def geo_server(request: pytest.FixtureRequest) -> Iterator[GeoTestServer]:
    """A stepped geo-server for one test (see `geo_clients.testing.GeoTestServer`)."""
    marker = request.node.get_closest_marker("geo_machine")
    args: tuple[Any, ...] = marker.args if marker else ()
    kwargs: dict[str, Any] = dict(marker.kwargs) if marker else {}
    startup = args[0] if args else kwargs.pop("startup", None)
    if startup is not None:
        startup = Path(request.node.path).parent / startup  # an absolute path stays
    else:
        option = request.config.getoption("--geo-startup", default=None)
        startup = Path(request.config.invocation_params.dir) / option if option else None
    if startup is not None and not Path(startup).is_file():
        pytest.fail(
            f"geo_machine: no start-up list {startup}; copy the default machine there with "
            f"`geo-server init {Path(startup).parent}` (or give the path to your own lists)",
            pytrace=False,
        )
    srv = GeoTestServer(startup, **kwargs)
    try:
        yield srv
    finally:
        srv.close()


@pytest.fixture
def geo_server_factory() -> Iterator[Callable[..., GeoTestServer]]:
    """`geo_server_factory(startup=None, homed=True, ...)` -> a new `GeoTestServer`; all of
    them are closed after the test (several machines, or options chosen in the test)."""
    servers: list[GeoTestServer] = []

    def make(startup: str | Path | None = None, **options: Any) -> GeoTestServer:
        srv = GeoTestServer(startup, **options)
        servers.append(srv)
        return srv

    try:
        yield make
    finally:
        for srv in reversed(servers):
            srv.close()


@pytest.fixture
def geo_golden(request: pytest.FixtureRequest) -> Callable[..., Comparison | None]:
    """`geo_golden(trace, "golden/warmup.csv", ["TEMPC::*=0.5"])`: hold a recorded trace
    to a golden one (relative paths: beside the test file); `--geo-update-golden` writes
    the new ones (`geo_clients.testing.check_golden`)."""
    update = bool(request.config.getoption("--geo-update-golden", default=False))
    here = Path(request.node.path).parent

    def check(trace: Trace, path: str | Path, tolerances: Any = (), **kw: Any) -> Any:
        return check_golden(trace, here / path, tolerances, update=update, **kw)

    return check


@pytest.fixture
def geo_via(request: pytest.FixtureRequest) -> str:
    """The transport of `geo` (`--geo-via`, or parametrize `geo_via`)."""
    return str(request.config.getoption("--geo-via", default="service"))


@pytest.fixture
def geo(geo_server: GeoTestServer, geo_via: str) -> GeoView:
    """Reads, writes and assertions over the chosen transport, machine control included."""
    if geo_via == "ads":
        pytest.importorskip("pyads", reason="the ADS transport needs pyads")
    geo_server.start(geo_via)
    return geo_server.via(geo_via)


__all__ = ["geo", "geo_golden", "geo_server", "geo_server_factory", "geo_via"]
