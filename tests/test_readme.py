"""The README's examples, and those of the docs pages they moved to (`SOURCES`), run as a
user would run them, so they cannot drift.

- `console` blocks are transcripts: each `$ command` runs in a shell (the installed
  console scripts on PATH) and its output must match the lines after it; `…` in a line
  matches any text, a line that is only `…` any number of lines. `geo-server init DIR`
  runs as written; `geo-server run … &` is started by the test on free ports (the
  clients find them through `GEO_CLIENT_ZENOH/MODBUS/ADS`), and a block without one runs
  against a fresh copy of the default machine.
- `python` blocks run in a subprocess against one server; the ports of the text
  (7447, 5020, 48898) are replaced by the server's, and every `print(…)  # → value` must
  print that value. A block that defines tests runs with pytest, beside a
  `geo-server init mymachine`, from another directory.
- the `mbpoll` line runs when mbpoll is installed (`.ci/run` installs it).
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import free_port

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
#: The files whose fenced blocks run here: the README, and every docs page that holds
#: examples moved out of it (issue 48). Each of their `console`, `python`, `sh` (mbpoll)
#: and `js` blocks is run with the same checks, wherever it is.
SOURCES = [
    README,
    DOCS / "fleets.md",
    DOCS / "ads.md",
    DOCS / "opcua.md",
    DOCS / "recorder.md",
    DOCS / "twin.md",
    DOCS / "volumetric.md",
]
BIN = Path(sys.executable).parent
TIMEOUT = 60.0


@dataclass
class Block:
    lang: str
    text: str
    line: int
    source: str = "README.md"

    @property
    def id(self) -> str:
        return f"{self.source}:line{self.line}"


def blocks(path: Path = README) -> list[Block]:
    out: list[Block] = []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^```(\w*)\s*$", lines[i])
        if m:
            start = i
            body = []
            i += 1
            while not lines[i].startswith("```"):
                body.append(lines[i])
                i += 1
            out.append(Block(m.group(1), "\n".join(body) + "\n", start + 1, path.name))
        i += 1
    return out


def all_blocks() -> list[Block]:
    return [b for source in SOURCES for b in blocks(source)]


def env() -> dict[str, str]:
    e = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    e["PATH"] = f"{BIN}{os.pathsep}{e.get('PATH', '')}"
    return e


def _listens(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT).close()
    except OSError:
        return False
    return True


class Server:
    """`geo-server run` in a subprocess on free ports."""

    def __init__(self, startup: Path, args: list[str], cwd: Path) -> None:
        self.zport, self.mport, self.aport = free_port(), free_port(), free_port()
        self.oport = free_port()
        cmd = [
            str(BIN / "geo-server"),
            "run",
            str(startup),
            *args,
            "--zenoh-listen",
            f"tcp/127.0.0.1:{self.zport}",
            "--modbus-port",
            str(self.mport),
            "--ads-port",
            str(self.aport),
            "--opcua-endpoint",
            f"opc.tcp://127.0.0.1:{self.oport}",
            "--opcua-cert-dir",
            str(cwd / "opcua"),
        ]
        # stderr into a file, not a pipe: nobody reads a pipe while the server runs, and
        # a server blocked on a full pipe answers nothing
        self.log = cwd / "server.log"
        self._log = self.log.open("w", encoding="utf-8")
        self.proc = subprocess.Popen(
            cmd, cwd=cwd, env=env(), stdout=subprocess.DEVNULL, stderr=self._log, text=True
        )
        self.env = env() | {
            "GEO_CLIENT_ZENOH": f"tcp/127.0.0.1:{self.zport}",
            "GEO_CLIENT_MODBUS": f"127.0.0.1:{self.mport}",
            "GEO_CLIENT_ADS": f"127.0.0.1:{self.aport}",
        }
        deadline = time.monotonic() + TIMEOUT
        while True:  # ready once a client gets an answer over each interface
            ok = all(
                subprocess.run(
                    [str(BIN / "geo-client"), "--via", via, "read", "SIM::cycle_count"],
                    env=self.env,
                    capture_output=True,
                    timeout=TIMEOUT,
                ).returncode
                == 0
                for via in ("zenoh", "modbus", "ads")
            ) and _listens(self.oport)  # OPC UA starts in the background
            if ok:
                return
            assert self.proc.poll() is None, self.log.read_text(encoding="utf-8")
            assert time.monotonic() < deadline, "server not ready"
            time.sleep(0.2)

    def rewrite(self, text: str) -> str:
        return rewrite_ports(
            text, {7447: self.zport, 48898: self.aport, 5020: self.mport, 4840: self.oport}
        )

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()


def rewrite_ports(text: str, ports: dict[int, int]) -> str:
    """The README's default ports in `text` replaced by a test server's, in one pass over
    whole numbers: replacing one port after another rewrote a port just put in (Modbus
    on 24840 became "2" followed by the OPC UA port)."""
    pattern = r"\b(" + "|".join(str(p) for p in ports) + r")\b"
    return re.sub(pattern, lambda m: str(ports[int(m[1])]), text)


def test_a_port_put_in_is_not_rewritten_again() -> None:
    ports = {5020: 24840, 4840: 24529}
    assert rewrite_ports("-p 5020 and :4840/x", ports) == "-p 24840 and :24529/x"
    assert rewrite_ports("15020 50201", ports) == "15020 50201"


def matches(expected: list[str], got: list[str]) -> bool:
    """`…` alone: any lines; `…` in a line: any text."""
    if not expected:
        return not got
    head, rest = expected[0], expected[1:]
    if head.strip() == "…":
        return any(matches(rest, got[i:]) for i in range(len(got) + 1))
    if not got:
        return False
    pattern = ".*".join(re.escape(part) for part in head.split("…"))
    return re.fullmatch(pattern, got[0]) is not None and matches(rest, got[1:])


def transcript(text: str) -> list[tuple[str, list[str]]]:
    steps: list[tuple[str, list[str]]] = []
    for line in text.splitlines():
        if line.startswith("$ "):
            steps.append((line[2:], []))
        elif steps:
            steps[-1][1].append(line)
    return steps


CONSOLE = [b for b in all_blocks() if b.lang == "console"]


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("block", CONSOLE, ids=[b.id for b in CONSOLE])
def test_console_transcripts(block: Block, tmp_path: Path) -> None:
    steps = transcript(block.text)
    assert steps, "a console block without commands"
    server: Server | None = None
    try:
        for command, expected in steps:
            run = re.match(r"geo-server run (\S+)(.*)&$", command)
            if run:
                server = Server(tmp_path / run.group(1), run.group(2).split(), tmp_path)
                continue
            if server is None and command.startswith("geo-client"):
                fresh = tmp_path / "fresh"
                subprocess.run(
                    [str(BIN / "geo-server"), "init", str(fresh)],
                    check=True,
                    capture_output=True,
                    env=env(),
                )
                server = Server(fresh / "hochlauf.lis", ["--homed"], tmp_path)
            r = subprocess.run(
                command,
                shell=True,
                cwd=tmp_path,
                env=server.env if server else env(),
                capture_output=True,
                text=True,
                timeout=TIMEOUT,
            )
            got = r.stdout.splitlines()
            assert r.returncode == 0, f"$ {command}\n{r.stdout}{r.stderr}"
            assert matches(expected, got), f"$ {command}\nexpected {expected}\ngot {got}"
    finally:
        if server is not None:
            server.close()


PYTHON = [b for b in all_blocks() if b.lang == "python"]


@pytest.fixture(scope="module")
def shared_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("readme")
    subprocess.run(
        [str(BIN / "geo-server"), "init", str(folder / "m")],
        check=True,
        capture_output=True,
        env=env(),
    )
    srv = Server(folder / "m" / "hochlauf.lis", ["--homed"], folder)
    yield srv
    srv.close()


def expected_prints(text: str) -> list[str]:
    return [m.group(1) for m in re.finditer(r"print\(.*\)\s+# → (.*)$", text, re.M)]


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("block", PYTHON, ids=[b.id for b in PYTHON])
def test_python_examples(block: Block, shared_server: Server, tmp_path: Path) -> None:
    if "def test_" in block.text:
        return run_pytest_example(block, tmp_path)
    script = tmp_path / "example.py"
    script.write_text(shared_server.rewrite(block.text), encoding="utf-8")
    r = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        env=env(),
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    want = expected_prints(block.text)
    assert want, "a python example should show what it prints (`# → value`)"
    assert r.stdout.splitlines() == want
    if "quiet_adslib(pyads)" in block.text:  # what the README says it silences
        assert "connection closed by remote" not in r.stderr


def run_pytest_example(block: Block, tmp_path: Path) -> None:
    """The plugin example as a test file, its machine made beside it with `geo-server
    init`, pytest started from another directory (the marker's path is relative to the
    test file)."""
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "test_example.py").write_text(block.text, encoding="utf-8")
    subprocess.run(
        [str(BIN / "geo-server"), "init", "mymachine"],
        cwd=suite,
        check=True,
        capture_output=True,
        env=env(),
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(suite)],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        timeout=240,
        env=env(),
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "5 passed" in r.stdout, r.stdout


SH = [b for b in all_blocks() if b.lang == "sh" and b.text.startswith("mbpoll")]


@pytest.mark.parametrize("block", SH, ids=[b.id for b in SH])
def test_mbpoll_lines(block: Block, shared_server: Server) -> None:
    if shutil.which("mbpoll") is None:
        pytest.skip("mbpoll is not installed (Debian: apt-get install -y mbpoll)")
    for line in block.text.splitlines():
        command = shared_server.rewrite(line.split("  #", 1)[0])
        r = subprocess.run(command, shell=True, capture_output=True, text=True, timeout=TIMEOUT)
        assert r.returncode == 0, r.stdout + r.stderr
        assert re.search(r"\[264\]:\s+40\b", r.stdout), r.stdout  # TEMPC::actual_offset of X


JS = [b for b in all_blocks() if b.lang == "js"]
NODE = shutil.which("node")
NODE_DIR = README.parent / "tests" / "node"


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.skipif(
    os.environ.get("GEO_SERVER_REQUIRE_NODE") != "1"
    and (NODE is None or not (NODE_DIR / "node_modules" / "ads-client").is_dir()),
    reason="node or tests/node/node_modules missing (npm ci --prefix tests/node)",
)
@pytest.mark.parametrize("block", JS, ids=[b.id for b in JS])
def test_node_examples(block: Block, tmp_path: Path) -> None:
    """Issue 48 #3: each Node.js snippet as pasted into the file its first line names
    (an ES module), beside the project's Node clients (tests/node, whose node_modules
    it imports from), run with `node` against a server of its own; what it prints is
    what its `// → value` comments say."""
    assert NODE is not None
    fresh = tmp_path / "fresh"
    subprocess.run(
        [str(BIN / "geo-server"), "init", str(fresh)], check=True, capture_output=True, env=env()
    )
    server = Server(fresh / "hochlauf.lis", ["--homed"], tmp_path)
    name = re.match(r"// (\S+\.mjs) ", block.text)
    assert name, "a Node.js snippet names its file on its first line"
    script = NODE_DIR / f".readme-{os.getpid()}-{name.group(1)}"
    try:
        script.write_text(server.rewrite(block.text), encoding="utf-8")
        r = subprocess.run(
            [NODE, str(script)], capture_output=True, text=True, timeout=120, cwd=NODE_DIR
        )
    finally:
        script.unlink(missing_ok=True)
        server.close()
    assert r.returncode == 0, r.stdout + r.stderr
    want = [m for line in block.text.splitlines() for m in re.findall(r"// → (.+)$", line)]
    got = [ln for ln in r.stdout.splitlines() if not ln.startswith("[")]  # (client logs)
    assert got[: len(want)] == want, r.stdout


def test_the_readme_has_examples_of_each_kind() -> None:
    """The README keeps its own runnable examples (the tour, one per interface); the
    pages of `SOURCES` hold the rest, Node.js among them."""
    mine = blocks(README)
    assert len([b for b in mine if b.lang == "console"]) >= 2
    assert len([b for b in mine if b.lang == "python"]) >= 4
    assert [b for b in mine if b.lang == "sh" and b.text.startswith("mbpoll")]
    assert len(CONSOLE) >= 2 and len(PYTHON) >= 4 and SH and JS


def test_every_page_with_examples_is_a_source() -> None:
    """A docs page of `SOURCES` holds at least one block that runs here (else it need
    not be listed), and every page whose blocks the README's test would run is listed:
    a `console` or `python` block with `# →` outside `SOURCES` would go unchecked."""
    runnable = {"console", "python", "js"}
    for source in SOURCES[1:]:
        assert [b for b in blocks(source) if b.lang in runnable], source.name
    listed = {s.name for s in SOURCES}
    for page in sorted(DOCS.glob("*.md")):
        if page.name in listed:
            continue
        unlisted = [
            b.id
            for b in blocks(page)
            if b.lang == "console" or (b.lang == "python" and "# → " in b.text)
        ]
        assert not unlisted, f"{page.name}: examples the tests would not run: {unlisted}"
